"""Planner dynamics: the fused rollout equals the reference (the model stepped sample by sample)
to float rounding for every architecture, the C++ and Python loops are bit-identical, and the
result does not depend on the number of rollout workers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from peel_model.config import ModelConfig
from peel_model.predictor import ForcePredictor, Normalization
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import DynamicsConfig, FusedConfig, PlannerConfig
from peel_planner_node.dynamics import (
    Dynamics,
    OracleDynamics,
    ReferenceDynamics,
    history_window,
    learned_dynamics,
)
from peel_planner_node.fused_dynamics import FusedDynamics, chunk_spans
from peel_planner_node.fused_weights import fused_support

torch.set_num_threads(1)
NORM = Normalization(in_mean=(10.0, 2.0, 6.0, 4.0), in_std=(7.0, 1.5, 3.0, 2.0),
                     out_mean=(0.1, -0.05), out_std=(0.5, 0.3))
FUSED_ARCHS = ("ours", "cnn-lstm")


def history(n: int = 20, seed: int = 0) -> Trajectory:
    """A random measured history: random speeds (so q steps unevenly) and forces."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    v = rng.uniform(0.0, 5.0, n)
    return Trajectory(t=t, q=np.cumsum(0.1 * v), v=v, u=v, fx=8 + 3 * rng.normal(size=n),
                      fz=5 + 2 * rng.normal(size=n), psi=np.full(n, np.nan))


def model(arch: str, seed: int, dtype: torch.dtype = torch.float32, **changes) -> ForcePredictor:
    torch.manual_seed(seed)
    return ForcePredictor(ModelConfig(**changes).with_arch(arch), NORM).to(dtype)


def fused(pred: ForcePredictor, **settings) -> FusedDynamics:
    return FusedDynamics(pred, config=FusedConfig(**settings))


def stepwise(pred: ForcePredictor, hist: Trajectory, v: torch.Tensor) -> torch.Tensor:
    """An independent step-by-step evaluation with predictor.predict (no Dynamics code)."""
    h = pred.h
    win = torch.tensor(history_window(hist, h), dtype=v.dtype).unsqueeze(0).repeat(len(v), 1, 1)
    out = []
    with torch.no_grad():
        for k in range(v.shape[1]):
            f = pred.predict(win, v[:, k])
            q = win[:, -1, 0] + 0.1 * v[:, k]
            row = torch.stack([q, v[:, k], f[:, 0], f[:, 1]], dim=1)
            win = torch.cat([win[:, 1:], row.unsqueeze(1)], dim=1)
            out.append(torch.stack([q, f[:, 0], f[:, 1]], dim=1))
    return torch.stack(out, dim=1)


# ---------------------------------------------------------------- the reference
@pytest.mark.parametrize("arch", ["ours", "cnn-lstm", "mlp"])
def test_reference_dynamics_is_the_model_stepped_sample_by_sample(arch: str) -> None:
    pred = model(arch, 0)
    hist, v = history(), torch.rand(7, 12) * 4.0
    got = ReferenceDynamics(pred).rollout(hist, v)
    assert got.shape == (7, 12, 3)
    torch.testing.assert_close(got, stepwise(pred, hist, v), atol=2e-5, rtol=1e-5)


def test_learned_dynamics_chooses_by_one_capability_check() -> None:
    """Fused for ours / cnn-lstm; the reference for the mlp baseline, for a model whose
    predict() adds something (a subclass: the fused path would silently drop it), and when
    dynamics.implementation is 'reference'."""
    for arch in FUSED_ARCHS:
        assert isinstance(learned_dynamics(model(arch, 0)), FusedDynamics)
        assert fused_support(model(arch, 0)) is None
    assert isinstance(learned_dynamics(model("mlp", 0)), ReferenceDynamics)
    narrow = model("ours", 0, h=4)  # merged kernel (width 6) wider than the window
    assert "exceeds the history" in fused_support(narrow)
    assert isinstance(learned_dynamics(narrow), ReferenceDynamics)

    class Compensated(ForcePredictor):
        def predict(self, hist, v_next):
            return super().predict(hist, v_next) + 1.0

    extra = Compensated(ModelConfig(), NORM)
    assert "Compensated" in fused_support(extra)
    dyn = learned_dynamics(extra)
    assert isinstance(dyn, ReferenceDynamics)
    hist, v = history(), torch.rand(3, 6)
    torch.testing.assert_close(dyn.rollout(hist, v), stepwise(extra, hist, v))
    assert isinstance(learned_dynamics(model("ours", 0), DynamicsConfig(implementation="reference")),
                      ReferenceDynamics)
    with pytest.raises(PeelError, match="fused dynamics cannot"):
        FusedDynamics(model("mlp", 0))
    for dyn in (learned_dynamics(model("ours", 0)), learned_dynamics(model("mlp", 0))):
        assert isinstance(dyn, Dynamics) and dyn.describe()


