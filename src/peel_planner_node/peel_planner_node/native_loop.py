"""The C++ model-step loop of the fused rollout (``csrc/rollout_loop.cpp``): built at setup,
only loaded while planning.

Why: at N = 50, H = 5 a plan makes ~1075 small torch calls, and the Python around each one
(~0.4 us) is ~10 % of the plan (docs/planner.md). The C++ loop makes the same ATen calls in the
same order on the same tensors, so its results are bit-identical to the Python loop
(``fused.run_steps``; ``test_planner_dynamics``); the GIL is released while it runs.

**The build belongs to the installation.** ``python -m peel_planner_node.native_loop`` (run by
``scripts/setup.sh``) compiles it with ``torch.utils.cpp_extension.load_inline`` (g++ and ninja,
~25-110 s) into :func:`build_dir`: a folder inside the Python environment (``sys.prefix``) when
that is writable, else ``~/.cache/peel/native/<hash of sys.prefix>``; either way named by the
Python and torch versions and a hash of the source and flags. Two clones (two venvs) never share
or rebuild each other's build, and an edited source gets a new folder. ``PEEL_NATIVE_LOOP_DIR``
moves the base folder.

**Planning never compiles.** :func:`load` only imports a finished build (its ``built`` stamp is
written after the compiler succeeded). When there is none, or ``PEEL_NATIVE_LOOP=0`` is set, the
Python loop runs at once (same results, ~18 % slower at N = 50), a warning is logged once and
:func:`status` says why.

Builds are serialised with an OS file lock (``fcntl.flock``, released when a process dies).
torch's own lock is a plain file that a killed build leaves behind, after which every later
build waits for it forever; while holding ours, a torch lock file in the folder can only be
such a leftover, and it is removed.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import shutil
import sys
import threading
from pathlib import Path
from typing import Any

import torch

from peel_msgs_py.errors import PeelError

_LOG = logging.getLogger(__name__)
_SOURCE = Path(__file__).with_name("csrc") / "rollout_loop.cpp"
_NAME = "peel_rollout_loop"
_CFLAGS = ("-O2",)
_LOCK = threading.Lock()
_STATE: dict[str, Any] = {"module": None, "tried": False, "reason": "not loaded yet"}


# ---------------------------------------------------------------- where the build lives
def build_key() -> str:
    """Python and torch versions and a hash of the source and compiler flags."""
    digest = hashlib.sha256(_SOURCE.read_bytes() + " ".join(_CFLAGS).encode()).hexdigest()[:12]
    tag = f"py{sys.version_info[0]}{sys.version_info[1]}_torch{torch.__version__}"
    return f"{tag.replace('+', '_').replace('.', '_')}_{digest}"


def install_base(prefix: str | None = None) -> Path:
    """The installation's folder for native builds: ``<sys.prefix>/peel_native`` when the
    environment is writable (a venv), else a per-user cache keyed by the prefix's path."""
    env = os.environ.get("PEEL_NATIVE_LOOP_DIR")
    if env:
        return Path(env)
    prefix = prefix if prefix is not None else sys.prefix
    if os.access(prefix, os.W_OK):
        return Path(prefix) / "peel_native"
    key = hashlib.sha256(str(Path(prefix).resolve()).encode()).hexdigest()[:12]
    return Path.home() / ".cache" / "peel" / "native" / key


def build_dir(prefix: str | None = None) -> Path:
    """Folder of this installation's build of this source (module docstring)."""
    return install_base(prefix) / f"rollout_loop_{build_key()}"


# ---------------------------------------------------------------- build (setup time)
def toolchain_missing() -> str | None:
    """What is missing to build the loop (a C++ compiler, ninja), or None when both are there."""
    _ninja_on_path()
    compiler = os.environ.get("CXX", "c++")
    if shutil.which(compiler) is None:
        return f"no C++ compiler ({compiler!r} not on PATH)"
    if shutil.which("ninja") is None:
        return "no ninja on PATH"
    return None


def _ninja_on_path() -> None:
    """torch looks for ``ninja`` on PATH; a venv's own bin directory may not be on it."""
    if shutil.which("ninja") is None:
        bindir = str(Path(sys.executable).parent)
        if shutil.which("ninja", path=bindir) is not None:
            os.environ["PATH"] = bindir + os.pathsep + os.environ.get("PATH", "")


def is_built() -> bool:
    """True when this installation holds a finished build of this source."""
    folder = build_dir()
    return (folder / "built").is_file() and (folder / f"{_NAME}.so").is_file()


