"""The compensated forward model: terms, their algebra, checkpoints, MAML and the planner.

F = f_theta(x with the terms removed, v) + g (docs/residual.md): checked against the base model
on inputs where the answer is known exactly (a sensor offset, a cross-talk matrix), round trips
through safetensors + JSON read back by ``json`` and ``safetensors.numpy``, refusals naming the
problem, MAML changing f_theta only, and the planner rolling the terms out step by step.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.numpy import load_file

from model_learner_node.maml import MamlConfig, MetaLearner, sample_batch
from model_learner_node.synthetic import synthetic_trajectory
from peel_model.checkpoint import load_checkpoint, save_checkpoint
from peel_model.compensated import CompensatedPredictor
from peel_model.config import ModelConfig
from peel_model.effect_terms import FAMILIES, Candidate, Rows, Term
from peel_model.predictor import ForcePredictor, fit_normalization
from peel_model.windows import padded_times
from peel_msgs_py.errors import CheckpointError, PeelError
from peel_planner_node.config import load_planner_config
from peel_planner_node.cost import Cost, total
from peel_planner_node.dynamics import ReferenceDynamics, history_window, learned_dynamics
from peel_planner_node.fused_dynamics import FusedDynamics
from peel_planner_node.model_check import validate_model
from peel_planner_node.mppi import Planner
from peel_residual.params import FAMILY_NAMES, GRIDS


@pytest.fixture(scope="module")
def base() -> ForcePredictor:
    torch.manual_seed(0)
    trajs = [synthetic_trajectory(i) for i in range(4)]
    return ForcePredictor(ModelConfig(), fit_normalization(trajs, 10)).eval()


def _hist(n: int = 6, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    hist = torch.rand(n, 10, 4, generator=g) * torch.tensor([20.0, 4.0, 12.0, 8.0])
    return hist, torch.rand(n, generator=g) * 5.0


def _term(family: str, channel: str, *coef: float, param: float | None = None) -> Term:
    return Term(Candidate(family, param), channel, tuple(coef))


def test_every_family_has_its_basis_and_expressions() -> None:
    rows = Rows(q=torch.linspace(0, 25, 11)[None], v=torch.linspace(0.5, 6, 11)[None],
                t=torch.linspace(0, 9, 11)[None], f=torch.rand(1, 11, 2) * 10,
                u=torch.linspace(1, 5, 11)[None])
    # the declared parameters (torch-free) list the library's families and shape grids
    assert tuple(FAMILIES) == FAMILY_NAMES
    assert all(FAMILIES[fam].param is not None for fam, _ in GRIDS.values())
    for name, fam in FAMILIES.items():
        cand = Candidate(name, None if fam.param is None else 2.0)
        phi = cand.basis(rows, 0)
        assert phi.shape == (1, 11, cand.n_basis) and torch.isfinite(phi).all(), name
        assert len(cand.expressions) == cand.n_basis and fam.meaning and fam.variable


def test_terms_round_trip_and_refuse_bad_input() -> None:
    t = _term("periodic_adhesion", "fz", 0.5, -0.25, param=6.0)
    back = Term.from_json(json.loads(json.dumps(t.to_json())))
    assert back == Term(t.candidate, "fz", (0.5, -0.25))
    assert "sin(2*pi*q/6)" in t.expression
    for bad, needle in [
        ({"family": "magic", "channel": "fx", "coefficients": [1.0]}, "unknown effect family"),
        ({"family": "viscous_drag", "channel": "v", "coefficients": [1.0]}, "acts on"),
        ({"family": "viscous_drag", "channel": "fx", "coefficients": [1.0, 2.0]}, "coefficient"),
        ({"family": "viscous_drag", "channel": "fx", "coefficients": [math.inf]}, "finite"),
        ({"family": "decay_in_time", "channel": "fx", "coefficients": [1.0]}, "parameter"),
        ({"family": "decay_in_time", "param": -2, "channel": "fx", "coefficients": [1.0]}, "> 0"),
    ]:
        with pytest.raises(PeelError, match=needle):
            Term.from_json(bad)


def test_no_terms_is_the_base_model(base: ForcePredictor) -> None:
    hist, v = _hist()
    assert torch.equal(CompensatedPredictor(base, []).predict(hist, v), base.predict(hist, v))


def test_offset_is_removed_from_the_history_and_added_back(base: ForcePredictor) -> None:
    """A sensor offset c: the model with the term on shifted data = base on clean data + c."""
    hist, v = _hist()
    comp = CompensatedPredictor(base, [_term("sensor_offset", "fz", 1.5),
                                       _term("sensor_offset", "fx", -0.7)])
    shifted = hist.clone()
    shifted[..., 2] -= 0.7
    shifted[..., 3] += 1.5
    want = base.predict(hist, v) + torch.tensor([-0.7, 1.5])
    assert torch.allclose(comp.predict(shifted, v), want, atol=1e-5)


def test_cross_talk_is_inverted_exactly(base: ForcePredictor) -> None:
    """m = (I + C) F: the model on mixed data = (I + C) base(F)."""
    hist, v = _hist()
    c = torch.tensor([[1.0, 0.08], [-0.05, 1.0]])
    comp = CompensatedPredictor(base, [_term("cross_talk", "fx", 0.08),
                                       _term("cross_talk", "fz", -0.05)])
    mixed = hist.clone()
    mixed[..., 2:4] = hist[..., 2:4] @ c.T
    assert torch.allclose(comp.predict(mixed, v), base.predict(hist, v) @ c.T, atol=1e-4)


def test_time_terms_need_times(base: ForcePredictor) -> None:
    hist, v = _hist()
    comp = CompensatedPredictor(base, [_term("decay_in_time", "fx", 2.0, param=5.0)])
    assert comp.needs_time
    assert torch.equal(comp.predict(hist, v), base.predict(hist, v))  # no times: no time term
    t = torch.full((hist.shape[0],), 1.5)
    got = comp.predict(hist, v, t)
    clean = hist.clone()
    clean[..., 2] -= 2.0 * torch.exp(-(t[:, None] - 0.1 * torch.arange(10, 0, -1)) / 5.0)
    want = base.predict(clean, v)
    want[:, 0] += 2.0 * math.exp(-1.5 / 5.0)
    assert torch.allclose(got, want, atol=1e-5)


@torch.no_grad()
def _rollout_by_hand(comp: CompensatedPredictor, hist, v: torch.Tensor) -> torch.Tensor:
    """Eq. 1-2 with the terms, step by step, written out independently of the planner: speeds
    from the speed response, q from the speeds, forces from ``predict`` at t_now + (k+1) dt."""
    n, s = v.shape
    window = torch.as_tensor(history_window(hist, comp.h), dtype=torch.float32).repeat(n, 1, 1)
    speed = torch.full((n,), float(hist.v[-1]))
    t, rows = float(hist.t[-1]), []
    for k in range(s):
        speed = comp.speed(v[:, k], speed)
        t += 0.1
        f = comp.predict(window, speed, torch.full((n,), t))
        row = torch.stack([window[:, -1, 0] + 0.1 * speed, speed, f[:, 0], f[:, 1]], dim=1)
        window = torch.cat([window[:, 1:], row[:, None]], dim=1)
        rows.append(row)
    return torch.stack(rows, dim=1)[..., [0, 2, 3]]


def test_speed_response_and_the_planners_rollouts_carry_the_terms(base: ForcePredictor) -> None:
    comp = CompensatedPredictor(base, [_term("actuator_lag", "v", 0.6),
                                       _term("speed_scale", "v", -0.1),
                                       _term("drift_in_time", "fz", 0.5),
                                       _term("near_start_hold", "fx", 3.0, param=4.0)])
    u, prev = torch.tensor([2.0, 4.0]), torch.tensor([1.0, 1.0])
    assert torch.allclose(comp.speed(u, prev), u + 0.6 * (prev - u) - 0.1 * u)
    # the capability check: not the fused path (it reproduces the plain network only)
    cfg = load_planner_config()
    assert cfg.dynamics.implementation == "fused"
    dyn = learned_dynamics(comp, cfg.dynamics)
    assert isinstance(dyn, ReferenceDynamics) and isinstance(learned_dynamics(base), FusedDynamics)
    hist = synthetic_trajectory(0).slice(0, 30)
    v = torch.rand(5, 12, generator=torch.Generator().manual_seed(3)) * 5.0
    out = dyn.rollout(hist, v)
    assert torch.allclose(out, _rollout_by_hand(comp, hist, v), atol=1e-4)
    assert not torch.allclose(out, ReferenceDynamics(base).rollout(hist, v), atol=1e-2)
    # the planner's cost is that of rollouts with the terms (Algorithm 2 lines 9-12)
    planner = Planner(dyn, Cost(cfg.cost), cfg)
    planner.reset()
    planner.plan(hist)
    sampled = planner.last["v"]
    k = cfg.mppi.steps_per_horizon_step
    v_model = sampled.repeat_interleave(k, dim=1)
    want = total(planner.cost.rollout_terms(float(hist.q[-1]), float(hist.t[-1]),
                                            _rollout_by_hand(comp, hist, v_model)))
    assert torch.allclose(planner.last["cost"], want.to(planner.last["cost"].dtype), rtol=1e-4)
    with pytest.raises(PeelError, match="stable"):
        CompensatedPredictor(base, [_term("actuator_lag", "v", 1.2)])


def test_checkpoint_round_trip_and_refusals(base: ForcePredictor, tmp_path: Path) -> None:
    comp = CompensatedPredictor(base, [_term("periodic_adhesion", "fz", 0.4, -0.2, param=8.0),
                                       _term("decay_in_time", "fx", 1.0, param=2.0),
                                       _term("actuator_lag", "v", 0.5)])
    path = save_checkpoint(tmp_path / "c", comp, {"note": "test"})
    cfg = json.loads(path.with_suffix(".json").read_text())
    assert cfg["format_version"] == 2
    assert [t["family"] for t in cfg["compensation"]["terms"]] == [
        "periodic_adhesion", "decay_in_time", "actuator_lag"]
    tensors = load_file(str(path))  # f_theta alone, under the plain names
    assert set(tensors) == set(base.state_dict())
    back = load_checkpoint(path)
    assert isinstance(back, CompensatedPredictor) and back.terms == comp.terms
    hist, v = _hist()
    t = torch.full((hist.shape[0],), 2.0)
    assert torch.equal(back.predict(hist, v, t), comp.predict(hist, v, t))
    plain = save_checkpoint(tmp_path / "plain", base)
    assert json.loads(plain.with_suffix(".json").read_text())["format_version"] == 1
    # the identity (SHA-256 of the weights file) differs with the terms, f_theta unchanged
    other = save_checkpoint(tmp_path / "other", CompensatedPredictor(base, comp.terms[:2]))
    shas = {json.loads(p.with_suffix(".json").read_text())["safetensors_sha256"]
            for p in (path, plain, other)}
    assert len(shas) == 3
    for edit, needle in [
        (lambda c: c["compensation"]["terms"][0].update(family="magic"), "unknown effect family"),
        (lambda c: c["compensation"]["terms"][2].update(coefficients=[1.5]), "stable"),
        (lambda c: c["compensation"]["terms"][1].update(coefficients=[]), "coefficient"),
        (lambda c: c.pop("compensation"), "go together"),
        (lambda c: c.update(format_version=1), "go together"),
        (lambda c: c["compensation"].update(dt_s=0.05), "dt_s"),
        (lambda c: c["compensation"]["terms"][1].update(coefficients=[2.0]), "sealed"),
    ]:
        bad = json.loads(path.with_suffix(".json").read_text())
        edit(bad)
        bad_js = tmp_path / "bad.json"
        bad_js.write_text(json.dumps(bad))
        (tmp_path / "bad.safetensors").write_bytes(path.read_bytes())
        with pytest.raises(CheckpointError, match=needle):
            load_checkpoint(tmp_path / "bad.safetensors")


def test_maml_adapts_f_theta_with_the_terms_held(base: ForcePredictor) -> None:
    comp = CompensatedPredictor(
        ForcePredictor(base.cfg, base.normalization),
        [_term("decay_in_time", "fx", 1.0, param=2.0), _term("viscous_drag", "fz", 0.3)])
    comp.base.load_state_dict(base.state_dict())
    trajs = [synthetic_trajectory(i) for i in range(4)]
    before = {k: v.clone() for k, v in comp.state_dict().items()}
    terms = comp.terms
    # planned with first (inference mode, as in peel experiment's one process), then adapted
    learned_dynamics(comp).rollout(synthetic_trajectory(5).slice(0, 20), torch.ones(2, 5))
    rep = MetaLearner(comp, MamlConfig(meta_steps=2, m=2, support_slices=4, query_slices=4,
                                       eval_slices=4)).update(trajs[0], trajs[1:])
    assert rep["updated"]
    assert comp.terms == terms
    assert any(not torch.equal(before[k], v) for k, v in comp.state_dict().items())
    one = trajs[2]
    batch = sample_batch([one], 40, 10, 11, np.random.default_rng(0), with_time=True)
    assert batch.t_next is not None and batch.t_next.shape == (40,)
    idx = np.searchsorted(one.t, batch.t_next.numpy() - 1e-4)  # the sample each window predicts
    assert np.allclose(one.fx[idx], batch.f_next[:, 0].numpy(), atol=1e-5)
    assert np.allclose(padded_times(one, 3)[:3], one.t[0] - one.dt * np.arange(3, 0, -1))


def test_planner_accepts_and_plans_with_a_corrected_checkpoint(base: ForcePredictor,
                                                               tmp_path: Path) -> None:
    comp = CompensatedPredictor(base, [_term("near_start_hold", "fz", 2.0, param=4.0),
                                       _term("drift_in_time", "fz", 0.1),
                                       _term("actuator_lag", "v", 0.5)])
    path = save_checkpoint(tmp_path / "corrected", comp)
    pred = validate_model(path, None, 16, 10)
    assert isinstance(pred, CompensatedPredictor)
    cfg = load_planner_config()
    planner = Planner(learned_dynamics(pred, cfg.dynamics), Cost(cfg.cost), cfg)
    planner.reset()
    u = planner.plan(synthetic_trajectory(1).slice(0, 25))
    assert math.isfinite(u) and cfg.mppi.u_min <= u <= cfg.mppi.u_max
    # the swap check probes the terms too: a time term that overflows late in a task is refused
    late = save_checkpoint(tmp_path / "late", CompensatedPredictor(
        base, [_term("drift_in_time", "fz", 1e38)]))
    with pytest.raises(CheckpointError, match="non-finite forces"):
        validate_model(late, None, 16, 10)
