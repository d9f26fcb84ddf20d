"""Error before and after the correction, on held-out tasks: per channel and per mode.

Channels ``fx``, ``fz`` (N) and ``v`` (mm/s, the speed the planner assumes for a command);
modes ``one_step`` (every sample, Eq. 1) and ``open_loop`` (every valid step of every horizon,
the model fed its own forces and the measured speeds, :func:`~.predict.open_loop`; for ``v`` the
speeds predicted from the commands alone).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from peel_model.effect_terms import FORCE_CHANNELS
from peel_msgs_py.trajectory import Trajectory

from . import predict as P
from .data import Horizons, Steps, horizons, one_step_samples


def _rmse(err: np.ndarray) -> float | None:
    err = err[np.isfinite(err)]
    return float(np.sqrt(np.mean(err ** 2))) if err.size else None


@dataclass
class Errors:
    """Residuals of one model on one set of tasks."""

    one_step: np.ndarray  # [n, 2] F - F_hat
    open_loop: np.ndarray  # [m, S, 2], NaN where the horizon ran past the task end
    speed_one_step: np.ndarray  # [n] v - v_hat (NaN without commands)
    speed_open_loop: np.ndarray  # [m, S]

    def rmse(self) -> dict[str, dict[str, float | None]]:
        out: dict[str, dict[str, float | None]] = {}
        for i, ch in enumerate(FORCE_CHANNELS):
            out[ch] = {"one_step": _rmse(self.one_step[:, i]),
                       "open_loop": _rmse(self.open_loop[:, :, i])}
        out["v"] = {"one_step": _rmse(self.speed_one_step),
                    "open_loop": _rmse(self.speed_open_loop)}
        return out

    def by_step(self) -> dict[str, list[float | None]]:
        """Open-loop RMSE per horizon step."""
        out = {ch: [_rmse(self.open_loop[:, k, i]) for k in range(self.open_loop.shape[1])]
               for i, ch in enumerate(FORCE_CHANNELS)}
        out["v"] = [_rmse(self.speed_open_loop[:, k]) for k in range(self.speed_open_loop.shape[1])]
        return out


def errors(model: Any, s: Steps, hz: Horizons) -> Errors:
    """All residuals of ``model`` (its speed response if it has one, else v = u)."""
    ol = hz.rows[:, -hz.steps:, 2:4] - P.open_loop(model, hz)
    ol[~hz.valid] = np.nan
    v_hat = P.speed_one_step(model, s.hist[:, -1, 1], s.u)
    v_ol = hz.rows[:, -hz.steps:, 1] - P.speed_open_loop(model, hz)
    v_ol[~hz.valid] = np.nan
    return Errors(s.f_next - P.one_step(model, s), ol, s.v_next - v_hat, v_ol)


def held_out(tasks: list[Trajectory], h: int, steps: int, stride: int
             ) -> tuple[Steps, Horizons]:
    """The one-step samples and horizons of the held-out tasks."""
    return one_step_samples(tasks, h), horizons(tasks, h, steps, stride)


def term_shares(corrected: Any, before: Errors, s: Steps, hz: Horizons) -> list[dict[str, Any]]:
    """Per term of ``corrected``: the share of the *before* open-loop (and one-step) MSE of its
    channel that the term removes, measured by leaving it out of the corrected model."""
    from peel_model.compensated import CompensatedPredictor

    full = errors(corrected, s, hz).rmse()
    base_rmse = before.rmse()
    out = []
    for term in corrected.terms:
        rest = [t for t in corrected.terms if t is not term]
        without = errors(CompensatedPredictor(corrected.base, rest, dt_s=corrected.dt_s), s,
                         hz).rmse()
        shares = {}
        for mode in ("one_step", "open_loop"):
            b, w, f = (d[term.channel][mode] for d in (base_rmse, without, full))
            shares[mode] = None if None in (b, w, f) or b == 0 else (w ** 2 - f ** 2) / b ** 2
        out.append({"key": term.candidate.key, "channel": term.channel, **shares})
    return out
