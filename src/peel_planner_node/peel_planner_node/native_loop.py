"""The C++ model-step loop of the fused rollout (``csrc/rollout_loop.cpp``), built on first use.

Why: at N = 50, H = 5 a plan makes ~1075 small torch calls, and the Python around each one
(~0.4 us) is ~10 % of the plan (docs/planner.md, third round). The C++ loop makes the same
ATen calls in the same order on the same tensors, so its results are bit-identical to the
Python loop (``test_planner_dynamics``); the GIL is released while it runs.

It is compiled with ``torch.utils.cpp_extension.load_inline`` (g++ and ninja; ~25 s the first
time, then cached under torch's extension directory, ``TORCH_EXTENSIONS_DIR`` to move it, in a
folder per Python and torch version). When it cannot be built, or ``PEEL_NATIVE_LOOP=0`` is set,
the Python loop is used; :func:`status` says which and why.

Builds are serialised with an OS file lock (``fcntl.flock``, released when a process dies).
torch's own lock is a plain file that a killed build leaves behind, after which every later
build waits for it forever; while holding ours, a torch lock file in the folder can only be
such a leftover, and it is removed.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import threading
from pathlib import Path
from typing import Any

_LOG = logging.getLogger(__name__)
_SOURCE = Path(__file__).with_name("csrc") / "rollout_loop.cpp"
_LOCK = threading.Lock()
_STATE: dict[str, Any] = {"module": None, "tried": False, "reason": "not built yet"}


def _ninja_on_path() -> None:
    """torch looks for ``ninja`` on PATH; a venv's own bin directory may not be on it."""
    if shutil.which("ninja") is None:
        bindir = str(Path(sys.executable).parent)
        if shutil.which("ninja", path=bindir) is not None:
            os.environ["PATH"] = bindir + os.pathsep + os.environ.get("PATH", "")


def _build_dir() -> Path:
    import torch

    base = os.environ.get("TORCH_EXTENSIONS_DIR") or str(
        Path.home() / ".cache" / "torch_extensions")
    tag = f"py{sys.version_info[0]}{sys.version_info[1]}_torch{torch.__version__}"
    return Path(base) / f"peel_rollout_loop_{tag.replace('+', '_').replace('.', '_')}"


def _build() -> Any:
    from torch.utils.cpp_extension import load_inline

    build_dir = _build_dir()
    build_dir.mkdir(parents=True, exist_ok=True)
    with open(build_dir / "peel.lock", "w") as lock:
        try:
            import fcntl

            fcntl.flock(lock, fcntl.LOCK_EX)  # waits for another process's build
        except ImportError:  # pragma: no cover - not POSIX: torch's own lock only
            pass
        stale = build_dir / "lock"  # torch's FileBaton file: left by a killed build
        if stale.exists():
            stale.unlink()
        return load_inline(name="peel_rollout_loop", cpp_sources=[_SOURCE.read_text()],
                           functions=None, extra_cflags=["-O2"], verbose=False,
                           build_directory=str(build_dir))


def toolchain_missing() -> str | None:
    """What is missing to build the loop (a C++ compiler, ninja), or None when both are there."""
    _ninja_on_path()
    compiler = os.environ.get("CXX", "c++")
    if shutil.which(compiler) is None:
        return f"no C++ compiler ({compiler!r} not on PATH)"
    if shutil.which("ninja") is None:
        return "no ninja on PATH"
    return None


def load() -> Any | None:
    """The compiled module (with ``RolloutLoop``), or None when disabled or not buildable."""
    if os.environ.get("PEEL_NATIVE_LOOP", "1") == "0":
        _STATE["reason"] = "disabled by PEEL_NATIVE_LOOP=0"
        return None
    with _LOCK:
        if _STATE["tried"]:
            return _STATE["module"]
        _STATE["tried"] = True
        missing = toolchain_missing()
        if missing is not None:
            _STATE["reason"] = missing
            _LOG.warning("peel: C++ rollout loop unavailable (%s); using the Python loop", missing)
            return None
        try:
            _STATE["module"] = _build()
            _STATE["reason"] = "built"
        except Exception as exc:  # no compiler, no ninja, no headers: the Python loop runs
            _STATE["reason"] = f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1:]}"
            _LOG.warning("peel: C++ rollout loop unavailable (%s); using the Python loop",
                         _STATE["reason"])
    return _STATE["module"]


def status() -> dict[str, Any]:
    """{'native': bool, 'reason': str} of the last :func:`load`."""
    return {"native": _STATE["module"] is not None, "reason": _STATE["reason"]}


def main() -> int:
    """``python -m peel_planner_node.native_loop``: build (or find) the loop, print the status."""
    import time

    t0 = time.perf_counter()
    load()
    st = status()
    print(f"setup: planner C++ rollout loop: {st['reason']} ({time.perf_counter() - t0:.1f} s)",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
