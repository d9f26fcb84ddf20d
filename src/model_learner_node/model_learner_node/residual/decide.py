"""The held-out decision: no term is kept that makes the held-out open-loop error worse.

The selection (:mod:`.trace`) guards the open loop of the fit tasks' folds only; on plant data
the model's own gap differs from task to task, and a term can help those folds and hurt new
tasks (docs/residual.md, "Method"). So, after the selection, on the held-out tasks' horizons
(the model fed its own forces over the planner's horizon, :func:`~.predict.open_loop`):

    repeat: for every remaining term T, RMSE_ch(terms) - RMSE_ch(terms without T) on T's own
    channel, and on every channel whose error is above the uncorrected model's; drop the term
    with the largest positive difference; until none is positive.

The result is a corrected model whose held-out open-loop RMSE is, per channel, not above the
uncorrected model's, and in which every term lowers its own channel's error. The held-out tasks
decide, so their after / before is not an independent estimate; the power study
(``scripts/residual_study.py``) measures it again on fresh tasks.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..effect_terms import CHANNELS, FORCE_CHANNELS, VELOCITY_CHANNEL, Term
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
    from .analysis import corrected_model

    def rmse(ts: Sequence[Term]) -> dict[str, float]:
        return open_loop_rmse(corrected_model(model, ts, dt_s) if ts else model, hz)

    base = rmse([])
    current, dropped = list(terms), []
    while current:
        full = rmse(current)
        worse = [ch for ch in CHANNELS if full[ch] > base[ch]]
        best: tuple[float, Term, str] | None = None
        for term in current:
            without = rmse([t for t in current if t is not term])
            for ch in {term.channel, *worse}:
                gain = full[ch] - without[ch]
                if gain > 0 and (best is None or gain > best[0]):
                    best = (gain, term, f"makes the held-out open-loop error of {ch} worse "
                                        f"({without[ch]:.3f} -> {full[ch]:.3f}; uncorrected "
                                        f"{base[ch]:.3f})")
        if best is None:
            break
        current.remove(best[1])
        dropped.append((best[1], best[2]))
    return current, dropped
