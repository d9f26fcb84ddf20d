"""The planner's C++ model-step loop: built with the installation, only loaded while planning,
bit-identical to the Python loop (docs/planner.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_planner_dynamics import FUSED_ARCHS, fused, history, model

from peel_planner_node import native_loop as loader

torch.set_num_threads(1)


@pytest.fixture()
def native_loop():
    """The C++ loop's loader, built. Skipped only where it cannot be built (no compiler or no
    ninja) or was switched off with PEEL_NATIVE_LOOP=0, and never under CI (``CI`` set), where
    that fails; with the toolchain present a failed build fails the test. scripts/setup.sh
    builds it, so this normally only loads."""
    why = "switched off by PEEL_NATIVE_LOOP=0" if os.environ.get("PEEL_NATIVE_LOOP", "1") == "0" \
        else loader.toolchain_missing()
    if why is not None:
        if os.environ.get("CI"):  # CI has the toolchain: a skip there would hide a lost loop
            pytest.fail(f"C++ loop not available in CI: {why}")
        pytest.skip(f"C++ loop not available: {why}")
    if not loader.is_built():
        loader.build()
    assert loader.load() is not None, loader.status()["reason"]
    return loader


# ---------------------------------------------------------------- the C++ loop
@pytest.mark.parametrize("arch", FUSED_ARCHS)
def test_native_loop_is_bit_identical_to_the_python_loop(arch: str, native_loop) -> None:
    """The C++ model-step loop (csrc/rollout_loop.cpp) makes the same ATen calls as the Python
    loop: equal bit for bit, over S > h, the wavefront's cut-off windows, a reused workspace,
    chunks on worker threads (the GIL is released) and after an in-place weight update."""
    pred = model(arch, 7)
    hist = history(25, seed=8)
    fast, slow = fused(pred), fused(pred, native_loop=False)
    chunked = fused(pred, workers=2, chunk_samples=3)
    chunked_slow = fused(pred, workers=1, chunk_samples=3, native_loop=False)
    for n, s in ((6, 30), (5, 7), (6, 30), (7, 1)):
        v = torch.rand(n, s) * 5.0
        assert torch.equal(fast.rollout(hist, v), slow.rollout(hist, v))
        assert torch.equal(chunked.rollout(hist, v), chunked_slow.rollout(hist, v))
    assert all(ws.native is not None for ws in fast.engines[0]._workspaces.values())
    assert all(ws.native is None for ws in slow.engines[0]._workspaces.values())
    assert "C++ loop" in fast.describe() and "Python loop" in slow.describe()
    with torch.no_grad():
        pred.body.lstm.w_h.weight.mul_(0.9)
    v = torch.rand(4, 12) * 5.0
    assert torch.equal(fast.rollout(hist, v), slow.rollout(hist, v))


def test_native_loop_receives_its_tensors_by_name(native_loop) -> None:
    """The C++ loop looks every tensor up by its field name once: a workspace record without
    one is refused with that name, not read from a wrong position."""
    dyn = fused(model("ours", 1))
    dyn.rollout(history(), torch.rand(3, 6))
    ws = next(iter(dyn.engines[0]._workspaces.values()))
    w = dyn.weights.current()
    bad = ws.steps[0]._replace(force_next=None)
    ws.steps = (bad, *ws.steps[1:])
    with pytest.raises(RuntimeError, match="no tensor named 'force_next'"):
        native_loop.bind(ws, w)


_PLAN_WITHOUT_BUILD = r"""
import json, logging, sys
import torch.utils.cpp_extension as ext
calls = []
def compile_attempt(*args, **kwargs):
    calls.append(kwargs.get("name"))
    raise RuntimeError("compiling inside the planning loop")
ext.load_inline = ext.load = compile_attempt
logging.basicConfig(level=logging.WARNING)
import numpy as np
from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node import native_loop
from peel_planner_node.config import load_planner_config
from peel_planner_node.cost import Cost
from peel_planner_node.dynamics import learned_dynamics
from peel_planner_node.mppi import Planner
cfg = load_planner_config()
planner = Planner(learned_dynamics(load_checkpoint(shipped_checkpoint()), cfg.dynamics),
                  Cost(cfg.cost), cfg)