def build() -> Path:
    """Compile the loop into :func:`build_dir` (waits for another process's build of it) and
    load it; returns the folder. Raises PeelError without a toolchain or when the compiler
    fails."""
    missing = toolchain_missing()
    if missing is not None:
        raise PeelError(f"cannot build the C++ rollout loop: {missing}")
    from torch.utils.cpp_extension import load_inline

    folder = build_dir()
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "peel.lock", "w") as lock:
        try:
            import fcntl

            fcntl.flock(lock, fcntl.LOCK_EX)  # waits for another process's build
        except ImportError:  # pragma: no cover - not POSIX: torch's own lock only
            pass
        stale = folder / "lock"  # torch's FileBaton file: left by a killed build
        if stale.exists():
            stale.unlink()
        try:
            module = load_inline(name=_NAME, cpp_sources=[_SOURCE.read_text()], functions=None,
                        extra_cflags=list(_CFLAGS), verbose=False, build_directory=str(folder))
        except Exception as exc:  # compiler errors, missing headers
            raise PeelError(f"C++ rollout loop build failed: {type(exc).__name__}: "
                            f"{str(exc).strip().splitlines()[-1:]}") from exc
        (folder / "built").write_text(build_key() + "\n")
    with _LOCK:  # the module load_inline imported (a second import of it would fail)
        _STATE.update(tried=True, module=module, reason=f"built in {folder}")
    return folder


# ---------------------------------------------------------------- load (planning time)
def load() -> Any | None:
    """The built module (with ``RolloutLoop``), or None: disabled, or not built for this
    installation (never compiles; see the module docstring)."""
    if os.environ.get("PEEL_NATIVE_LOOP", "1") == "0":
        _STATE["reason"] = "disabled by PEEL_NATIVE_LOOP=0"
        return None
    with _LOCK:
        if _STATE["tried"]:
            return _STATE["module"]
        _STATE["tried"] = True
        folder = build_dir()
        library = folder / f"{_NAME}.so"
        if not is_built():
            _STATE["reason"] = (f"not built for this installation (no {folder}); build it with "
                                "`python -m peel_planner_node.native_loop` (scripts/setup.sh "
                                "does)")
        else:
            try:
                spec = importlib.util.spec_from_file_location(_NAME, library)
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
                _STATE.update(module=module, reason=f"loaded from {folder}")
            except Exception as exc:  # a broken or foreign build: the Python loop runs
                _STATE["reason"] = f"cannot load {library}: {type(exc).__name__}: {exc}"
        if _STATE["module"] is None:
            _LOG.warning("peel: C++ rollout loop unavailable (%s); using the Python loop",
                         _STATE["reason"])
    return _STATE["module"]


def status() -> dict[str, Any]:
    """{'native': bool, 'reason': str} of the last :func:`load`."""
    return {"native": _STATE["module"] is not None, "reason": _STATE["reason"]}


def bind(ws: Any, w: Any) -> Any | None:
    """The C++ loop bound to a workspace's tensors by name (None: the Python loop runs)."""
    module = load()
    if module is None:
        return None
    sh = ws.shared
    named = {name: t for name, t in sh._asdict().items() if isinstance(t, torch.Tensor)}
    named.update({name: getattr(w, name) for name in (
        "conv_wave", "conv_wave_bias", "att1_weight_t", "att1_bias", "att2_weight_t",
        "att2_bias", "scale_expand", "wx_gates_aug", "wh_gates", "fc1_h_t")})
    named.update(fc1_out=sh.fc_out[0], head_in=sh.fc_in[-1], head_weight=w.fc_layers[-1])
    layers = [{"act": y, "weight": weight, "out": out} for y, weight, out in
              zip(sh.fc_in[:-1], w.fc_layers[:-1], sh.fc_out[1:], strict=True)]

    def tensors(record: Any) -> dict[str, torch.Tensor]:
        return {k: v for k, v in record._asdict().items() if isinstance(v, torch.Tensor)}

    return module.RolloutLoop(named, layers, [tensors(s) for s in ws.steps],
                              [[tensors(c) for c in s.cells] for s in ws.steps],
                              bool(w.att_shift))


def main() -> int:
    """``python -m peel_planner_node.native_loop``: build this installation's loop unless it
    is already built, then print the status (exit 0 either way: the Python loop is the
    fallback)."""
    import time

    t0 = time.perf_counter()
    if os.environ.get("PEEL_NATIVE_LOOP", "1") == "0" or is_built():
        load()
    else:
        try:
            build()
        except PeelError as exc:
            _STATE["reason"] = str(exc)
    print(f"setup: planner C++ rollout loop: {status()['reason']} "
          f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
