"""Cost critics (Eq. 3-5, barrier, cost-to-go), SafetyMonitor (4.2) and the planner's config file."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml

from peel_msgs_py.errors import ParameterError, PeelError
from peel_msgs_py.params import config_dir
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import PlannerConfig, load_planner_config
from peel_planner_node.cost import (
    BarrierCritic,
    Cost,
    Critic,
    Rollouts,
    episode_cost,
    episode_cost_terms,
)
from peel_planner_node.mppi import Planner
from peel_planner_node.safety import SafetyMonitor

CFG = PlannerConfig()


def traj(q, fx, fz, outcome="done") -> Trajectory:
    n = len(q)
    return Trajectory(t=np.arange(n) * 0.1, q=q, v=np.zeros(n), u=np.zeros(n), fx=fx, fz=fz,
                      psi=np.full(n, np.nan), outcome=outcome)


def test_episode_cost_is_eq3_by_hand() -> None:
    c = CFG.cost
    q = [0.0, 10.0, 20.0, 25.0]
    fx = [1.0, -8.0, 10.0, 12.0]
    fz = [2.0, 4.0, -6.0, 5.0]
    want = 0.0
    for k in range(1, 4):  # Eq. 4 per 100 ms sample after t0
        want += (-c.progress.weight * (q[k] - q[k - 1]) / 25.0
                 + c.force_x.weight * abs(fx[k]) / c.force_x.f_lim_n
                 + c.force_z.weight * abs(fz[k]) / c.force_z.f_lim_n)
    assert episode_cost(traj(q, fx, fz), Cost(c)) == pytest.approx(want)
    terms = episode_cost_terms(traj(q, fx, fz), Cost(c))
    assert set(terms) == {"progress", "force_x", "force_z", "terminal", "total", "t_cpl",
                          "reached"}  # the paper's critics only: no barrier, no cost-to-go


def test_terminal_cost_eq5() -> None:
    cost = Cost(CFG.cost)
    n_late = 700  # 69.9 s > t_max = 60 s
    q = np.linspace(0.0, 25.0, n_late)
    zeros = np.zeros(n_late)
    assert episode_cost_terms(traj(q, zeros, zeros), cost)["terminal"] == 1.0
    short = traj(np.linspace(0, 10, n_late), zeros, zeros, outcome="timeout")
    assert episode_cost_terms(short, cost)["terminal"] == 2.0
    assert episode_cost_terms(traj([0.0, 25.0], [0, 0], [0, 0]), cost)["terminal"] == 0.0
    stopped = traj([0.0, 3.0], [0.0, 21.0], [0.0, 0.0], outcome="safety_stop")
    assert episode_cost_terms(stopped, cost)["terminal"] == 2.0
    with pytest.raises(PeelError, match="fx"):
        episode_cost(traj([0.0, 1.0], [0.0, np.nan], [0.0, 0.0]), cost)


def test_rollout_cost_masks_after_goal_and_rewards_finishing_sooner() -> None:
    cost = Cost(PlannerConfig().replace(**{"cost.barrier.weight": 0.0,
                                           "cost.cost_to_go.weight": 0.0}).cost)
    s = 5
    fast = torch.tensor([[24.5, 25.5, 26.5, 27.5, 28.5]])
    slow = torch.tensor([[24.6, 24.7, 24.8, 24.9, 25.0]])
    f = torch.full((1, s), 10.0)
    out_fast = torch.stack([fast, f, f], dim=-1)
    out_slow = torch.stack([slow, f, f], dim=-1)
    j_fast = cost.rollout_cost(24.0, 5.0, out_fast)
    j_slow = cost.rollout_cost(24.0, 5.0, out_slow)
    per_sample = 0.25 * 10 / 20 * 2
    assert float(j_fast) == pytest.approx(-1.0 * 1.0 / 25.0 + 2 * per_sample, rel=1e-5)
    assert float(j_slow) == pytest.approx(-1.0 * 1.0 / 25.0 + 5 * per_sample, rel=1e-5)
    late = cost.rollout_cost(24.0, 59.9, out_slow)  # reaches q_ter at 60.4 s > t_max
    assert float(late - j_slow) == pytest.approx(1.0)


def test_rollout_cost_is_the_critics_per_sample_costs_summed() -> None:
    """One code path: the planner's batched rollout cost equals, sequence by sequence and
    sample by sample, the critics run on one-sample rollouts (as a step-by-step caller like
    pytorch_mppi uses them) summed while the task runs, + cost-to-go + phi, with Eq. 4 and the
    barrier written out by hand beside them (float64, forces on both sides of the barrier
    onset and the prewarning)."""
    cost = Cost(CFG.cost)
    c = CFG.cost
    rng = np.random.default_rng(2)
    n, s = 7, 9
    q = torch.tensor(18.0 + np.cumsum(rng.uniform(0.0, 1.5, (n, s)), axis=1))
    fx = torch.tensor(rng.uniform(-22.0, 22.0, (n, s)))
    fz = torch.tensor(rng.uniform(-22.0, 22.0, (n, s)))
    got = cost.rollout_cost(18.0, 3.0, torch.stack([q, fx, fz], dim=-1))
    width = c.barrier.f_prewarn_n - c.barrier.start_n

    def by_hand(dq: float, f1: float, f2: float) -> float:
        out = (-c.progress.weight * dq / 25.0 + c.force_x.weight * abs(f1) / c.force_x.f_lim_n
               + c.force_z.weight * abs(f2) / c.force_z.f_lim_n)
        for f in (abs(f1), abs(f2)):
            out += c.barrier.weight * (max(0.0, f - c.barrier.start_n) / width) ** 2
            out += c.barrier.stop_weight * (f >= c.barrier.f_prewarn_n)
        return out

    for k in range(n):
        total, q_prev, t_reach = 0.0, 18.0, None
        for t in range(s):
            qt = min(float(q[k, t]), c.q_ter_mm)
            one = Rollouts.predicted(q_prev, 0.0, torch.tensor([[[float(q[k, t]),
                                                                  float(fx[k, t]),
                                                                  float(fz[k, t])]]],
                                                               dtype=torch.float64), c)
            step = float(cost.running_cost(one)[0])
            if q_prev < c.q_ter_mm:
                assert step == pytest.approx(by_hand(qt - q_prev, float(fx[k, t]),
                                                     float(fz[k, t])), rel=1e-12, abs=1e-12)
            else:
                assert step == 0.0  # the task is over
            total += step
            if t_reach is None and qt >= c.q_ter_mm:
                t_reach = 3.0 + (t + 1) * c.dt_s
            q_prev = qt
        total += c.cost_to_go.weight * (c.q_ter_mm - q_prev) / (c.q_ter_mm - c.q0_mm)
        total += c.terminal.phi_late if t_reach is not None and t_reach > c.t_max_s else 0.0
        assert float(got[k]) == pytest.approx(total, rel=1e-12, abs=1e-12)


def test_each_critic_has_its_own_prefix_and_weight() -> None:
    """cost.<critic>.weight scales exactly that critic's N costs (the barrier's two parts have
    a weight each: weight and stop_weight); the objective is their sum."""
    out = torch.stack([torch.tensor([[20.0, 21.0, 22.0]]), torch.tensor([[16.0, 18.0, 21.0]]),
                       torch.tensor([[3.0, -4.0, 5.0]])], dim=-1).double()
    base = Cost(CFG.cost).rollout_terms(19.0, 1.0, out)
    assert set(base) == {"progress", "force_x", "force_z", "terminal", "barrier", "cost_to_go"}
    for name in base:
        double = {f"cost.{name}.{w}": 2.0 * getattr(getattr(CFG.cost, name), w)
                  for w in ("weight", "stop_weight") if f"cost.{name}.{w}" in CFG.to_params()}
        doubled = Cost(CFG.replace(**double).cost).rollout_terms(19.0, 1.0, out)
        for other, value in doubled.items():
            want = 2.0 * base[other] if other == name else base[other]
            torch.testing.assert_close(value, want)
    total = Cost(CFG.cost).rollout_cost(19.0, 1.0, out)
    torch.testing.assert_close(total, sum(base.values()))


def test_a_new_critic_joins_the_objective_but_not_the_papers_j() -> None:
    class Slow(Critic):
        name = "slow"

        def score(self, r: Rollouts) -> torch.Tensor:
            return 3.0 * (r.active.sum(dim=1))

    cost = Cost(CFG.cost, critics=[*Cost(CFG.cost).critics, Slow()])
    out = torch.stack([torch.tensor([[1.0, 2.0]]), torch.ones(1, 2), torch.ones(1, 2)], dim=-1)
    terms = cost.rollout_terms(0.0, 0.0, out)
    assert float(terms["slow"][0]) == 6.0
    assert float(cost.rollout_cost(0.0, 0.0, out)[0]) == pytest.approx(
        float(Cost(CFG.cost).rollout_cost(0.0, 0.0, out)[0]) + 6.0)
    finished = traj([0.0, 10.0, 25.0], [1.0, 2.0, 3.0], [1.0, 1.0, 1.0])
    assert episode_cost(finished, cost) == episode_cost(finished, Cost(CFG.cost))
    with pytest.raises(PeelError, match="distinct"):
        Cost(CFG.cost, critics=[Slow(), Slow()])


def test_barrier_penalises_forces_near_prewarning() -> None:
    barrier = BarrierCritic(CFG.cost.barrier)
    f = torch.tensor([[0.0, 15.0, 17.5, 19.9, 20.0, 25.0]])
    zero = torch.zeros_like(f)
    r = Rollouts.predicted(0.0, 0.0, torch.stack([zero, f, zero], dim=-1), CFG.cost)
    b = barrier.sample_costs(r)[0]
    assert float(b[0]) == 0.0 and float(b[1]) == 0.0
    assert 0.0 < float(b[2]) < float(b[3]) < float(b[4])
    assert float(b[4]) >= CFG.cost.barrier.weight + CFG.cost.barrier.stop_weight
    mirrored = Rollouts.predicted(0.0, 0.0, torch.stack([zero, zero, -f], dim=-1), CFG.cost)
    torch.testing.assert_close(barrier.sample_costs(mirrored)[0], b)


def test_safety_monitor_reasons_and_latch() -> None:
    m = SafetyMonitor(CFG.safety)
    assert m.check_sample(1.0, 5.0, 19.99, 3.0) is None
    stop = m.check_sample(1.1, 5.1, 20.0, 3.0)
    assert stop.reason == "prewarning_fx" and stop.outcome == "safety_stop"
    assert m.check_sample(1.2, 5.2, 0.0, 0.0).reason == "prewarning_fx"  # latched
    m.reset()
    assert m.check_sample(1.0, 5.0, 0.0, -20.5).reason == "prewarning_fz"
    m.reset()
    assert m.check_sample(60.0, 5.0, 0.0, 0.0) is None
    assert m.check_sample(60.1, 5.0, 0.0, 0.0).reason == "timeout"
    m.reset()
    assert m.check_sample(8.0, 25.0, 0.0, 0.0).outcome == "done"


def test_planner_returns_zero_and_reason_after_prewarning() -> None:
    class Dyn:
        def rollout(self, history, v):
            q = float(history.q[-1]) + 0.1 * torch.cumsum(v, 1)
            return torch.stack([q, torch.ones_like(v), torch.ones_like(v)], dim=-1)

    planner = Planner(Dyn(), Cost(CFG.cost), CFG)
    ok = traj([0.0, 0.1], [1.0, 2.0], [1.0, 2.0], outcome="running")
    assert planner.plan(ok) > 0.0
    bad = traj([0.0, 0.1, 0.2], [1.0, 2.0, 20.0], [1.0, 2.0, 2.0], outcome="running")
    assert planner.plan(bad) == 0.0
    assert planner.stop.reason == "prewarning_fx"
    assert planner.plan(ok) == 0.0
    planner.reset()
    assert planner.stop is None and planner.plan(ok) > 0.0


def test_shipped_config_file_documents_and_loads() -> None:
    path = config_dir() / "peel_planner_node.yaml"
    doc = yaml.safe_load(path.read_text())
    params = doc["peel_planner_node"]["ros__parameters"]
    assert params["mppi"]["n_samples"] == 50 and params["mppi"]["horizon"] == 5
    assert params["mppi"]["lambda"] == 0.1
    cfg = load_planner_config()
    assert cfg.to_params() == PlannerConfig.from_params(cfg.to_params()).to_params()
    assert cfg.mppi.horizon * cfg.mppi.steps_per_horizon_step * cfg.cost.dt_s == pytest.approx(2.5)
    for line in path.read_text().splitlines():  # every constant carries a comment
        if ":" in line and not line.strip().startswith("#") and line.split(":", 1)[1].strip():
            assert "#" in line, line


def test_bad_parameters_name_the_field(tmp_path) -> None:
    with pytest.raises(ParameterError, match=r"mppi\.n_samples"):
        PlannerConfig.from_params({"mppi.n_samples": 0})
    with pytest.raises(ParameterError, match=r"mppi\.lambda"):
        PlannerConfig.from_params({"mppi.lambda": "big"})
    with pytest.raises(ParameterError, match="control_period_s"):
        PlannerConfig.from_params({"mppi.steps_per_horizon_step": 3})
    with pytest.raises(ParameterError, match="u_min"):
        PlannerConfig.from_params({"mppi.u_min": 5.0, "mppi.u_max": 1.0})
    ok = PlannerConfig.from_params({"mppi.steps_per_horizon_step": 1, "task.control_period_s": 0.1})
    assert ok.mppi.steps_per_horizon_step == 1
    override = tmp_path / "o.yaml"
    override.write_text("peel_planner_node:\n  ros__parameters:\n    mppi:\n      horizon: 7\n")
    assert load_planner_config(override).mppi.horizon == 7


def test_config_round_trips_every_parameter() -> None:
    """to_params() names every declared parameter once; from_params() of it rebuilds the config,
    and a changed parameter lands in its field (task.* and safety.* feed several sections)."""
    from peel_planner_node.config import PARAM_SPECS

    cfg = load_planner_config()
    flat = cfg.to_params()
    assert set(flat) == {spec.name for spec in PARAM_SPECS}
    assert PlannerConfig.from_params(flat) == cfg
    new = cfg.replace(**{"mppi.lambda": 0.3, "task.dt_s": 0.05, "task.control_period_s": 0.25,
                         "safety.f_prewarn_n": 25.0})
    assert new.mppi.lam == 0.3 and new.mppi.dt_s == new.cost.dt_s == 0.05
    assert new.cost.barrier.f_prewarn_n == new.safety.f_prewarn_n == 25.0
    assert new.dynamics.dt_s == 0.05  # task.dt_s feeds the dynamics too
