"""OL-MPPI planning (paper section 3.5, Eq. 28-38, Algorithm 2).

One :meth:`Planner.plan` call is one pass of Algorithm 2's inner loop:

1. (line 2) the :class:`~.safety.SafetyMonitor` ends the task on a 20 N prewarning, t > t_max or
   q >= q_ter: the command is 0 and the reason is kept (``planner.stop``);
2. (lines 15-17, for the previous command) the measured velocity v* over the control period
   that just ended, ``(q_now - q_issue) / (t_now - t_issue)``, is compared with the command u*
   issued then; the error joins D_Sigma (the last ``sigma_window`` errors) and Sigma becomes
   their mean square, ``Sigma = mean(e^2)``, clamped to [sigma_min, sigma_max]; until
   ``sigma_min_count`` errors exist Sigma stays sigma0. The mean square about zero (not the
   sample variance) is used because Eq. 2 models v ~ N(u, Sigma): a bias of v* is spread too;
3. (lines 4-13) N sequences eps^k over the H horizon steps, each eps^k_t ~ N(0, Sigma);
   with ``noise_correlation`` rho > 0 the steps of one sequence are AR(1)-correlated,
   eps_t = rho eps_{t-1} + sqrt(1 - rho^2) z_t (:func:`ar1_matrix`; rho = 0: white, the paper);
   ``v^k = clip(u + eps^k, u_min, u_max)`` and eps^k is replaced by the clipped ``v^k - u`` (so
   the control term sees the perturbation actually applied); each v^k_t is held for
   ``steps_per_horizon_step`` model steps of dt (default 5 x 0.1 s = one 0.5 s control period)
   and the whole batch is rolled out at once through the Dynamics (:mod:`~.dynamics`); J^k =
   the sum of the cost critics: Eq. 4's terms + phi + barrier + cost-to-go (:mod:`~.cost`);
4. (line 13, Eq. 38) ``S^k = J^k + c lambda/2 (u' Sigma_H^-1 u + 2 eps^k' Sigma_H^-1 u)``
   with c = ``control_cost_scale`` (1 in the paper), Sigma_H the covariance of the noise over
   the horizon and ``omega^k = exp(-(S^k - min_j S^j) / lambda) / eta`` -- subtracting the
   minimum before the exponential (the "min-cost shift") leaves omega unchanged and keeps exp()
   finite. The control term is the log-likelihood ratio of the sampled sequence under the
   zero-mean and the u-mean noise (:func:`control_cost`): with independent steps Sigma_H =
   Sigma I and it is Eq. 36-37's per-step ``sum_t (u_t^2 + 2 eps_t u_t) / Sigma``
   (``control_term: per_step``); with AR(1) noise Sigma_H = Sigma R, R_ts = rho^|t-s|, whose
   inverse is tridiagonal (:func:`ar1_precision`; ``control_term: joint``). Sigma here is
   sigma0 (``control_cost_sigma: sigma0``, a fixed control cost) or the re-estimate
   (``estimate``). ``J^k`` is the sum of the cost critics (:mod:`~.cost`); each critic's N
   costs are kept in ``planner.last["terms"]`` (:func:`term_influence`: which term drives U);
5. (line 14, Eq. 31) ``U = sum_k omega^k v^k`` -- already inside the speed limits because each
   v^k is; repeated ``iterations`` times (1 in the paper);
6. (line 15) u* = U_0 is returned; (lines 18-19) U is shifted by one horizon step and the last
   entry is refilled (``shift_fill``: repeat the last, or u_init).

Sigma is a scalar variance (mm/s)^2: the control is one-dimensional (m = 1, section 2).
All planner state (U, Sigma, D_Sigma, the noise generator, the last command) survives
:meth:`Planner.set_dynamics`, so the model can be swapped between two calls of plan().
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .config import PlannerConfig
from .cost import Cost, Rollouts, total
from .dynamics import Dynamics
from .guard import (
    ForceMargin,
    GuardStats,
    check_candidates,
    fallback_speed,
    first_period_forces,
    largest_safe,
    peak_over_limit,
    slowdown_speed,
)
from .safety import SafetyMonitor, Stop

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def control_cost(eps: torch.Tensor, u: torch.Tensor, sigma: float, lam: float,
                 control_cost_scale: float = 1.0,
                 precision: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 38's control term of each sample, [N], for perturbations eps [N, H] and U [H]:
    ``c lambda/2 (u' P u + 2 eps' P u) / Sigma`` with P the inverse correlation of the noise
    over the horizon (None: independent steps, P = I, the paper's per-step term)."""
    pu = u if precision is None else precision @ u
    return (0.5 * lam * control_cost_scale / sigma) * ((u * pu).sum() + 2.0 * (eps @ pu))


