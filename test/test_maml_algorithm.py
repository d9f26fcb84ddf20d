"""Algorithm 1 (Eq. 26-27): meta-gradient vs central finite differences, task-oriented sampling,
and one update lowering the loss on the new trajectory's query set."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from model_learner_node.maml import (
    FAILED_PENALTY,
    MamlConfig,
    MetaLearner,
    default_loss,
    load_maml_config,
    sample_batch,
    select_task_oriented,
    trajectory_score,
)
from peel_msgs_py.errors import ParameterError, PeelError
from peel_msgs_py.trajectory import Trajectory

H = 3


class TinyModel(torch.nn.Module):
    """A small smooth forward model: [hist(h x 4), v_next] -> (fx, fz)."""

    def __init__(self, h: int = H, width: int = 6) -> None:
        super().__init__()
        self.h = h
        self.l1 = torch.nn.Linear(4 * h + 1, width)
        self.l2 = torch.nn.Linear(width, 2)
        self.register_buffer("scale", torch.tensor(0.1))

    def forward(self, hist: torch.Tensor, v_next: torch.Tensor) -> torch.Tensor:
        x = torch.cat([hist.flatten(1), v_next[:, None]], dim=1) * self.scale
        return self.l2(torch.tanh(self.l1(x)))


def make_traj(seed: int, n: int = 40, gain: float = 1.0, outcome: str = "done",
              cost: float | None = None) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    v = 2.0 + rng.normal(0, 0.5, n)
    q = np.cumsum(v) * 0.1
    fx = gain * (3.0 + 0.8 * v + 0.1 * q) + rng.normal(0, 0.05, n)
    fz = gain * (1.0 + 0.3 * v) + rng.normal(0, 0.05, n)
    meta = {} if cost is None else {"cost": cost}
    return Trajectory(t=t, q=q, v=v, u=v, fx=fx, fz=fz, psi=np.full(n, np.nan),
                      outcome=outcome, meta=meta)


def tasks_for(learner: MetaLearner, trajs: list[Trajectory], seed: int) -> list:
    rng = np.random.default_rng(seed)
    return learner.draw_tasks(trajs[0], trajs[1:], rng)


def flat(params: dict[str, torch.Tensor]) -> torch.Tensor:
    return torch.cat([v.reshape(-1) for v in params.values()])


def unflat(vec: torch.Tensor, like: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    out, i = {}, 0
    for k, v in like.items():
        out[k] = vec[i:i + v.numel()].reshape(v.shape)
        i += v.numel()
    return out


def _learner(first_order: bool, inner_steps: int = 2) -> MetaLearner:
    torch.manual_seed(0)
    model = TinyModel().double()
    cfg = MamlConfig(alpha=0.05, beta=0.01, m=2, support_slices=4, query_slices=4,
                     slice_len=H + 3, inner_steps=inner_steps, first_order=first_order)
    return MetaLearner(model, cfg, loss_fn=default_loss)


def test_second_order_meta_gradient_matches_central_differences() -> None:
    learner = _learner(first_order=False)
    trajs = [make_traj(1), make_traj(2, gain=1.5), make_traj(3, gain=0.7)]
    tasks = tasks_for(learner, trajs, seed=5)
    theta = learner.params()
    g = flat(learner.meta_gradient(theta, tasks))
    x0 = flat(theta)
    eps = 1e-6
    fd = torch.zeros_like(x0)
    for i in range(x0.numel()):
        e = torch.zeros_like(x0)
        e[i] = eps
        fp = learner.meta_objective(unflat(x0 + e, theta), tasks)
        fm = learner.meta_objective(unflat(x0 - e, theta), tasks)
        fd[i] = (fp - fm) / (2 * eps)
    assert g.dtype == torch.float64
    assert torch.allclose(g, fd, rtol=1e-5, atol=1e-8), (g - fd).abs().max()
    # and it really differs from the first-order approximation
    fo = _learner(first_order=True)
    g_fo = flat(fo.meta_gradient(theta, tasks))
    assert (g - g_fo).abs().max() > 1e-6


def test_first_order_meta_gradient_is_query_gradient_at_adapted_params() -> None:
    learner = _learner(first_order=True)
    trajs = [make_traj(4), make_traj(5, gain=1.3)]
    tasks = tasks_for(learner, trajs, seed=6)
    theta = learner.params()
    g = flat(learner.meta_gradient(theta, tasks))
    eps = 1e-6
    expected = torch.zeros_like(g)
    for support, query in tasks:
        adapted = learner.adapt(theta, support)
        x0 = flat(adapted).detach()
        for i in range(x0.numel()):
            e = torch.zeros_like(x0)
            e[i] = eps
            fp = learner.loss(unflat(x0 + e, adapted), query)
            fm = learner.loss(unflat(x0 - e, adapted), query)
            expected[i] += (fp - fm) / (2 * eps)
    assert torch.allclose(g, expected, rtol=1e-5, atol=1e-8), (g - expected).abs().max()


def test_adapt_is_eq26_gradient_step() -> None:
    learner = _learner(first_order=False, inner_steps=1)
    support = sample_batch([make_traj(7)], 4, H, H + 3, np.random.default_rng(0), torch.float64)
    theta = learner.params()
    g = torch.func.grad(learner.loss)(theta, support)
    adapted = learner.adapt(theta, support)
    for k in theta:
        assert torch.allclose(adapted[k], theta[k] - 0.05 * g[k])


def test_task_oriented_sampling_takes_the_m_best_by_score() -> None:
    costs = [30.0, 12.0, 50.0, 12.0, 8.0, 20.0]
    pool = [make_traj(i, cost=c) for i, c in enumerate(costs)]
    pool.append(make_traj(99, cost=1.0, outcome="safety_stop"))  # cheap but failed
    pool.append(make_traj(98))  # no cost: scored by -t_cpl = -3.9, ranks first
    assert trajectory_score(pool[0]) == -30.0
    assert trajectory_score(pool[6]) == -1.0 - FAILED_PENALTY
    assert trajectory_score(pool[7]) == pytest.approx(-3.9)
    assert select_task_oriented(pool, 3) == [7, 4, 3]  # tie 12.0 at 1 and 3: newer first
    assert select_task_oriented(pool, 5) == [7, 4, 3, 1, 5]
    assert select_task_oriented(pool, 0) == []
    assert select_task_oriented(pool, 50)[-1] == 6  # the failed one ranks last
    assert select_task_oriented(pool, 3, score_fn=lambda t: t.meta.get("cost", 0.0)) == [2, 0, 5]


def test_update_picks_pool_trajectories_and_lowers_new_query_loss() -> None:
    torch.manual_seed(1)
    model = TinyModel()
    # the "pretrained" model is wrong about the plant: targets scaled by gain 1.6
    cfg = MamlConfig(alpha=0.01, beta=0.02, m=2, support_slices=16, query_slices=16,
                     slice_len=H + 4, inner_steps=1, meta_steps=20, eval_slices=64, seed=3)
    learner = MetaLearner(model, cfg, loss_fn=default_loss)
    pool = [make_traj(10, gain=1.6, cost=20.0), make_traj(11, gain=1.6, cost=10.0),
            make_traj(12, gain=1.6, cost=40.0)]
    new = make_traj(13, gain=1.6, cost=15.0)
    before = [p.detach().clone() for p in model.parameters()]
    report = learner.update(new, [*pool, new])
    assert report["updated"] and report["version"] == 1
    assert report["chosen"] == [1, 0]
    assert report["query_loss_after"] < 0.8 * report["query_loss_before"]
    assert any(not torch.equal(a, b) for a, b in zip(before, model.parameters(), strict=True))
    assert report["update_s"] >= 0.0 and len(report["grad_norms"]) == 20


def test_update_is_deterministic_given_seed() -> None:
    reports = []
    for _ in range(2):
        torch.manual_seed(2)
        model = TinyModel()
        learner = MetaLearner(model, MamlConfig(m=1, meta_steps=3, slice_len=H + 2, seed=9),
                              loss_fn=default_loss)
        reports.append((learner.update(make_traj(20), [make_traj(21, cost=3.0)]),
                        [p.detach().clone() for p in model.parameters()]))
    for a, b in zip(reports[0][1], reports[1][1], strict=True):
        assert torch.equal(a, b)
    assert reports[0][0]["query_loss_after"] == reports[1][0]["query_loss_after"]


def test_adam_option_and_short_trajectory() -> None:
    model = TinyModel()
    learner = MetaLearner(model, MamlConfig(optimizer="adam", beta=0.01, m=0, meta_steps=2,
                                            slice_len=H + 2), loss_fn=default_loss)
    rep = learner.update(make_traj(30), None)
    assert rep["updated"] and rep["chosen"] == []
    short = make_traj(31, n=2)  # + h-1 = 2 padding rows: 4 < slice_len 5
    rep2 = learner.update(short, [])
    assert not rep2["updated"] and "samples" in rep2["reason"]
    assert learner.version == 1


def test_task_reduce_mean_divides_the_eq27_sum_by_the_number_of_tasks() -> None:
    summed = _learner(first_order=False)
    trajs = [make_traj(40), make_traj(41, gain=1.4), make_traj(42, gain=0.8)]
    tasks = tasks_for(summed, trajs, seed=7)
    theta = summed.params()
    torch.manual_seed(0)
    mean = MetaLearner(TinyModel().double(), replace(summed.cfg, task_reduce="mean"),
                       loss_fn=default_loss)
    assert summed.cfg.task_reduce == "sum" and len(tasks) == 3
    assert torch.allclose(mean.meta_objective(theta, tasks),
                          summed.meta_objective(theta, tasks) / 3)
    g_sum, g_mean = summed.meta_gradient(theta, tasks), mean.meta_gradient(theta, tasks)
    for k in theta:
        assert torch.allclose(g_mean[k], g_sum[k] / 3)
    with pytest.raises(ParameterError, match=r"maml\.task_reduce"):
        MamlConfig.from_params({"maml.task_reduce": "max"})


def test_config_validation_names_the_field() -> None:
    with pytest.raises(ParameterError, match=r"maml\.alpha"):
        MamlConfig.from_params({"maml.alpha": -1.0})
    with pytest.raises(ParameterError, match=r"maml\.optimizer"):
        MamlConfig.from_params({"maml.optimizer": "rmsprop"})
    with pytest.raises(PeelError, match="slice_len"):
        MetaLearner(TinyModel(), MamlConfig(slice_len=H))
    cfg = load_maml_config()
    assert cfg.alpha > 0 and cfg.beta > 0 and cfg.m >= 1


@pytest.mark.parametrize("arch", ["ours", "mlp"])
def test_meta_gradient_of_the_real_forward_model_with_training_loss(arch: str) -> None:
    """Second-order meta-gradient of a tiny ForcePredictor (conv + attention + LSTM) with the
    model's own loss L_MSE + kappa L_PENE, against central differences, in float64."""
    from model_learner_node.config import TrainConfig
    from peel_model.config import ModelConfig
    from peel_model.predictor import ForcePredictor, Normalization

    torch.manual_seed(3)
    cfg = ModelConfig(arch=arch, h=4, conv_channels=2, attention_hidden=2, lstm_hidden=2,
                      fc=(3,))
    norm = Normalization(in_mean=(5.0, 2.0, 3.0, 1.0), in_std=(3.0, 0.5, 1.0, 0.5),
                         out_mean=(0.0, 0.0), out_std=(0.3, 0.2), pad_compliance_mm_per_n=0.2)
    model = ForcePredictor(cfg, norm).double()
    # psi_lim low enough that L_PENE is active on part of the data (psi = 0.2 * fz ~ 0.3 mm)
    learner = MetaLearner(model, MamlConfig(alpha=0.05, m=1, support_slices=2, query_slices=2,
                                            slice_len=6, inner_steps=1),
                          train_cfg=TrainConfig(kappa=2.0, psi_lim_mm=0.3))
    trajs = [make_traj(40), make_traj(41, gain=1.4)]
    tasks = tasks_for(learner, trajs, seed=8)
    theta = learner.params()
    g = flat(learner.meta_gradient(theta, tasks))
    x0 = flat(theta)
    eps = 1e-6
    rng = np.random.default_rng(0)
    coords = rng.choice(x0.numel(), size=min(60, x0.numel()), replace=False)
    for i in coords:
        e = torch.zeros_like(x0)
        e[i] = eps
        fd = (learner.meta_objective(unflat(x0 + e, theta), tasks)
              - learner.meta_objective(unflat(x0 - e, theta), tasks)) / (2 * eps)
        assert float(g[i]) == pytest.approx(float(fd), rel=1e-4, abs=1e-7), i
    assert float(g.abs().max()) > 0
