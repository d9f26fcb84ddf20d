"""The cost as a sum of critics: the paper's J (Eq. 3-5) plus two planning-only terms.

Each critic scores N sample sequences (:class:`Rollouts`) and returns N costs, with its own
weight and parameters under its own config prefix (``cost.<name>.*``, nav2's critic layout):

==============  =====  ========================================================================
critic          paper  cost of one sequence
==============  =====  ========================================================================
``progress``    Eq. 4  sum_t -w_dis (q_t - q_{t-1}) / (q_ter - q_0)
``force_x``     Eq. 4  sum_t w_fX |F_RX_t| / F_lim^RX
``force_z``     Eq. 4  sum_t w_fZ |F_RZ_t| / F_lim^RZ
``terminal``    Eq. 5  phi: 0 if q_ter is reached by t_max, phi_late after it, phi_fail if not
``barrier``     no     sum_t B(F_RX_t) + B(F_RZ_t), B below
``cost_to_go``  no     w_togo (q_ter - q_S) / (q_ter - q_0), the distance left at the end
==============  =====  ========================================================================

The paper's J (Eq. 3, used in every report) is the sum of the paper's critics over a finished
task (:func:`episode_cost`); the planner's objective (:meth:`Cost.rollout_cost`) is the sum of
all of them over a predicted horizon. Both are the same critics on the same :class:`Rollouts`
record: a finished trajectory is one sequence (N = 1) whose last sample ends the task. The
integral of Eq. 3 is the sum over the 100 ms samples (the paper's J values, 12-42, are sums).

Running critics (Eq. 4 terms, barrier) cost ``sum_t l_t`` over the samples in which the task
still runs: positions are capped at q_ter and the samples after the one that reaches it cost
nothing (Algorithm 2 line 2), so finishing sooner is cheaper.

Planning only, cost-to-go: a rollout covers H x 0.5 s = 2.5 s of a 7-30 s task, and over so
short a window Eq. 4 barely depends on the speed (its progress term is worth w_dis = 1 for the
whole 25 mm, its force terms accrue per sample whatever the speed); what makes a faster peel
cheaper in Eq. 3 is the samples it saves *after* the horizon: w_togo = (per-sample force cost) x
(samples for the whole stroke at a reference speed) = 0.25 (10 N + 6 N) / 20 N x 25 mm /
(3.5 mm/s x 0.1 s) ~ 14 with the simulator's typical forces.

Planning only, barrier (docs/planner.md): per sample and axis::

    B(F) = weight * (max(0, |F| - start_n) / (f_prewarn_n - start_n))^2
           + stop_weight * [|F| >= f_prewarn_n]

so a predicted force that would stop the task costs at least ``weight + stop_weight`` per
sample (18 by default, against ~0.5 for the largest Eq. 4 force term). With the force margin
m_a of the planner's guard (Eq. M1, :mod:`~.guard`) the limit is tightened per axis (Eq. M2)::

    B_a(F) = weight * (max(0, |F| - start_n) / max(f_prewarn_n - m_a - start_n, 1 N))^2
             + stop_weight * [|F| >= f_prewarn_n - m_a]

which is B(F) for m_a = 0.

A new term is a new :class:`Critic` (``name``, ``in_paper``, ``score(rollouts) -> [N]``) passed
to ``Cost(cfg, critics=[...])``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .config import BarrierConfig, CostConfig, ForceConfig


@dataclass
class Rollouts:
    """What the critics score: N sequences of S samples (nav2's ``CriticData``).

    ``q`` [N, S] positions capped at q_ter (mm); ``dq`` [N, S] = q_t - q_{t-1} (capped);
    ``forces`` [N, S, 2] (F_RX, F_RZ in N; ``fx``, ``fz`` are its columns); ``active`` [N, S]
    1 where the task still runs in sample t (q_{t-1} < q_ter), else 0; ``t_end`` the last
    sample's time from the task start (s); ``task_over``: the last sample ends the task (a
    finished trajectory) rather than a planning horizon. :meth:`reach` gives whether and when
    each sequence reached q_ter (computed on first use: only phi needs it, and only late in a
    task). ``margin`` [2]: the force margin m_a per axis (Eq. M1) the barrier adds to |F_a|
    (Eq. M2), None for none.
    """

    q: torch.Tensor
    dq: torch.Tensor
    forces: torch.Tensor
    active: torch.Tensor
    t_end: float
    task_over: bool
    q_ter: float
    dt: float
    reached: torch.Tensor | None = None
    t_reach: torch.Tensor | None = None
    margin: torch.Tensor | None = None

    @property
    def fx(self) -> torch.Tensor:
        return self.forces[..., 0]

    @property
    def fz(self) -> torch.Tensor:
        return self.forces[..., 1]

    def reach(self) -> tuple[torch.Tensor, torch.Tensor]:
        """[N] q_ter reached by the last sample, and [N] the time of the first sample at q_ter
        (the last sample's time where never)."""
        if self.reached is None:
            s = self.q.shape[1]
            t = self.t_end - self.dt * torch.arange(s - 1, -1, -1, dtype=self.q.dtype)
            hit = self.q >= self.q_ter
            first = torch.argmax(hit.to(torch.int8), dim=1)  # first sample at q_ter (0: none)
            self.reached = hit[:, -1]
            self.t_reach = torch.where(self.reached, t[first], t[-1])
        return self.reached, self.t_reach

    @classmethod
    def predicted(cls, q_prev: float | torch.Tensor, t_now: float, out: torch.Tensor,
                  cfg: CostConfig, margin: torch.Tensor | None = None) -> Rollouts:
        """Rollouts ``out`` [N, S, 3] (q_mm, fx_N, fz_N) of the samples t_now + dt .. t_now +
        S dt (S >= 1), from the measured ``q_prev`` at t_now (float, or [N] per sequence);
        ``margin`` [2] per axis (Eq. M2) or None."""
        q, dq, active = _positions(q_prev, out[..., 0], cfg.q_ter_mm)
        return cls(q=q, dq=dq, forces=out[..., 1:3], active=active,
                   t_end=t_now + q.shape[1] * cfg.dt_s, task_over=False, q_ter=cfg.q_ter_mm,
                   dt=cfg.dt_s, margin=margin)

    @classmethod
    def measured(cls, traj: Trajectory, cfg: CostConfig) -> Rollouts:
        """A finished trajectory as one sequence (float64): its samples 1..T-1 after t_0 (each
        100 ms interval); reached if q_ter was reached or the outcome is ``done``, at the end
        time t_cpl."""
        if len(traj) < 1:
            raise PeelError("trajectory 'q' is empty: no cost can be computed")
        cols = {name: np.asarray(getattr(traj, name), dtype=np.float64)
                for name in ("t", "q", "fx", "fz")}
        for name in ("q", "fx", "fz"):
            if not np.all(np.isfinite(cols[name])):
                raise PeelError(f"trajectory '{name}' holds non-finite values")
        q, dq, active = _positions(float(cols["q"][0]), torch.tensor(cols["q"][None, 1:]),
                                   cfg.q_ter_mm)
        t_end = float(cols["t"][-1] - cols["t"][0])
        reached = bool(cols["q"][-1] >= cfg.q_ter_mm - 1e-9) or traj.outcome == "done"
        forces = torch.tensor(np.stack([cols["fx"][1:], cols["fz"][1:]], axis=-1)[None])
        return cls(q=q, dq=dq, forces=forces, active=active, t_end=t_end, task_over=True,
                   q_ter=cfg.q_ter_mm, dt=cfg.dt_s, reached=torch.tensor([reached]),
                   t_reach=torch.tensor([t_end], dtype=torch.float64))


def _positions(q_prev: float | torch.Tensor, q_raw: torch.Tensor,
               q_ter: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """q capped at q_ter [N, S], its increments dq, and the 0/1 mask of the samples in which
    the task still runs (the sample before has not reached q_ter); ``q_prev`` is the position
    before the first sample, one for all (float) or one per sequence ([N])."""
    q = torch.clamp(q_raw, max=q_ter)
    q_before = torch.empty_like(q)
    q_before[:, 0] = (torch.clamp(q_prev, max=q_ter) if isinstance(q_prev, torch.Tensor)
                      else min(float(q_prev), q_ter))
    q_before[:, 1:] = q[:, :-1]
    return q, q - q_before, (q_before < q_ter).to(q.dtype)


# ---------------------------------------------------------------- critics
class Critic:
    """One cost term: ``score(rollouts) -> [N]``; ``in_paper``: part of the paper's J."""

    name: str = "critic"
    in_paper: bool = False

    def score(self, r: Rollouts) -> torch.Tensor:
        raise NotImplementedError


class RunningCritic(Critic):
    """A sum over samples of a per-sample cost l_t, over the samples where the task runs."""

    def sample_costs(self, r: Rollouts) -> torch.Tensor:
        """l_t per sample, [N, S]."""
        raise NotImplementedError

    def score(self, r: Rollouts) -> torch.Tensor:
        return (self.sample_costs(r) * r.active).sum(dim=1)


class ProgressCritic(RunningCritic):
    """Eq. 4, progress: ``-w_dis (q_t - q_{t-1}) / (q_ter - q_0)``."""

    name, in_paper = "progress", True

    def __init__(self, weight: float, span_mm: float) -> None:
        self.per_mm = weight / span_mm

    def sample_costs(self, r: Rollouts) -> torch.Tensor:
        return -self.per_mm * r.dq

    def score(self, r: Rollouts) -> torch.Tensor:  # the same sum in fewer ops
        return -self.per_mm * (r.dq * r.active).sum(dim=1)


class ForceCritic(RunningCritic):
    """Eq. 4, one force axis: ``w_f |F_t| / F_lim``."""

    in_paper = True

    def __init__(self, name: str, axis: str, cfg: ForceConfig) -> None:
        if axis not in ("fx", "fz"):
            raise PeelError(f"force critic axis must be 'fx' or 'fz', got {axis!r}")
        self.name, self.axis = name, axis
        self.per_n = cfg.weight / cfg.f_lim_n

    def sample_costs(self, r: Rollouts) -> torch.Tensor:
        return self.per_n * getattr(r, self.axis).abs()


class BarrierCritic(RunningCritic):
    """Planning only: B(F_RX_t) + B(F_RZ_t) (module docstring); with the margin m_a of Eq. M1
    in the rollouts, the limit of each axis is f_prewarn_n - m_a (Eq. M2, :meth:`tightened`)."""

    name = "barrier"

    def __init__(self, cfg: BarrierConfig) -> None:
        self.cfg = cfg
        self.per_n2 = cfg.weight / max(cfg.f_prewarn_n - cfg.start_n, 1e-9) ** 2
        self._axis_weights: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def sample_costs(self, r: Rollouts) -> torch.Tensor:
        c = self.cfg
        f = r.forces.abs()  # both axes at once, [N, S, 2]
        if r.margin is not None:
            return self.tightened(f, r.margin.to(f.dtype))
        key = (f.dtype, f.device)
        if key not in self._axis_weights:  # the sums over the 2 axes as matmuls (faster)
            self._axis_weights[key] = tuple(torch.full((2,), w, dtype=f.dtype, device=f.device)
                                            for w in (self.per_n2, c.stop_weight))
        quadratic, stop = self._axis_weights[key]
        over = (f - c.start_n).clamp_(min=0.0)
        out = torch.matmul(over * over, quadratic)
        if c.stop_weight:
            out += torch.matmul((f >= c.f_prewarn_n).to(f.dtype), stop)
        return out


    def tightened(self, f: torch.Tensor, margin: torch.Tensor) -> torch.Tensor:
        """Eq. M2: B_a with the limit f_prewarn_n - m_a per axis, summed over the two axes: the
        stop term from there on and (``margin_ramp``) the ramp from start_n reaching ``weight``
        there, at least 1 N above start_n; without ``margin_ramp`` the ramp is the barrier's."""
        c = self.cfg
        lim = c.f_prewarn_n - margin
        ramp_end = lim if c.margin_ramp else torch.full_like(lim, c.f_prewarn_n)
        span = (ramp_end - c.start_n).clamp(min=1.0)
        over = (f - c.start_n).clamp(min=0.0) / span
        out = c.weight * (over * over).sum(dim=-1)
        if c.stop_weight:
            out += c.stop_weight * (f >= lim).to(f.dtype).sum(dim=-1)
        return out


class TerminalCritic(Critic):
    """Eq. 5: phi = 0 (q_ter reached by t_max), phi_late (reached after t_max), phi_fail (not
    reached: at the end of a task, or past t_max). A task ended unfinished by a safety stop gets
    phi_fail too (Eq. 5 does not cover it: it is scored like one that ran out of time)."""

    name, in_paper = "terminal", True

    def __init__(self, cfg: CostConfig) -> None:
        c = cfg.terminal
        self.t_max, self.late, self.fail = cfg.t_max_s, c.weight * c.phi_late, c.weight * c.phi_fail

    def score(self, r: Rollouts) -> torch.Tensor:
        if not r.task_over and r.t_end <= self.t_max:  # reached or not: phi = 0 until t_max
            return torch.zeros(r.q.shape[0], dtype=r.q.dtype, device=r.q.device)
        reached, t_reach = r.reach()
        on_time = torch.where(t_reach > self.t_max, self.late, 0.0).to(t_reach.dtype)
        failed = self.fail if (r.task_over or r.t_end > self.t_max) else 0.0
        return torch.where(reached, on_time, torch.full_like(t_reach, failed))


class CostToGoCritic(Critic):
    """Planning only: ``w_togo (q_ter - q_S) / (q_ter - q_0)`` for the distance left."""

    name = "cost_to_go"

    def __init__(self, weight: float, cfg: CostConfig) -> None:
        self.per_mm, self.q_ter = weight / (cfg.q_ter_mm - cfg.q0_mm), cfg.q_ter_mm

    def score(self, r: Rollouts) -> torch.Tensor:
        return self.per_mm * (self.q_ter - r.q[:, -1])


def default_critics(cfg: CostConfig) -> tuple[Critic, ...]:
    """The critics of config/peel_planner_node.yaml's ``cost:`` section, paper terms first."""
    span = cfg.q_ter_mm - cfg.q0_mm
    return (ProgressCritic(cfg.progress.weight, span), ForceCritic("force_x", "fx", cfg.force_x),
            ForceCritic("force_z", "fz", cfg.force_z), TerminalCritic(cfg),
            BarrierCritic(cfg.barrier), CostToGoCritic(cfg.cost_to_go.weight, cfg))


# ---------------------------------------------------------------- the sum
class Cost:
    """The planner's objective: the sum of its critics; the paper's J: the paper's critics.

    ``Cost(cfg)`` holds :func:`default_critics`; ``Cost(cfg, critics=[...])`` any others.
    A critic with weight 0 is dropped (it costs nothing).
    """

    def __init__(self, cfg: CostConfig | None = None,
                 critics: Sequence[Critic] | None = None) -> None:
        self.cfg = cfg if cfg is not None else CostConfig()
        self.critics = tuple(critics) if critics is not None else default_critics(self.cfg)
        names = [c.name for c in self.critics]
        if len(set(names)) != len(names):
            raise PeelError(f"cost critics must have distinct names, got {names}")
        self.paper_critics = tuple(c for c in self.critics if c.in_paper)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.critics)

    def terms(self, r: Rollouts, *, paper_only: bool = False) -> dict[str, torch.Tensor]:
        """Each critic's N costs, by name (diagnostics: which term drives a plan)."""
        return {c.name: c.score(r) for c in (self.paper_critics if paper_only else self.critics)}

    def rollout_terms(self, q_prev: float, t_now: float, out: torch.Tensor,
                      margin: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """:meth:`terms` of predicted rollouts ``out`` [N, S, 3] (:meth:`Rollouts.predicted`),
        the barrier on |F| + ``margin`` (Eq. M2) when one is given."""
        return self.terms(Rollouts.predicted(q_prev, t_now, out, self.cfg, margin))

    def rollout_cost(self, q_prev: float, t_now: float, out: torch.Tensor) -> torch.Tensor:
        """The planner's objective of each rollout, [N]: the sum of every critic."""
        return total(self.rollout_terms(q_prev, t_now, out))

    def running_cost(self, r: Rollouts) -> torch.Tensor:
        """Sum of the running critics only (for a caller that steps sample by sample)."""
        return total({c.name: c.score(r) for c in self.critics if isinstance(c, RunningCritic)})

    def terminal_cost(self, r: Rollouts) -> torch.Tensor:
        """Sum of the critics that score the end of a sequence (phi, cost-to-go)."""
        return total({c.name: c.score(r) for c in self.critics
                      if not isinstance(c, RunningCritic)})

    def episode_terms(self, traj: Trajectory) -> dict[str, float | bool]:
        """The paper's J of a finished trajectory split into its critics (see
        :func:`episode_cost_terms`)."""
        return episode_cost_terms(traj, self)


def total(terms: dict[str, torch.Tensor]) -> torch.Tensor:
    """The sum of the critics' costs."""
    if not terms:
        raise PeelError("the cost has no critics")
    return torch.stack(list(terms.values())).sum(dim=0)


def episode_cost_terms(traj: Trajectory, cost: Cost) -> dict[str, float | bool]:
    """J of Eq. 3 for a recorded trajectory, split into the paper's critics (no planning term).

    The critics run on :meth:`Rollouts.measured`: the samples k = 1..T-1 (every 100 ms interval
    after t_0 at point C), L_k with q_k - q_{k-1} and the forces measured at sample k; phi from
    the last sample. Returns each paper critic by name, ``total`` (= J), ``t_cpl``, ``reached``.
    """
    r = Rollouts.measured(traj, cost.cfg)
    terms = {name: float(v[0]) for name, v in cost.terms(r, paper_only=True).items()}
    return {**terms, "total": float(sum(terms.values())), "t_cpl": r.t_end,
            "reached": bool(r.reach()[0][0])}


def episode_cost(traj: Trajectory, cost: Cost) -> float:
    """J of Eq. 3 (sum of Eq. 4 over the 100 ms samples + phi of Eq. 5) of a finished task."""
    value = float(episode_cost_terms(traj, cost)["total"])
    if not math.isfinite(value):
        raise PeelError("trajectory cost is not finite")
    return value
