"""The planner on the simulator with an exact model (PeelEnv.rollout as Dynamics)."""

from __future__ import annotations

import torch

from peel_planner_node.config import load_planner_config
from peel_planner_node.cost import Cost, episode_cost
from peel_planner_node.dynamics import OracleDynamics
from peel_planner_node.mppi import Planner
from peel_sim_node.config import load_sim_config
from peel_sim_node.env import PeelEnv
from peel_sim_node.episode import run_episode

torch.set_num_threads(1)


def test_planner_with_exact_model_peels_faster_than_cautious_speed() -> None:
    env = PeelEnv(load_sim_config(), seed=0)
    try:
        cfg = load_planner_config().replace(**{"mppi.n_samples": 16})
        cost = Cost(cfg.cost)
        planner = Planner(OracleDynamics(env), cost, cfg)
        for seed in (3, 4):
            cautious = run_episode(env, lambda _h: 1.0, seed=seed)
            planner.reset()
            planned = run_episode(env, planner, seed=seed)
            assert cautious.outcome == "done"
            assert planned.outcome == "done", planner.stop
            assert planned.q[-1] >= 25.0
            assert planned.t_cpl < cautious.t_cpl
            assert episode_cost(planned, cost) < episode_cost(cautious, cost)
    finally:
        env.close()
