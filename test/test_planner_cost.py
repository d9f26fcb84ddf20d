"""Cost (Eq. 3-5), planning barrier, SafetyMonitor (4.2) and the planner's config file."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml

from peel_msgs_py.errors import ParameterError, PeelError
from peel_msgs_py.params import config_dir
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import PlannerConfig, load_planner_config
from peel_planner_node.cost import Cost, episode_cost, episode_cost_terms
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
        want += (-c.w_dis * (q[k] - q[k - 1]) / 25.0 + c.w_fx * abs(fx[k]) / 20.0
                 + c.w_fz * abs(fz[k]) / 20.0)
    assert episode_cost(traj(q, fx, fz), Cost(c)) == pytest.approx(want)


def test_terminal_cost_eq5() -> None:
    cost = Cost(CFG.cost)
    n_late = 700  # 69.9 s > t_max = 60 s
    q = np.linspace(0.0, 25.0, n_late)
    zeros = np.zeros(n_late)
    assert episode_cost_terms(traj(q, zeros, zeros), cost)["phi"] == 1.0
    short = traj(np.linspace(0, 10, n_late), zeros, zeros, outcome="timeout")
    assert episode_cost_terms(short, cost)["phi"] == 2.0
    assert episode_cost_terms(traj([0.0, 25.0], [0, 0], [0, 0]), cost)["phi"] == 0.0
    stopped = traj([0.0, 3.0], [0.0, 21.0], [0.0, 0.0], outcome="safety_stop")
    assert episode_cost_terms(stopped, cost)["phi"] == 2.0
    with pytest.raises(PeelError, match="fx"):
        episode_cost(traj([0.0, 1.0], [0.0, np.nan], [0.0, 0.0]), cost)


def test_rollout_cost_masks_after_goal_and_rewards_finishing_sooner() -> None:
    cost = Cost(PlannerConfig().replace(**{"cost.barrier_w": 0.0, "cost.w_togo": 0.0}).cost)
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


def test_rollout_cost_equals_per_sample_terms_summed() -> None:
    """The batched rollout cost (both force axes in one tensor) is the sum over samples of
    immediate() + barrier(), masked after q_ter, + cost-to-go + phi, written out sample by
    sample here (float64, forces on both sides of the barrier onset and the prewarning)."""
    cost = Cost(CFG.cost)
    c = CFG.cost
    rng = np.random.default_rng(2)
    n, s = 7, 9
    q = torch.tensor(18.0 + np.cumsum(rng.uniform(0.0, 1.5, (n, s)), axis=1))
    fx = torch.tensor(rng.uniform(-22.0, 22.0, (n, s)))
    fz = torch.tensor(rng.uniform(-22.0, 22.0, (n, s)))
    got = cost.rollout_cost(18.0, 3.0, torch.stack([q, fx, fz], dim=-1))
    for k in range(n):
        total, q_prev, t_reach = 0.0, 18.0, None
        for t in range(s):
            qt = min(float(q[k, t]), c.q_ter_mm)
            if q_prev < c.q_ter_mm:
                one = lambda x: torch.tensor([x], dtype=torch.float64)  # noqa: E731
                total += float(cost.immediate(one(qt - q_prev), one(fx[k, t]), one(fz[k, t]))
                               + cost.barrier(one(fx[k, t]), one(fz[k, t])))
            if t_reach is None and qt >= c.q_ter_mm:
                t_reach = 3.0 + (t + 1) * c.dt_s
            q_prev = qt
        total += c.w_togo * (c.q_ter_mm - q_prev) / (c.q_ter_mm - c.q0_mm)
        total += c.phi_late if t_reach is not None and t_reach > c.t_max_s else 0.0
        assert float(got[k]) == pytest.approx(total, rel=1e-12, abs=1e-12)


def test_barrier_penalises_forces_near_prewarning() -> None:
    cost = Cost(CFG.cost)
    f = torch.tensor([0.0, 15.0, 17.5, 19.9, 20.0, 25.0])
    b = cost.barrier(f, torch.zeros_like(f))
    assert float(b[0]) == 0.0 and float(b[1]) == 0.0
    assert 0.0 < float(b[2]) < float(b[3]) < float(b[4])
    assert float(b[4]) >= CFG.cost.barrier_w + CFG.cost.barrier_stop_w
    assert float(cost.barrier(-f, torch.zeros_like(f))[3]) == pytest.approx(float(b[3]))


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
    assert new.cost.f_prewarn_n == new.safety.f_prewarn_n == 25.0