def eq38_weights(cost: torch.Tensor, eps: torch.Tensor, u: torch.Tensor, sigma: float,
                 lam: float, control_cost_scale: float = 1.0,
                 precision: torch.Tensor | None = None) -> torch.Tensor:
    """omega of Eq. 38 for costs J [N], perturbations eps [N, H] and the mean sequence u [H].

    ``S = J + control_cost(...)``; ``omega = exp(-(S - min S) / lambda) / sum(...)`` (the shift
    cancels in the normalisation).
    """
    s = cost + control_cost(eps, u, sigma, lam, control_cost_scale, precision)
    return torch.softmax(-(s - s.min()) / lam, dim=0)


def ar1_matrix(h: int, rho: float, dtype: torch.dtype) -> torch.Tensor | None:
    """[H, H] matrix A with (z A)_t = rho (z A)_{t-1} + sqrt(1 - rho^2) z_t, (z A)_0 = z_0:
    unit-variance AR(1) noise from white z (None for rho = 0). Its covariance is A'A = R,
    R_ts = rho^|t-s|."""
    if rho == 0.0:
        return None
    a = torch.zeros((h, h), dtype=torch.float64)
    c = math.sqrt(1.0 - rho * rho)
    for t in range(h):
        for s in range(t + 1):
            a[s, t] = rho ** (t - s) * (1.0 if s == 0 else c)
    return a.to(dtype)


def ar1_precision(h: int, rho: float, dtype: torch.dtype) -> torch.Tensor:
    """R^-1 of the AR(1) correlation R_ts = rho^|t-s|: tridiagonal, 1/(1 - rho^2) times
    1, 1 + rho^2, ..., 1 + rho^2, 1 on the diagonal and -rho beside it (identity for rho = 0
    or H = 1)."""
    if h == 1:
        return torch.ones((1, 1), dtype=dtype)
    diag = torch.full((h,), 1.0 + rho * rho, dtype=torch.float64)
    diag[0] = diag[-1] = 1.0
    p = torch.diag(diag) - rho * (torch.diag(torch.ones(h - 1, dtype=torch.float64), 1)
                                  + torch.diag(torch.ones(h - 1, dtype=torch.float64), -1))
    return (p / (1.0 - rho * rho)).to(dtype)


def term_influence(terms: dict[str, torch.Tensor], omega: torch.Tensor) -> dict[str, float]:
    """How much the weighting lowered each term: mean over the N samples minus the
    omega-weighted mean (the cost of the new U's samples). The largest drives the plan; a
    negative value is a term the plan pays for the others."""
    return {name: float(v.mean() - omega.to(v.dtype) @ v) for name, v in terms.items()}