# ---------------------------------------------------------------- fused == reference
@pytest.mark.parametrize("arch", FUSED_ARCHS)
def test_fused_equals_reference_over_random_histories_and_commands(arch: str) -> None:
    """Random histories (also shorter than h: padded), random commands, N and S around the
    wavefront depth D (7 for ours, 8 for cnn-lstm: windows cut off at the end), S > h, reused
    and reallocated workspaces. float32: float rounding (measured <= 2e-5; a projection carried
    over from the wrong position is off by ~2e-4). float64: equal to 1e-9."""
    for dtype, atol in ((torch.float32, 5e-5), (torch.float64, 1e-9)):
        pred = model(arch, 3, dtype)
        ref = ReferenceDynamics(pred)
        dyn = fused(pred, dtype="float64" if dtype == torch.float64 else "float32")
        gen = torch.Generator().manual_seed(4)
        for trial, (n, s) in enumerate(((6, 30), (6, 30), (2, 13), (9, 1), (4, 6), (4, 7),
                                        (3, 8), (5, 25))):
            hist = history(25 if trial % 3 else 4, seed=trial)
            v = (torch.rand(n, s, generator=gen) * 6.0).to(dtype)
            got = dyn.rollout(hist, v)
            assert got.dtype == dtype
            torch.testing.assert_close(got, ref.rollout(hist, v), atol=atol, rtol=atol / 20)


def test_fused_dtype_is_its_own_setting() -> None:
    """dynamics.fused.dtype float64 runs a float32 model in float64: closer to the float64
    reference than the float32 rollout is."""
    pred = model("ours", 2)
    hist, v = history(25, seed=1), torch.rand(4, 20, dtype=torch.float64) * 5.0
    want = ReferenceDynamics(model("ours", 2, torch.float64)).rollout(hist, v)
    wide = fused(pred, dtype="float64").rollout(hist, v)
    narrow = fused(pred).rollout(hist, v)
    assert wide.dtype == torch.float64 and narrow.dtype == torch.float32
    assert (wide - want).abs().max() < 1e-9 < (narrow.double() - want).abs().max()


def test_fused_variants_without_padding_and_with_large_attention_logits() -> None:
    """Paddings 0 (no edge positions: h_L comes from the batched step), a window with a
    single interior position (h = merged kernel width), a small network, and attention weights
    large enough that the softmax needs its max-shift: all still equal the reference."""
    hist, v = history(25, seed=6), torch.rand(5, 20) * 4.0
    for changes in ({"kernels": (3, 3, 3), "paddings": (0, 0, 0)}, {"h": 6},
                    {"h": 7, "conv_channels": 2, "attention_hidden": 2, "lstm_hidden": 4,
                     "fc": (8,)}):
        pred = model("ours", 5, **changes)
        dyn = fused(pred)
        assert dyn.weights.schedule.pad == 0 or "kernels" not in changes
        torch.testing.assert_close(dyn.rollout(hist, v),
                                   ReferenceDynamics(pred).rollout(hist, v), atol=5e-5,
                                   rtol=2e-6)
    pred = model("ours", 5)
    with torch.no_grad():
        pred.body.attention.mlp[2].weight.mul_(40.0)
    dyn = fused(pred)
    got = dyn.rollout(hist, v)
    assert dyn.weights.current().att_shift
    torch.testing.assert_close(got, ReferenceDynamics(pred).rollout(hist, v), atol=5e-5,
                               rtol=2e-6)


def test_schedule_covers_every_position_once() -> None:
    for arch in FUSED_ARCHS:
        sch = fused(model(arch, 0)).weights.schedule
        reused = [j for j in range(sch.length) if j not in sch.fresh]
        assert reused and sorted(reused + sch.fresh) == list(range(sch.length))
        assert sch.depth == sch.h + sch.pad - sch.width + 1 and len(sch.wave) == 2 * sch.pad + 1


