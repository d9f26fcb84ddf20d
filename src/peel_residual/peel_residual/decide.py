"""The held-out decision: no term is kept that makes the held-out open-loop error worse.

The selection (:mod:`.trace`) guards the open loop of the fit tasks' folds only; on plant data
the model's own gap differs from task to task, and a term can help those folds and hurt new
tasks (docs/residual.md, "Method"). So, after the selection, on the held-out tasks' horizons
(the model fed its own forces over the planner's horizon, :func:`~.predict.open_loop`):

    score(terms) = sum over the channels fx, fz, v of (RMSE_ch(terms) / RMSE_ch(no terms))^2;
    repeat: a remaining term T fails if leaving it out lowers its own channel's RMSE or the
    score; drop the failing term whose removal lowers the score most (relative to its own
    channel's change when only that fails); until none fails.

The result is a corrected model in which every term lowers its own channel's held-out
open-loop error and the error summed over the channels (each relative to the uncorrected
model); a term that helps F_RZ much and moves F_RX slightly (through the model) stays. The
held-out tasks decide, so their after / before is not an independent estimate; the power study
(``scripts/residual_study.py``) measures it again on fresh tasks.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from peel_model.compensated import corrected_model
from peel_model.effect_terms import CHANNELS, FORCE_CHANNELS, VELOCITY_CHANNEL, Term

from . import predict as P
from .data import Horizons


def open_loop_rmse(model: Any, hz: Horizons) -> dict[str, float]:
    """Held-out open-loop RMSE per channel (``fx``, ``fz`` N; ``v`` mm/s)."""
    out = {}
    valid = hz.valid
    pred = P.open_loop(model, hz)
    for i, ch in enumerate(FORCE_CHANNELS):
        err = (hz.rows[:, -hz.steps:, 2 + i] - pred[:, :, i])[valid]
        out[ch] = float(np.sqrt(np.mean(err ** 2))) if err.size else 0.0
    err = (hz.rows[:, -hz.steps:, 1] - P.speed_open_loop(model, hz))[valid]
    err = err[np.isfinite(err)]
    out[VELOCITY_CHANNEL] = float(np.sqrt(np.mean(err ** 2))) if err.size else 0.0
    return out


def held_out_decision(model: Any, terms: Sequence[Term], hz: Horizons, dt_s: float
                      ) -> tuple[list[Term], list[tuple[Term, str]]]:
    """(kept terms, [(dropped term, reason)]) by the rule of the module docstring."""
    def rmse(ts: Sequence[Term]) -> dict[str, float]:
        return open_loop_rmse(corrected_model(model, ts, dt_s) if ts else model, hz)

    base = rmse([])

    def score(r: dict[str, float]) -> float:
        return sum((r[ch] / base[ch]) ** 2 for ch in CHANNELS if base[ch] > 0)

    current, dropped = list(terms), []
    while current:
        full = rmse(current)
        best: tuple[float, Term, str] | None = None
        for term in current:
            without = rmse([t for t in current if t is not term])
            own = (full[term.channel] - without[term.channel]) / max(base[term.channel], 1e-12)
            total = score(full) - score(without)
            gain = max(own, total)
            if gain > 0 and (best is None or gain > best[0]):
                ch = term.channel
                why = (f"makes the held-out open-loop error of {ch} worse ({without[ch]:.3f} -> "
                       f"{full[ch]:.3f})" if own > 0 else
                       f"makes the held-out open-loop error over the channels worse (relative "
                       f"score {score(without):.3f} -> {score(full):.3f})")
                best = (gain, term, why)
        if best is None:
            break
        current.remove(best[1])
        dropped.append((best[1], best[2]))
    return current, dropped
