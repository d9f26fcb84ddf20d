"""The task cost J (paper Eq. 3-5) on rollouts (torch, batched) and on finished trajectories.

Immediate cost per 100 ms sample t (Eq. 4)::

    L_t = -w_dis (q_t - q_{t-1}) / (q_ter - q_0) + w_fX |F_RX_t| / F_lim^RX + w_fZ |F_RZ_t| / F_lim^RZ

terminal cost (Eq. 5): phi = 0 if q_ter is reached by t_max, ``phi_late`` (1) if it is reached
after t_max, ``phi_fail`` (2) if it is not reached and t > t_max; and (Eq. 3)
``J = phi + sum_t L_t`` where the integral of Eq. 3 is the sum over the 100 ms samples (the
paper's J values, 12-42, are sums, not sums times dt).

Planning only, cost-to-go (not in the paper): a rollout covers H x 0.5 s = 2.5 s of a 7-30 s
task, and over so short a window Eq. 4 barely depends on the speed (its progress term is worth
w_dis = 1 for the whole 25 mm, its force terms accrue per sample whatever the speed); what makes a
faster peel cheaper in Eq. 3 is the samples it saves *after* the horizon. The rollout cost
therefore ends with ``w_togo * (q_ter - q_H) / (q_ter - q_0)``, the cost of the samples still
needed: w_togo = (per-sample force cost) x (samples for the whole stroke at a reference speed)
= 0.25 (10 N + 6 N) / 20 N x 25 mm / (3.5 mm/s x 0.1 s) ~ 14 with the simulator's typical forces.

Planning only (issue 5, section 3, not in the paper): a barrier keeps plans clear of the 20 N
prewarning. Per predicted sample and per axis::

    B(F) = barrier_w * (max(0, |F| - barrier_start_n) / (f_prewarn_n - barrier_start_n))^2
           + barrier_stop_w * [|F| >= f_prewarn_n]

so a predicted force that would stop the task costs at least ``barrier_w + barrier_stop_w``
per sample (18 by default, against ~0.5 for the largest Eq. 4 force term). The barrier is
not part of :func:`episode_cost`, which is the paper's J.

In a rollout, positions are capped at q_ter and samples after the one that reaches q_ter cost
nothing (the task is over: Algorithm 2 line 2), so finishing sooner is cheaper.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .config import CostConfig


class Cost:
    """The cost of Eq. 3-5 with the planning barrier; see the module docstring."""

    def __init__(self, cfg: CostConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else CostConfig()
        c = self.cfg
        self._span = c.q_ter_mm - c.q0_mm
        self._bar_width = max(c.f_prewarn_n - c.barrier_start_n, 1e-9)
        # per-axis weights (x, z) of the batched rollout cost
        self._vec_vals = {
            "w_force": (c.w_fx / c.f_lim_x_n, c.w_fz / c.f_lim_z_n),
            "w_bar": (c.barrier_w / self._bar_width ** 2,) * 2,
            "w_stop": (c.barrier_stop_w,) * 2,
        }
        self._vec_key: tuple | None = None
        self._vecs: dict[str, torch.Tensor] = {}

    # ------------------------------------------------------------------ per sample (Eq. 4)
    def immediate(self, dq: torch.Tensor, fx: torch.Tensor, fz: torch.Tensor) -> torch.Tensor:
        """L_t of Eq. 4 for progress ``dq = q_t - q_{t-1}`` (mm) and forces (N), elementwise."""
        c = self.cfg
        return (-c.w_dis * dq / self._span + c.w_fx * fx.abs() / c.f_lim_x_n
                + c.w_fz * fz.abs() / c.f_lim_z_n)

    def barrier(self, fx: torch.Tensor, fz: torch.Tensor) -> torch.Tensor:
        """The planning barrier B(F_RX) + B(F_RZ) per sample (module docstring), elementwise."""
        c = self.cfg
        out = torch.zeros_like(fx)
        if c.barrier_w > 0.0 or c.barrier_stop_w > 0.0:
            for f in (fx.abs(), fz.abs()):
                over = torch.clamp(f - c.barrier_start_n, min=0.0) / self._bar_width
                out = out + c.barrier_w * over * over
                out = out + c.barrier_stop_w * (f >= c.f_prewarn_n).to(fx.dtype)
        return out

    def phi(self, reached: torch.Tensor, t_reach: torch.Tensor, t_end: float) -> torch.Tensor:
        """Terminal cost of Eq. 5: 0 / phi_late / phi_fail (a float tensor like ``t_reach``)."""
        c = self.cfg
        late = torch.full_like(t_reach, c.phi_late)
        zero = torch.zeros_like(t_reach)
        at_end = c.phi_fail if t_end > c.t_max_s else 0.0
        return torch.where(reached, torch.where(t_reach > c.t_max_s, late, zero),
                           torch.full_like(t_reach, at_end))

    # ------------------------------------------------------------------ rollouts (Alg. 2, 9-12)
    def rollout_cost(self, q_prev: float, t_now: float, out: torch.Tensor, *,
                     barrier: bool = True) -> torch.Tensor:
        """J of each predicted rollout: sum of L_t (+ barrier) over its samples plus phi.

        ``out`` is [N, S, 3] (q_mm, fx_N, fz_N) for the samples t_now + dt .. t_now + S dt;
        ``q_prev`` is the measured q at t_now. Returns [N].

        The same sums as :meth:`immediate` + :meth:`barrier` per sample, with both force axes
        handled as one [N, S, 2] tensor (weights as a 2-vector): about 20 tensor ops instead of
        45, which at N = 50 is a measurable part of a plan (docs/planner.md).
        """
        c = self.cfg
        q = torch.clamp(out[..., 0], max=c.q_ter_mm)
        s = q.shape[1]
        f = out[..., 1:3].abs()
        key = (f.dtype, f.device)
        if self._vec_key != key:
            self._vecs = {name: torch.tensor(vals, dtype=f.dtype, device=f.device)
                          for name, vals in self._vec_vals.items()}
            self._vec_key = key
        vec = self._vecs
        step = torch.matmul(f, vec["w_force"])  # Eq. 4 force terms [N, S]
        if barrier and (c.barrier_w > 0.0 or c.barrier_stop_w > 0.0):
            over = (f - c.barrier_start_n).clamp_(min=0.0)
            step += torch.matmul(over * over, vec["w_bar"])
            step += torch.matmul((f >= c.f_prewarn_n).to(f.dtype), vec["w_stop"])
        q_before = torch.empty_like(q)
        q_before[:, 0] = min(q_prev, c.q_ter_mm)
        q_before[:, 1:] = q[:, :-1]
        step -= (c.w_dis / self._span) * (q - q_before)  # Eq. 4 progress term
        active = q_before < c.q_ter_mm  # the task is still running in this sample
        total = (step * active).sum(dim=1)
        if c.w_togo > 0.0:  # cost-to-go of the distance still left after the horizon
            total += c.w_togo * (c.q_ter_mm - q[:, -1]) / self._span
        reached = q[:, -1] >= c.q_ter_mm
        # time of the first sample at or past q_ter (t_end where never reached)
        idx = torch.argmax((q >= c.q_ter_mm).to(torch.int8), dim=1).to(q.dtype)
        t_reach = t_now + (idx + 1.0) * c.dt_s
        t_end = t_now + s * c.dt_s
        return total + self.phi(reached, t_reach, t_end)

    # ------------------------------------------------------------------ finished tasks (Eq. 3)
    def episode_terms(self, traj: Trajectory) -> dict[str, float | bool]:
        """The parts of J for a finished trajectory: progress, force_x, force_z, phi, total."""
        return episode_cost_terms(traj, self)


def episode_cost_terms(traj: Trajectory, cost: Cost) -> dict[str, float | bool]:
    """J of Eq. 3 for a recorded trajectory, split into its terms (no planning barrier).

    The sum runs over the samples k = 1..T-1 (every 100 ms interval after t_0 at point C):
    L_k uses q_k - q_{k-1} and the forces measured at sample k. phi (Eq. 5) uses the last
    sample: 0 if q_ter was reached by t_max, phi_late if reached later, phi_fail otherwise -- a
    task ended unfinished by a safety stop also gets phi_fail (Eq. 5 does not cover it; an
    unfinished task is scored like one that ran out of time).
    """
    c = cost.cfg
    if len(traj) < 1:
        raise PeelError("trajectory 'q' is empty: no cost can be computed")
    q = np.minimum(np.asarray(traj.q, dtype=np.float64), c.q_ter_mm)
    fx = np.abs(np.asarray(traj.fx, dtype=np.float64))
    fz = np.abs(np.asarray(traj.fz, dtype=np.float64))
    for name, arr in (("q", q), ("fx", fx), ("fz", fz)):
        if not np.all(np.isfinite(arr)):
            raise PeelError(f"trajectory '{name}' holds non-finite values")
    span = c.q_ter_mm - c.q0_mm
    progress = float(-c.w_dis * (q[-1] - q[0]) / span)
    force_x = float(c.w_fx * fx[1:].sum() / c.f_lim_x_n)
    force_z = float(c.w_fz * fz[1:].sum() / c.f_lim_z_n)
    t_end = float(traj.t[-1] - traj.t[0])
    reached = bool(traj.q[-1] >= c.q_ter_mm - 1e-9) or traj.outcome == "done"
    phi = (c.phi_late if t_end > c.t_max_s else 0.0) if reached else c.phi_fail
    total = progress + force_x + force_z + phi
    return {"progress": progress, "force_x": force_x, "force_z": force_z, "phi": float(phi),
            "total": float(total), "t_cpl": t_end, "reached": reached}


def episode_cost(traj: Trajectory, cost: Cost) -> float:
    """J of Eq. 3 (sum of Eq. 4 over the 100 ms samples + phi of Eq. 5) of a finished task."""
    value = float(episode_cost_terms(traj, cost)["total"])
    if not math.isfinite(value):
        raise PeelError("trajectory cost is not finite")
    return value