class Planner:
    """OL-MPPI (Algorithm 2) over a swappable :class:`~.dynamics.Dynamics`.

    ``Planner(dynamics, cost, config)``; ``plan(history) -> u`` (mm/s) once per control period;
    ``reset()`` before a new task; ``set_dynamics(dyn)`` swaps the model and keeps the state.
    """

    def __init__(self, dynamics: Dynamics, cost: Cost | None = None,
                 config: PlannerConfig | None = None) -> None:
        self.config = config if config is not None else PlannerConfig()
        self.cost = cost if cost is not None else Cost(self.config.cost)
        m = self.config.mppi
        self.n, self.h, self.lam = m.n_samples, m.horizon, m.lam
        self.k = m.steps_per_horizon_step
        self.dtype = _DTYPES[m.dtype]
        self.safety = SafetyMonitor(self.config.safety)
        self.margin = ForceMargin(self.config.safety.margin)
        self.lead_margin = ForceMargin(self.config.safety.margin, lead=True)
        self.set_dynamics(dynamics)
        self._gen = torch.Generator(device="cpu")
        self._noise = torch.empty((self.n, self.h), dtype=self.dtype)
        rho = self.config.mppi.noise_correlation
        self._ar = ar1_matrix(self.h, rho, self.dtype)
        self._precision = (ar1_precision(self.h, rho, self.dtype)
                           if m.control_term == "joint" and rho > 0.0 else None)
        self.last: dict[str, Any] = {}
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Start a new task: U = u_init, Sigma = sigma0, empty D_Sigma, noise seed restarted."""
        m = self.config.mppi
        self.U = torch.full((self.h,), float(m.u_init), dtype=self.dtype).clamp(m.u_min, m.u_max)
        self.sigma = float(m.sigma0)
        self.errors: deque[float] = deque(maxlen=m.sigma_window)
        self._gen.manual_seed(int(m.seed))
        self._issued: tuple[float, float, float] | None = None  # (t, q, u*) of the last command
        self._u_prev: float | None = None  # the command in force (Eq. M5)
        self.safety.reset()
        self.margin.reset()
        self.lead_margin.reset()
        self.guard = GuardStats()
        self._predicted: tuple[float, np.ndarray] | None = None  # (t, |F| [k, 2]) of u*
        self.last = {}

    def carry_from(self, previous: Planner | None) -> None:
        """Eq. M8 (``safety.margin.carry_over``; module :mod:`~.guard`): after :meth:`reset`,
        start Eq. M1's window with ``previous``'s (the last task's planner) last errors."""
        if previous is None or not self.config.safety.margin.carry_over:
            return
        for mine, theirs in zip(self.margin.errors, previous.margin.errors, strict=True):
            mine.extend(theirs)

    def set_dynamics(self, dynamics: Dynamics) -> None:
        """Swap the forward model; U, Sigma, D_Sigma and the noise stream are kept."""
        if not isinstance(dynamics, Dynamics):
            raise PeelError("dynamics must provide rollout(history, v) -> Tensor[N, S, 3]")
        self.dynamics = dynamics

    @property
    def stop(self) -> Stop | None:
        """Why the task ended (None while it runs)."""
        return self.safety.stop

    # ------------------------------------------------------------------ Sigma (lines 15-17)
    def observe(self, v_meas: float, u_cmd: float) -> float:
        """Add one velocity error v* - u* to D_Sigma and re-estimate Sigma; returns Sigma."""
        m = self.config.mppi
        err = float(v_meas) - float(u_cmd)
        if not math.isfinite(err):
            raise PeelError(f"measured velocity v* = {v_meas!r} is not finite")
        self.errors.append(err)
        if len(self.errors) >= m.sigma_min_count:
            ms = float(np.mean(np.square(np.asarray(self.errors))))
            self.sigma = min(max(ms, m.sigma_min), m.sigma_max)
        return self.sigma

    def _measure(self, history: Trajectory) -> None:
        if self._issued is None:
            return
        t0, q0, u0 = self._issued
        t1, q1 = float(history.t[-1]), float(history.q[-1])
        if t1 > t0 + 1e-9:
            self.observe((q1 - q0) / (t1 - t0), u0)
            self._issued = None

    # ------------------------------------------------------------------ margin (Eq. M1)
    def _observe_forces(self, history: Trajectory) -> None:
        """Eq. M1's errors: the forces measured since the last command against those the
        model predicted for it (the samples t_issue + dt, ..., at most one period)."""
        if self._predicted is None:
            return
        t0, pred = self._predicted
        tail = history.as_array()[-(len(pred) + 1):]
        step = np.rint((tail[:, 0] - t0) / self.config.cost.dt_s).astype(int) - 1
        keep = (tail[:, 0] > t0 + 1e-9) & (step >= 0) & (step < len(pred))
        if keep.any():
            self.margin.observe(tail[keep][:, [4, 5]], pred[step[keep]])
            self._predicted = None

    def _observe_horizon(self, history: Trajectory) -> None:
        """Eq. M7's errors: the model replayed from the sample L = H k steps back, fed the
        commands then in force, against the L samples measured since (module :mod:`~.guard`).
        Off for dynamics that cannot start from a past sample (``replays_history`` False)."""
        c = self.config.safety.margin
        steps = self.h * self.k
        start = len(history) - 1 - steps
        if not (c.enabled and c.lead_enabled) or start < 0 or not getattr(
                self.dynamics, "replays_history", True):
            return
        with torch.inference_mode():
            v = torch.as_tensor(history.u[start:start + steps], dtype=self.dtype).unsqueeze(0)
            out = self.dynamics.rollout(history.slice(0, start + 1), v)
        measured = np.stack([history.fx, history.fz], axis=1)[start + 1:]
        self.lead_margin.observe(measured, out[0, :, 1:3].double().numpy())

    def _margin(self) -> tuple[np.ndarray, bool]:
        """m_a in use (Eq. M1, or M7's max with it) and whether Eq. M7 set it on an axis (by
        more than 1e-6 N: a right model's replay differs from the samples by float rounding)."""
        m1 = self.margin.value
        if not self.config.safety.margin.lead_enabled:
            return m1, False
        m7 = self.lead_margin.value
        return np.maximum(m1, m7), bool((m7 > m1 + 1e-6).any())

    # ------------------------------------------------------------------ MPPI (lines 4-14)
    def _rows(self, v: torch.Tensor) -> tuple[torch.Tensor, int, torch.Tensor | None]:
        """The batch: the N samples, the slowest sequence (``safety.null_sample``: weighted
        with them, Eq. 31) and Eq. M3's candidates; returns it, the weighted row count and the
        candidate speeds."""
        g, m = self.config.safety, self.config.mppi
        null = torch.full((1, self.h), float(m.u_min), dtype=self.dtype)
        weighted = torch.cat([v, null]) if g.null_sample else v
        if not g.check.enabled:
            return weighted, len(weighted), None
        c, seq = check_candidates(self.U, float(v[:, 0].max()), m.u_min, g.check.candidates)
        return torch.cat([weighted, seq[1:] if g.null_sample else seq]), len(weighted), c

    def update(self, history: Trajectory) -> np.ndarray:
        """One MPPI update of U from ``history`` (Algorithm 2 lines 4-14); returns the new U.
        The barrier sees the margin m_a (Eq. M2); Eq. M3's candidates are rolled out in the
        same batch and their g kept in ``last["check"]``."""
        m = self.config.mppi
        t_now, q_now = float(history.t[-1]), float(history.q[-1])
        with torch.inference_mode():
            noise = torch.randn((self.n, self.h), generator=self._gen, out=self._noise)
            if self._ar is not None:  # AR(1) over the horizon, unit variance per step
                noise = noise @ self._ar
            u = self.U
            rows, n_w, cand = self._rows(torch.clamp(u + noise * math.sqrt(self.sigma),
                                                     m.u_min, m.u_max))
            v = rows[:n_w]
            eps = v - u
            r = len(rows)
            v_model = (rows.unsqueeze(-1).expand(r, self.h, self.k).reshape(r, self.h * self.k)
                       if self.k > 1 else rows)
            out = self.dynamics.rollout(history, v_model)
            if out.shape != (r, self.h * self.k, 3):
                raise PeelError(f"dynamics returned shape {tuple(out.shape)}, "
                                f"expected {(r, self.h * self.k, 3)}")
            m_a, from_horizon = self._margin()
            margin = torch.as_tensor(m_a, dtype=out.dtype)
            terms = self.cost.rollout_terms(q_now, t_now, out[:n_w], margin)
            j = total(terms).to(self.dtype)
            if not bool(torch.isfinite(j).all()):
                raise PeelError("rollout cost is not finite: the model predicted NaN/inf forces")
            sigma_ctrl = self.sigma if m.control_cost_sigma == "estimate" else m.sigma0
            omega = eq38_weights(j, eps, u, sigma_ctrl, self.lam, m.control_cost_scale,
                                 self._precision)
            ctrl = control_cost(eps, u, sigma_ctrl, self.lam, m.control_cost_scale,
                                self._precision)  # kept for the record (term influence)
            self.U = omega @ v  # Eq. 31
            active = Rollouts.predicted(q_now, t_now, out, self.cost.cfg).active
            g = peak_over_limit(out, active, margin, self.config.safety.f_prewarn_n)
            self.last = {"omega": omega, "cost": j, "terms": terms, "control": ctrl, "v": v,
                         "eps": eps, "ess": float(1.0 / (omega * omega).sum()),
                         "margin": margin.numpy().copy(), "from_horizon": from_horizon,
                         "all_unsafe": bool((g[:n_w] >= 0.0).all()),
                         "v0": rows[:, 0].double().numpy(),
                         "first": out[:, :self.k, 1:3].double().numpy()}
            if cand is not None:  # the candidates: the slowest sequence (c_0) and the rest
                first = n_w - 1 if self.config.safety.null_sample else n_w
                self.last["check"] = (cand.double().numpy(), g[first:].double().numpy())
        return self.U.numpy().copy()

    def _shift(self) -> None:
        m = self.config.mppi
        fill = self.U[-1] if m.shift_fill == "last" else torch.tensor(m.u_init, dtype=self.dtype)
        self.U = torch.cat([self.U[1:], fill.reshape(1)]).clamp(m.u_min, m.u_max)

    def _check(self, u_star: float) -> tuple[float, bool]:
        """Eq. M3 on the last update's candidates: the command that goes out and whether it is
        the fallback. U follows it (capped at the command, or u_min after a fallback)."""
        if "check" not in self.last:
            return u_star, False
        c, g = self.last["check"]
        safe = largest_safe(c, g, u_star)
        if safe is None:  # Eq. M4: nothing is safe; the blade keeps moving at >= u_min
            u_fb = fallback_speed(c, g, self.config.safety.fallback)
            self.U = torch.full_like(self.U, u_fb)
            return u_fb, True
        if safe < u_star:
            self.U = torch.clamp(self.U, max=safe)
        return safe, False

    def _slowdown(self, history: Trajectory, u_out: float) -> tuple[float, bool]:
        """Eq. M5 on the samples of the control period that just ended; U is capped at the
        command when it lowers it."""
        sd = self.config.safety.slowdown
        if not sd.enabled:
            return u_out, False
        n = max(1, round(self.config.control_period_s / self.config.cost.dt_s))
        f_hat = float(max(np.abs(history.fx[-n:]).max(), np.abs(history.fz[-n:]).max()))
        u = slowdown_speed(u_out, self._u_prev, f_hat, self.config.mppi.u_min,
                           self.config.safety.f_prewarn_n, sd.start_n)
        if u < u_out - 1e-9:
            self.U = torch.clamp(self.U, max=u)
            return u, True
        return u_out, False

    def plan(self, history: Trajectory) -> float:
        """The blade speed command (mm/s) for the next control period (Algorithm 2 with the
        guard of Eq. M1-M5: u* checked against the model before it goes out, then against
        the measured force when ``safety.slowdown`` is on)."""
        if len(history) == 0:
            raise PeelError("history 't' is empty: the planner needs at least the sample at t=0")
        if self.safety.check(history) is not None:
            return 0.0
        self._measure(history)
        self._observe_forces(history)
        self._observe_horizon(history)
        for _ in range(self.config.mppi.iterations):
            self.update(history)
        m = self.config.mppi
        u_star = float(min(max(float(self.U[0]), m.u_min), m.u_max))
        u_out, fallback = self._check(u_star)
        u_out, slowed = self._slowdown(history, u_out)
        self.guard.record(self.last["margin"], u_star, u_out, fallback, self.last["all_unsafe"],
                          slowed, self.last["from_horizon"])
        self.last.update(u_star=u_star, u_out=u_out, fallback=fallback, slowed=slowed)
        self._u_prev = u_out
        t_now = float(history.t[-1])
        pred = first_period_forces(self.last["v0"], self.last["first"], u_out)
        self._predicted = None if pred is None else (t_now, pred)
        self._issued = (t_now, float(history.q[-1]), u_out)
        self._shift()
        return u_out

    __call__ = plan