# ---------------------------------------------------------------- weight cache
def test_fused_weights_are_cached_until_the_predictor_changes() -> None:
    pred = model("ours", 2)
    dyn, hist, v = fused(pred), history(), torch.rand(4, 10) * 3.0
    dyn.rollout(hist, v)
    cached = dyn.weights.current()
    dyn.rollout(hist, v)
    assert dyn.weights.current() is cached  # unchanged weights: not rebuilt
    other = ForcePredictor(ModelConfig(), NORM)
    pred.load_state_dict(other.state_dict())  # copy_ in place: _version changes
    got = dyn.rollout(hist, v)
    assert dyn.weights.current() is not cached
    torch.testing.assert_close(got, stepwise(other, hist, v), atol=5e-5, rtol=1e-5)
    cached = dyn.weights.current()
    lin = pred.body.regressor[0]
    lin.weight.data = lin.weight.data * 1.5  # new storage, same Parameter object
    got = dyn.rollout(hist, v)
    assert dyn.weights.current() is not cached
    torch.testing.assert_close(got, stepwise(pred, hist, v), atol=5e-5, rtol=1e-5)
    with torch.no_grad():
        pred.in_std.mul_(1.1)  # a normalisation buffer changed in place
    torch.testing.assert_close(dyn.rollout(hist, v), stepwise(pred, hist, v), atol=5e-5,
                               rtol=1e-5)
    with torch.no_grad():
        for p in pred.parameters():  # an optimiser-like in-place update of every weight
            p.add_(0.05 * torch.randn_like(p))
    torch.testing.assert_close(dyn.rollout(hist, v), stepwise(pred, hist, v), atol=5e-5,
                               rtol=1e-5)


# ---------------------------------------------------------------- chunks and workers
def test_chunks_are_cut_by_n_and_the_chunk_size_only() -> None:
    assert chunk_spans(13, 4) == [(0, 4), (4, 8), (8, 12), (12, 13)]
    assert chunk_spans(50, 256) == [(0, 50)] and chunk_spans(1000, 256)[-1] == (768, 1000)
    with pytest.raises(PeelError, match="chunk_samples"):
        chunk_spans(5, 0)


@pytest.mark.parametrize("arch", FUSED_ARCHS)
@pytest.mark.parametrize("native", [True, False])
def test_any_number_of_workers_gives_bit_identical_results(arch: str, native: bool) -> None:
    """Chunks fixed by N and the chunk size, each rolled out with the caller's thread count:
    1, 2 and 3 workers agree bit for bit, for uneven chunks and repeated calls. Against one
    chunk of the whole batch the guarantee is float rounding (BLAS blocks a matmul by its row
    count)."""
    pred = model(arch, 5)
    hist = history(25, seed=6)
    gen = torch.Generator().manual_seed(6)
    dyns = [fused(pred, workers=w, chunk_samples=4, native_loop=native) for w in (1, 2, 3)]
    for n, s in ((13, 30), (11, 9), (13, 30), (3, 5)):
        v = torch.rand(n, s, generator=gen) * 5.0
        one, two, three = (d.rollout(hist, v) for d in dyns)
        assert torch.equal(one, two) and torch.equal(one, three)
        whole = fused(pred, chunk_samples=1000, native_loop=native).rollout(hist, v)
        torch.testing.assert_close(one, whole, atol=5e-5, rtol=2e-6)
    for d in dyns:
        d.close()


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


def test_short_history_is_padded_with_rest() -> None:
    hist = history(3)
    win = history_window(hist, 10)
    assert win.shape == (10, 4)
    np.testing.assert_allclose(win[-3:], hist.states())
    assert np.all(win[:7, 1] == 0.0) and np.all(win[:7, 0] == hist.q[0])
    with pytest.raises(PeelError, match="empty"):
        history_window(history(0), 10)


def test_dynamics_settings_are_their_own_config_section() -> None:
    """Threads, chunk size, dtype and the C++ loop are dynamics.fused.* parameters, not MPPI's."""
    cfg = PlannerConfig().replace(**{"dynamics.fused.workers": 3,
                                     "dynamics.fused.chunk_samples": 17,
                                     "dynamics.fused.dtype": "float64",
                                     "dynamics.fused.native_loop": False})
    assert cfg.dynamics.fused == FusedConfig(workers=3, chunk_samples=17, dtype="float64",
                                             native_loop=False)
    assert not any(name.startswith("mppi.") and ("worker" in name or "chunk" in name)
                   for name in cfg.to_params())
    dyn = learned_dynamics(model("ours", 0), cfg.dynamics)
    assert dyn.config is cfg.dynamics.fused and len(dyn.engines) == 3
