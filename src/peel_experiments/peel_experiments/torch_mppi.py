"""pytorch_mppi as a policy over peel's forward model and cost, the reference arm of
``peel bench planner`` and ``peel bench safety`` (docs/planner.md).

pytorch_mppi (PyPI ``pytorch-mppi``) drives the same model and the same cost: its state is the
model's history window (h x 4) plus the time, flattened; one of its dynamics steps is one horizon
step = ``steps_per_horizon_step`` model steps with the velocity held, and it returns that step's
Eq. 4 + barrier cost in an extra state column that its running cost reads; its terminal cost is
the cost-to-go + phi of :class:`peel_planner_node.cost.Cost`. Its noise covariance is sigma0
(it has no Sigma re-estimation) and its control term is scaled by the same
``control_cost_scale``, so both optimise the same objective.
"""

from __future__ import annotations

from typing import Any

import torch

from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import PlannerConfig
from peel_planner_node.cost import Cost, Rollouts
from peel_planner_node.dynamics import history_window


class TorchMppiPolicy:
    """pytorch_mppi.MPPI over the forward model and peel's cost (module docstring)."""

    def __init__(self, predictor: Any, cost: Cost, cfg: PlannerConfig, seed: int = 0) -> None:
        from pytorch_mppi import MPPI

        self.pred, self.cost, self.cfg = predictor, cost, cfg
        self.h = int(predictor.h)
        m = cfg.mppi
        self.k, self.dt = m.steps_per_horizon_step, cfg.cost.dt_s
        nx = self.h * 4 + 2  # window, t, cost of the last step
        self.mppi = MPPI(self._dynamics, self._running_cost, nx,
                         torch.tensor([[m.sigma0]]), num_samples=m.n_samples, horizon=m.horizon,
                         lambda_=m.lam, u_min=torch.tensor([m.u_min]),
                         u_max=torch.tensor([m.u_max]), u_init=torch.tensor([m.u_init]),
                         terminal_state_cost=self._terminal)
        inv = 1.0 / m.sigma0
        scale = m.control_cost_scale
        self.mppi._compute_action_cost = lambda noise: scale * m.lam * noise * inv
        self.seed = seed
        self.reset()

    def reset(self) -> None:
        torch.manual_seed(self.seed)
        self.mppi.U = torch.full_like(self.mppi.U, self.cfg.mppi.u_init)

    def _dynamics(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        n = state.shape[0]
        win = state[:, :self.h * 4].reshape(n, self.h, 4)
        t = state[:, -2]
        v = action[:, 0]
        step_cost = torch.zeros(n, dtype=state.dtype)
        for _ in range(self.k):
            f = self.pred.predict(win, v)
            q_before = win[:, -1, 0]
            q = q_before + self.dt * v
            row = torch.stack([q, v, f[:, 0], f[:, 1]], dim=1)
            win = torch.cat([win[:, 1:], row.unsqueeze(1)], dim=1)
            # the running critics (Eq. 4 + barrier) of this one model step, as peel's planner
            one = Rollouts.predicted(q_before, 0.0, row[:, [0, 2, 3]].unsqueeze(1),
                                     self.cost.cfg)
            step_cost = step_cost + self.cost.running_cost(one)
            t = t + self.dt
        return torch.cat([win.reshape(n, -1), t.unsqueeze(1), step_cost.unsqueeze(1)], dim=1)

    @staticmethod
    def _running_cost(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return state[:, -1]

    def _terminal(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """phi + cost-to-go (the terminal critics) of the last state of each sample."""
        last = states[..., -1, :]  # [1, K, nx]
        q = last[..., self.h * 4 - 4].reshape(-1)
        t_end = float(last[..., -2].reshape(-1)[0])
        end = torch.stack([q, torch.zeros_like(q), torch.zeros_like(q)], dim=-1).unsqueeze(1)
        one = Rollouts.predicted(q, t_end - self.dt, end, self.cost.cfg)
        return self.cost.terminal_cost(one).reshape(last.shape[:-1])

    def state(self, history: Trajectory) -> torch.Tensor:
        win = torch.as_tensor(history_window(history, self.h), dtype=torch.float32)
        return torch.cat([win.reshape(-1), torch.tensor([float(history.t[-1]), 0.0])])

    def __call__(self, history: Trajectory) -> float:
        if float(history.q[-1]) >= self.cost.cfg.q_ter_mm:
            return 0.0
        with torch.inference_mode():
            u = self.mppi.command(self.state(history))
        m = self.cfg.mppi
        return float(min(max(float(u.reshape(-1)[0]), m.u_min), m.u_max))