n = 12
hist = Trajectory(t=np.arange(n) * 0.1, q=np.arange(n) * 0.2, v=np.full(n, 2.0),
                  u=np.full(n, 2.0), fx=np.full(n, 8.0), fz=np.full(n, 5.0),
                  psi=np.full(n, np.nan))
u = planner.plan(hist)
print(json.dumps({"u": u, "compiles": calls, "status": native_loop.status(),
                  "dynamics": planner.dynamics.describe(),
                  "dir": str(native_loop.build_dir())}))
"""


def test_a_missing_build_never_compiles_inside_plan(tmp_path: Path) -> None:
    """An installation without a built loop (here: an empty build location) plans at once with
    the Python loop, logs why and reports it in status() and the dynamics' description; no
    compiler is ever started from plan(). (Before, plan() compiled the loop: 33-64 s stalls.)"""
    empty = tmp_path / "native"
    out = subprocess.run([sys.executable, "-c", _PLAN_WITHOUT_BUILD], capture_output=True,
                         text=True, timeout=300,
                         env={**os.environ, "PEEL_NATIVE_LOOP_DIR": str(empty),
                              "PEEL_NATIVE_LOOP": "1"})
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["compiles"] == [] and 0.5 <= report["u"] <= 8.0
    assert not report["status"]["native"] and "not built" in report["status"]["reason"]
    assert "Python loop" in report["dynamics"] and "not built" in report["dynamics"]
    assert "C++ rollout loop unavailable" in out.stderr
    assert report["dir"].startswith(str(empty)) and not empty.exists()


def test_the_build_location_belongs_to_the_installation(tmp_path: Path, monkeypatch) -> None:
    """Inside a writable environment (a venv) the build lives in it; otherwise in a per-user
    cache keyed by the environment's path. Either way the folder names the source hash, so two
    clones never share (or rebuild) one build and an edited source is a new build."""
    monkeypatch.delenv("PEEL_NATIVE_LOOP_DIR", raising=False)
    one, two = tmp_path / "venv1", tmp_path / "venv2"
    one.mkdir()
    two.mkdir()
    assert loader.build_dir(str(one)).parent == one / "peel_native"
    assert loader.build_dir(str(one)) != loader.build_dir(str(two))
    if os.access(sys.prefix, os.W_OK):  # this venv: its own build
        assert loader.build_dir().is_relative_to(Path(sys.prefix))
    locked = tmp_path / "system"
    locked.mkdir()
    locked.chmod(0o555)
    if not os.access(locked, os.W_OK):  # (root can write anywhere)
        cache = loader.build_dir(str(locked))
        assert cache.is_relative_to(Path.home() / ".cache" / "peel" / "native")
        assert cache != loader.build_dir(str(tmp_path))
    key = loader.build_key()
    edited = tmp_path / "rollout_loop.cpp"
    edited.write_text(loader._SOURCE.read_text() + "\n// edited\n")
    monkeypatch.setattr(loader, "_SOURCE", edited)
    assert loader.build_key() != key
    monkeypatch.setenv("PEEL_NATIVE_LOOP_DIR", str(tmp_path / "elsewhere"))
    assert loader.build_dir().parent == tmp_path / "elsewhere"


def test_native_loop_can_be_switched_off() -> None:
    """PEEL_NATIVE_LOOP=0 (a fresh process): the Python loop runs and status() says why."""
    code = ("from peel_planner_node import native_loop as m; import json; "
            "print(m.load() is None, json.dumps(m.status()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "PEEL_NATIVE_LOOP": "0"}, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("True") and "PEEL_NATIVE_LOOP=0" in out.stdout


def test_native_loop_build_survives_a_leftover_torch_lock(native_loop) -> None:
    """A killed build leaves torch's lock file behind, and torch would wait for it forever; a
    build (holding its own OS lock) removes it and finishes."""
    leftover = native_loop.build_dir() / "lock"
    leftover.touch()
    code = ("from peel_planner_node import native_loop as m; m.build(); "
            "print(m.load() is not None)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600, env=dict(os.environ))
    assert out.returncode == 0 and out.stdout.strip() == "True", out.stderr
    assert not leftover.exists()
