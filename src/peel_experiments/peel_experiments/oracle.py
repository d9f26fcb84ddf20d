"""The oracle (docs/experiments.md): the same MPPI planner with the plant's true dynamics as its model.

The OL-MPPI planner (Algorithm 2) rolls its N velocity sequences out through a learned forward
model F_theta. The oracle rolls them out through :meth:`peel_sim_node.env.PeelEnv.rollout`
instead: the plant's exact, noise-free dynamics from its current state (the env is left
unchanged). Everything else -- cost (Eq. 3-5 + barrier), N, H, lambda, Sigma, noise seed,
safety -- is the planner's, so the oracle's cost is the best any learned model can reach with
this planner, and ``J_method - J_oracle`` is the part of a method's cost that is due to its model.
"""

from __future__ import annotations

from typing import Any

import torch

from peel_planner_node.config import PlannerConfig
from peel_planner_node.cost import Cost
from peel_planner_node.dynamics import Dynamics, OracleDynamics, learned_dynamics
from peel_planner_node.mppi import Planner


def oracle_dynamics(env: Any, dtype: torch.dtype = torch.float32) -> Dynamics:
    """The plant's true dynamics ``env.rollout`` behind the planner's Dynamics protocol."""
    return OracleDynamics(env, dtype=dtype)


def oracle_planner(env: Any, config: PlannerConfig, cost: Cost | None = None) -> Planner:
    """An MPPI planner whose model is the plant ``env`` itself (see module docstring)."""
    dtype = torch.float64 if config.mppi.dtype == "float64" else torch.float32
    return Planner(oracle_dynamics(env, dtype), cost or Cost(config.cost), config)


def learned_planner(predictor: Any, config: PlannerConfig, cost: Cost | None = None) -> Planner:
    """The same planner with a learned forward model (OL-MPPI and the baselines)."""
    return Planner(learned_dynamics(predictor, config.dynamics), cost or Cost(config.cost),
                   config)
