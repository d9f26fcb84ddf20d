"""LearnedDynamics over the real ForcePredictor: the fused rollout equals step-by-step predict()."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from model_learner_node.config import ModelConfig
from model_learner_node.predictor import ForcePredictor, Normalization
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.dynamics import LearnedDynamics, OracleDynamics, history_window

torch.set_num_threads(1)
NORM = Normalization(in_mean=(10.0, 2.0, 6.0, 4.0), in_std=(7.0, 1.5, 3.0, 2.0),
                     out_mean=(0.1, -0.05), out_std=(0.5, 0.3))


def history(n: int = 20, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    return Trajectory(t=t, q=np.cumsum(np.full(n, 0.2)), v=np.full(n, 2.0), u=np.full(n, 2.0),
                      fx=8 + rng.normal(size=n), fz=5 + rng.normal(size=n), psi=np.full(n, np.nan))


def reference_rollout(pred: ForcePredictor, hist: Trajectory, v: torch.Tensor) -> torch.Tensor:
    """Independent, unbatched-in-time evaluation with predictor.predict, one step at a time."""
    h = pred.h
    rows = torch.tensor(history_window(hist, h), dtype=torch.float32)
    win = rows.unsqueeze(0).repeat(v.shape[0], 1, 1)
    out = []
    with torch.no_grad():
        for k in range(v.shape[1]):
            f = pred.predict(win, v[:, k])
            q = win[:, -1, 0] + 0.1 * v[:, k]
            row = torch.stack([q, v[:, k], f[:, 0], f[:, 1]], dim=1)
            win = torch.cat([win[:, 1:], row.unsqueeze(1)], dim=1)
            out.append(torch.stack([q, f[:, 0], f[:, 1]], dim=1))
    return torch.stack(out, dim=1)


@pytest.mark.parametrize("arch", ["ours", "cnn-lstm", "mlp"])
def test_learned_rollout_matches_stepwise_predict(arch: str) -> None:
    torch.manual_seed(0)
    pred = ForcePredictor(ModelConfig().with_arch(arch), NORM)
    dyn = LearnedDynamics(pred)
    assert (dyn.fused is not None) == (arch != "mlp")
    v = torch.rand(7, 12) * 4.0
    hist = history()
    got = dyn.rollout(hist, v)
    assert got.shape == (7, 12, 3)
    want = reference_rollout(pred, hist, v)
    torch.testing.assert_close(got, want, atol=2e-4, rtol=1e-4)
    torch.testing.assert_close(LearnedDynamics(pred, fast=False).rollout(hist, v), want,
                               atol=2e-5, rtol=1e-5)


@pytest.fixture()
def native_loop():
    """The C++ loop's loader, built. Skipped only where it cannot be built (no compiler or no
    ninja) or was switched off with PEEL_NATIVE_LOOP=0; with the toolchain present a failed
    build fails the test."""
    from peel_planner_node import native_loop as loader

    if os.environ.get("PEEL_NATIVE_LOOP", "1") == "0":
        pytest.skip("C++ loop switched off by PEEL_NATIVE_LOOP=0")
    missing = loader.toolchain_missing()
    if missing is not None:
        pytest.skip(f"C++ loop cannot be built here: {missing}")
    assert loader.load() is not None, loader.status()["reason"]
    return loader


@pytest.mark.parametrize("arch", ["ours", "cnn-lstm"])
def test_native_loop_is_bit_identical_to_the_python_loop(arch: str, native_loop) -> None:
    """The C++ model-step loop (csrc/rollout_loop.cpp) makes the same ATen calls as the Python
    loop: equal bit for bit, over S > h, the wavefront's cut-off windows, a reused workspace,
    chunks on worker threads (the GIL is released) and after an in-place weight update."""
    torch.manual_seed(7)
    pred = ForcePredictor(ModelConfig().with_arch(arch), NORM)
    hist = history(25, seed=8)
    fast, slow = LearnedDynamics(pred), LearnedDynamics(pred, native=False)
    chunked = LearnedDynamics(pred, workers=2, min_chunk=3)
    for n, s in ((6, 30), (5, 7), (6, 30), (7, 1)):
        v = torch.rand(n, s) * 5.0
        want = slow.rollout(hist, v)
        assert torch.equal(fast.rollout(hist, v), want)
        assert torch.equal(chunked.rollout(hist, v), want)
    assert fast.fused._ws["native"] is not None and slow.fused._ws["native"] is None
    with torch.no_grad():
        pred.body.lstm.w_h.weight.mul_(0.9)
    v = torch.rand(4, 12) * 5.0
    assert torch.equal(fast.rollout(hist, v), slow.rollout(hist, v))


def test_native_loop_can_be_switched_off() -> None:
    """PEEL_NATIVE_LOOP=0 (a fresh process): the Python loop runs and status() says why."""
    code = ("from peel_planner_node import native_loop as m; import json; "
            "print(m.load() is None, json.dumps(m.status()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "PEEL_NATIVE_LOOP": "0"}, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("True") and "PEEL_NATIVE_LOOP=0" in out.stdout


@pytest.mark.parametrize("arch", ["ours", "cnn-lstm"])
def test_rollout_workers_give_bit_identical_results(arch: str) -> None:
    """Sample chunks rolled out on worker threads (each with its own workspace) equal one
    rollout of the whole batch bit for bit, for uneven chunks and repeated calls; a batch below
    2 x min_chunk stays in one chunk."""
    torch.manual_seed(5)
    pred = ForcePredictor(ModelConfig().with_arch(arch), NORM)
    hist = history(25, seed=6)
    one = LearnedDynamics(pred)
    many = LearnedDynamics(pred, workers=3, min_chunk=4)
    assert many._chunk_count(11) == 2 and many._chunk_count(13) == 3
    assert many._chunk_count(7) == 1 and one._chunk_count(10_000) == 1
    for n, s in ((13, 30), (11, 9), (13, 30), (7, 5)):
        v = torch.rand(n, s) * 5.0
        assert torch.equal(many.rollout(hist, v), one.rollout(hist, v))
    assert len(many._chunks) == 2  # workspaces kept for the reused chunks
    with pytest.raises(PeelError, match="rollout workers"):
        many.set_workers(0)


@pytest.mark.parametrize("arch", ["ours", "cnn-lstm", "mlp"])
def test_fast_path_matches_stepwise_predict_over_long_horizons_and_reused_workspace(
        arch: str) -> None:
    """S > h (windows made only of predicted rows), repeated calls reuse the workspace and the
    carried-over interior projections, a new (N, S) reallocates: all equal predict() step by
    step."""
    torch.manual_seed(3)
    pred = ForcePredictor(ModelConfig().with_arch(arch), NORM)
    dyn = LearnedDynamics(pred)
    hist = history(25, seed=4)
    # S = 6, 7, 8 around the wavefront depth D = 7 (ours) / 8 (cnn-lstm): the last windows
    # are cut from the batched step
    for n, s in ((6, 30), (6, 30), (2, 13), (9, 1), (4, 6), (4, 7), (3, 8)):
        v = torch.rand(n, s) * 5.0
        # float rounding only: measured <= 2e-5 (q up to ~40 mm, forces ~10 N); a carried-over
        # projection from the wrong position is off by ~2e-4 with these weights
        torch.testing.assert_close(dyn.rollout(hist, v), reference_rollout(pred, hist, v),
                                   atol=5e-5, rtol=2e-6)
    if arch != "mlp":
        f = dyn.fused
        assert f.reused and set(f.reused).isdisjoint(f.fresh)
        assert sorted(f.reused + f.fresh) == list(range(f.length))
        assert f.depth == f.h + f.pad - f.width + 1 and len(f.wave) == 2 * f.pad + 1


def test_fused_variants_without_padding_and_with_large_attention_logits() -> None:
    """Paddings 0 (no edge positions: h_L comes from the batched step) and attention weights
    large enough that the softmax needs its max-shift: both still equal predict()."""
    torch.manual_seed(5)
    hist = history(25, seed=6)
    v = torch.rand(5, 20) * 4.0
    pred = ForcePredictor(ModelConfig(kernels=(3, 3, 3), paddings=(0, 0, 0)), NORM)
    dyn = LearnedDynamics(pred)
    assert dyn.fused is not None and dyn.fused.pad == 0
    torch.testing.assert_close(dyn.rollout(hist, v), reference_rollout(pred, hist, v),
                               atol=5e-5, rtol=2e-6)
    pred = ForcePredictor(ModelConfig(), NORM)
    with torch.no_grad():
        pred.body.attention.mlp[2].weight.mul_(40.0)
    dyn = LearnedDynamics(pred)
    dyn.rollout(hist, v)
    assert dyn.fused._w["att_shift"]
    torch.testing.assert_close(dyn.rollout(hist, v), reference_rollout(pred, hist, v),
                               atol=5e-5, rtol=2e-6)


def test_fused_weights_are_cached_until_the_predictor_changes() -> None:
    torch.manual_seed(2)
    pred = ForcePredictor(ModelConfig(), NORM)
    dyn = LearnedDynamics(pred)
    v = torch.rand(4, 10) * 3.0
    dyn.rollout(history(), v)
    cached = dyn.fused._w
    dyn.rollout(history(), v)
    assert dyn.fused._w is cached  # unchanged weights: not rebuilt
    other = ForcePredictor(ModelConfig(), NORM)
    pred.load_state_dict(other.state_dict())  # copy_ in place: _version changes
    got = dyn.rollout(history(), v)
    assert dyn.fused._w is not cached
    torch.testing.assert_close(got, reference_rollout(other, history(), v), atol=2e-4, rtol=1e-4)
    cached = dyn.fused._w
    lin = pred.body.regressor[0]
    lin.weight.data = lin.weight.data * 1.5  # new storage, same Parameter object
    got = dyn.rollout(history(), v)
    assert dyn.fused._w is not cached
    torch.testing.assert_close(got, reference_rollout(pred, history(), v), atol=2e-4, rtol=1e-4)
    with torch.no_grad():
        pred.in_std.mul_(1.1)  # a normalisation buffer changed in place
    torch.testing.assert_close(dyn.rollout(history(), v), reference_rollout(pred, history(), v),
                               atol=2e-4, rtol=1e-4)


def test_fused_rollout_sees_in_place_weight_updates() -> None:
    torch.manual_seed(1)
    pred = ForcePredictor(ModelConfig(), NORM)
    dyn = LearnedDynamics(pred)
    v = torch.rand(3, 6) * 3.0
    before = dyn.rollout(history(), v).clone()
    with torch.no_grad():
        for p in pred.parameters():
            p.add_(0.05 * torch.randn_like(p))
    after = dyn.rollout(history(), v)
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, reference_rollout(pred, history(), v), atol=2e-4, rtol=1e-4)


def test_short_history_is_padded_with_rest() -> None:
    hist = history(3)
    win = history_window(hist, 10)
    assert win.shape == (10, 4)
    np.testing.assert_allclose(win[-3:], hist.states())
    assert np.all(win[:7, 1] == 0.0) and np.all(win[:7, 0] == hist.q[0])
    with pytest.raises(PeelError, match="empty"):
        history_window(history(0), 10)


def test_oracle_adapter_checks_shape() -> None:
    class Env:
        def rollout(self, v):
            return np.stack([v.cumsum(1) * 0.1, v, v], axis=-1)

    out = OracleDynamics(Env()).rollout(history(), torch.ones(2, 4))
    assert out.shape == (2, 4, 3) and float(out[0, -1, 0]) == pytest.approx(0.4)

    class Bad:
        def rollout(self, v):
            return np.zeros((1, 1, 3))

    with pytest.raises(PeelError, match="shape"):
        OracleDynamics(Bad()).rollout(history(), torch.ones(2, 4))


def test_native_loop_build_survives_a_leftover_torch_lock(native_loop) -> None:
    """A killed build leaves torch's lock file behind, and torch would wait for it forever; the
    loader (holding its own OS lock) removes it and loads."""
    leftover = native_loop._build_dir() / "lock"
    leftover.touch()
    out = subprocess.run([sys.executable, "-m", "peel_planner_node.native_loop"],
                         capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert out.returncode == 0 and "rollout loop: built" in out.stderr, out.stderr
    assert not leftover.exists()
