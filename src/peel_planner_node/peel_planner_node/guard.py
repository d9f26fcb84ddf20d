"""Holding the force limit under model error (docs/planner.md, Eq. M1-M5; not in the paper).

The planner's model is wrong by an amount it can measure: at every control instant the forces
it predicted for the command that went out are compared with the forces then measured, sample
by sample (the 1-5 model steps of the control period the command was in force).

* Eq. M1, the margin per axis a in {RX, RZ}: a conformal (distribution-free) upper quantile of
  the last ``window`` errors W_a, n = |W_a|::

      e = |F_a measured| - |F_a predicted|          (> 0: the model under-predicted)
      r = ceil((n + 1) (1 - delta))
      m_a = min(m_max, max(0, e_(r)))   (e_(r): the r-th smallest of W_a; r > n: m_max)
                                                              once n >= min_count,
      m_a = init_n                                            before.

  If the next error is exchangeable with those in W_a, P(e > m_a) <= delta: the chance
  constraint of Eq. M2 below. Only under-prediction tightens the limit, and as the errors of a
  model that is right replace those of one that was wrong, m_a falls back (to 0 for an exact
  model): the limit widens again.
* Eq. M2, the tightened limit (a chance constraint): the barrier critic and the check see
  |F_a| + m_a, i.e. predicted forces must stay below f_prewarn - m_a, so that
  P(|F_a measured| >= f_prewarn) <= P(e > m_a) <= delta per sample.
* Eq. M3, the check of the command: candidate speeds c_0 = u_min < ... < c_{M-1} = max_k v^k_0,
  each rolled out as c_j for the first control period and then the prior plan capped at c_j,
  in the same batch as the N samples; g_j = max_{t, a} (|F_a,t| + m_a) - f_prewarn. The command
  is min(u*, c*) with c* the speed where g first crosses 0 (linear between the last candidate
  with g < 0 and the first with g >= 0; none: u*).
* Eq. M4, the fallback when g_0 >= 0 (even u_min is predicted over the tightened limit):
  ``least_force`` sends c_f, f = argmin_j g_j (the candidate with the lowest predicted peak,
  the slowest among equals), ``u_min`` sends c_0. Both are >= u_min > 0: the blade never stops,
  so q reaches q_ter within (q_ter - q_0) / u_min (50 s for 25 mm at 0.5 mm/s) < t_max.
* Eq. M5, the slowdown on the measured force (``safety.slowdown.*``): Eq. M1's margin is a
  quantile over the last ``window`` errors, and a stick-slip sawtooth whose teeth climb at
  speed reaches the limit before the quantile follows it. With F_hat = max_{t, a} |F_a,t| over the samples measured in
  the control period that just ended and u_prev the command that was in force::

      s = clip((f_prewarn - F_hat) / (f_prewarn - f_s), 0, 1)
      u_out = max(u_min, min(u_out, s u_prev))      when F_hat >= f_s

  (nav2 collision_monitor's slowdown zone, with force for distance). It reads no model.
  Eq. M6, the same zone at every sample, is the plant bridges' (:mod:`peel_bridge.slowdown`).
* Eq. M7, the horizon margin (``safety.margin.lead_*``): Eq. M1 measures the model over the
  first control period only, but the barrier and the check act over the whole horizon of
  L = H k model steps, where a model's error grows. Each plan replays the model from the sample
  L steps back, fed the commands then in force (the trajectory's ``u``), and keeps the errors
  e_l = |F_a measured| - |F_a replayed| of all l = 1..L in a window of its own, W'_a::

      m'_a = Eq. M1's quantile over W'_a (0 while |W'_a| < min_count)
      m_a  = max(Eq. M1's m_a, m'_a)

  So a model that under-predicts late in the horizon gets a margin that Eq. M1 does not see,
  and one that over-predicts there (m'_a = 0) keeps Eq. M1's. A model the history cannot
  replay (the oracle's plant, which rolls out from its own state) has no Eq. M7.
* Eq. M8, the margin carried over (``safety.margin.carry_over``): each task starts with an
  empty W_a and m_a = init_n until min_count errors exist (1 s), when a peel's force may already
  climb fast. With Eq. M8 a task's W_a starts as the last task's (its last ``window`` errors),
  so Eq. M1 applies from the first plan; the new task's errors replace them within ``window``
  samples. The model may have been updated in between: its errors then are the old model's.

:class:`ForceMargin` is Eq. M1 (and, with ``lead=True``, Eq. M7's m'_a),
:func:`check_candidates` / :func:`largest_safe` Eq. M3, :func:`fallback_speed` Eq. M4,
:func:`slowdown_speed` Eq. M5, :func:`first_period_forces` the prediction for the issued command
(from the batch's first control period, which depends only on v_0), :class:`GuardStats` what the
trajectory's meta and the log report. Everything here is plain torch / numpy.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from .config import MarginConfig


class ForceMargin:
    """Eq. M1 (module docstring): the margin per axis from the measured force errors."""

    def __init__(self, cfg: MarginConfig, *, lead: bool = False) -> None:
        self.cfg = cfg
        self.lead = lead
        size = cfg.lead_window if lead else cfg.window
        self.errors: tuple[deque[float], deque[float]] = (deque(maxlen=size), deque(maxlen=size))

    def reset(self) -> None:
        """A new task: no errors, the margin is ``init_n`` again."""
        for d in self.errors:
            d.clear()

    def observe(self, measured: np.ndarray, predicted: np.ndarray) -> None:
        """Add the errors |F measured| - |F predicted| of k model steps, [k, 2] (RX, RZ)."""
        e = np.abs(np.asarray(measured, dtype=np.float64)) - np.abs(np.asarray(predicted))
        for axis in (0, 1):
            self.errors[axis].extend(float(x) for x in e[:, axis] if math.isfinite(x))

    def axis_margin(self, axis: int) -> float:
        """m_a of Eq. M1 (m'_a of Eq. M7), N: the conformal (1 - delta) upper quantile of the
        window."""
        c, errs = self.cfg, self.errors[axis]
        n = len(errs)
        if not c.enabled:
            return 0.0
        if n < c.min_count:
            return 0.0 if self.lead else float(c.init_n)
        r = math.ceil((n + 1) * (1.0 - c.delta))
        if r > n:
            return float(c.max_n)
        e_r = float(np.partition(np.asarray(errs), r - 1)[r - 1])
        return float(min(c.max_n, max(0.0, e_r)))

    @property
    def value(self) -> np.ndarray:
        """[m_RX, m_RZ], N."""
        return np.array([self.axis_margin(0), self.axis_margin(1)])


def check_candidates(u_prior: torch.Tensor, top: float, u_min: float,
                     count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. M3's candidates: speeds c [M] from u_min to ``top`` and their sequences [M, H]:
    c_j for the first horizon step, then the prior plan ``u_prior`` [H] capped at c_j."""
    top = max(float(top), u_min)
    c = torch.linspace(u_min, top, count, dtype=u_prior.dtype)
    seq = torch.minimum(u_prior.unsqueeze(0), c.unsqueeze(1))
    seq[:, 0] = c
    return c, seq


def peak_over_limit(out: torch.Tensor, active: torch.Tensor, margin: torch.Tensor,
                    limit: float) -> torch.Tensor:
    """g [R] of Eq. M3: the largest |F_a| + m_a over the samples where the task still runs,
    minus ``limit``, of rollouts ``out`` [R, S, 3] (``active`` [R, S] 0/1)."""
    f = (out[..., 1:3].abs() + margin.to(out.dtype)) * active.to(out.dtype).unsqueeze(-1)
    return f.amax(dim=(1, 2)) - limit


def largest_safe(c: np.ndarray, g: np.ndarray, u_star: float) -> float | None:
    """Eq. M3: min(u*, c*) with c* the first zero crossing of g over the candidates c (linear
    between the two around it; no crossing: u*); None when g_0 >= 0 (nothing is safe)."""
    bad = np.flatnonzero(g >= 0.0)
    if bad.size == 0:
        return float(u_star)
    j = int(bad[0])
    if j == 0:
        return None
    lo, hi = float(c[j - 1]), float(c[j])
    frac = float(-g[j - 1] / (g[j] - g[j - 1]))
    return float(min(u_star, lo + (hi - lo) * frac))


def fallback_speed(c: np.ndarray, g: np.ndarray, mode: str) -> float:
    """Eq. M4: the command when no candidate is safe: ``least_force`` the candidate with the
    lowest g (the slowest among equals), ``u_min`` the slowest, c_0."""
    if mode == "u_min":
        return float(c[0])
    return float(c[int(np.argmin(g))])


def slowdown_speed(u_out: float, u_prev: float | None, f_hat: float, u_min: float,
                   f_prewarn: float, start_n: float) -> float:
    """Eq. M5: ``u_out`` capped at s u_prev (never below u_min) when the measured peak
    ``f_hat`` >= ``start_n``, s = (f_prewarn - f_hat) / (f_prewarn - start_n) in [0, 1];
    without a previous command the cap is s u_out."""
    if not f_hat >= start_n:
        return float(u_out)
    s = min(1.0, max(0.0, (f_prewarn - f_hat) / (f_prewarn - start_n)))
    ref = float(u_out if u_prev is None else u_prev)
    return float(max(u_min, min(u_out, s * ref)))


def first_period_forces(v0: np.ndarray, forces: np.ndarray, u: float) -> np.ndarray | None:
    """The predicted |F| [k, 2] of the first control period for speed ``u``, interpolated in
    v_0 between the batch's rollouts (their first period depends on v_0 only): ``v0`` [R],
    ``forces`` [R, k, 2]. None when ``u`` lies outside the sampled speeds."""
    xs, first = np.unique(v0, return_index=True)
    if not xs[0] - 1e-9 <= u <= xs[-1] + 1e-9:
        return None
    f = np.abs(forces[first])
    if xs.size == 1:
        return f[0]
    out = np.empty(f.shape[1:])
    for k in range(f.shape[1]):
        for a in range(f.shape[2]):
            out[k, a] = np.interp(u, xs, f[:, k, a])
    return out


@dataclass
class GuardStats:
    """What the guard did in one task: the trajectory meta's ``planner_guard`` fields."""

    plans: int = 0
    reduced: int = 0
    reduced_max_mmps: float = 0.0
    fallbacks: int = 0
    unsafe_plans: int = 0
    slowed: int = 0
    from_horizon: int = 0
    margins: list[list[float]] = field(default_factory=list)

    def record(self, margin: np.ndarray, u_star: float, u_out: float, fallback: bool,
               all_unsafe: bool, slowed: bool = False, from_horizon: bool = False) -> None:
        """One plan: the margin in use, the MPPI command u*, the command that went out,
        whether Eq. M5 lowered it and whether Eq. M7 set the margin on an axis."""
        self.plans += 1
        self.slowed += int(slowed)
        self.from_horizon += int(from_horizon)
        self.margins.append([float(margin[0]), float(margin[1])])
        self.fallbacks += int(fallback)
        self.unsafe_plans += int(all_unsafe)
        if not fallback and u_out < u_star - 1e-9:
            self.reduced += 1
            self.reduced_max_mmps = max(self.reduced_max_mmps, u_star - u_out)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary: counts and the margin in use (last, mean, max per axis), N."""
        m = np.asarray(self.margins) if self.margins else np.zeros((1, 2))
        return {"plans": self.plans, "commands_reduced": self.reduced,
                "reduced_max_mmps": round(self.reduced_max_mmps, 4),
                "fallbacks": self.fallbacks, "all_samples_unsafe": self.unsafe_plans,
                "commands_slowed": self.slowed, "margin_from_horizon": self.from_horizon,
                "margin_last_n": [round(float(x), 4) for x in m[-1]],
                "margin_mean_n": [round(float(x), 4) for x in m.mean(axis=0)],
                "margin_max_n": [round(float(x), 4) for x in m.max(axis=0)]}
