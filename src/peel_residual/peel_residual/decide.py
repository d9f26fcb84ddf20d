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
from peel_model.effect_terms import CHANNELS, FORCE_CHANNELS, Term

from . import predict as P
from .data import Horizons


def open_loop_errors(model: Any, hz: Horizons) -> np.ndarray:
    """Open-loop errors ``[n, S, 3]`` in the order of :data:`CHANNELS` (``fx``, ``fz`` N;
    ``v`` mm/s), NaN where a step is not valid."""
    return _errors(model, hz, P.open_loop(model, hz))


def _errors(model: Any, hz: Horizons, pred: np.ndarray) -> np.ndarray:
    err = np.stack([hz.rows[:, -hz.steps:, 2 + i] - pred[:, :, i]
                    for i in range(len(FORCE_CHANNELS))]
                   + [hz.rows[:, -hz.steps:, 1] - P.speed_open_loop(model, hz)], axis=-1)
    return np.where(hz.valid[:, :, None] & np.isfinite(err), err, np.nan)


def _rmse(err: np.ndarray) -> dict[str, float]:
    out = {}
    for i, ch in enumerate(CHANNELS):
        e = err[:, :, i][np.isfinite(err[:, :, i])]
        out[ch] = float(np.sqrt(np.mean(e ** 2))) if e.size else 0.0
    return out


def open_loop_rmse(model: Any, hz: Horizons) -> dict[str, float]:
    """Held-out open-loop RMSE per channel (``fx``, ``fz`` N; ``v`` mm/s)."""
    return _rmse(open_loop_errors(model, hz))


def _task_sse(err: np.ndarray, hz: Horizons) -> np.ndarray:
    """Open-loop SSE ``[tasks, 3]`` of each task of ``hz`` (in ``np.unique`` order) per channel."""
    sq = np.nan_to_num(err ** 2).sum(axis=1)
    return np.stack([sq[hz.task == j].sum(axis=0) for j in np.unique(hz.task)])


class _Alternatives:
    """The open-loop errors on ``hz`` of ``model`` with each set of terms asked for, the sets
    of one call rolled out together (:func:`~.predict.open_loop_many`) and each set once."""

    def __init__(self, model: Any, hz: Horizons, dt_s: float) -> None:
        self.model, self.hz, self.dt_s = model, hz, dt_s
        self.memo: dict[tuple[int, ...], np.ndarray] = {}

    def __call__(self, sets: Sequence[Sequence[Term]]) -> list[np.ndarray]:
        keys = [tuple(sorted(id(t) for t in ts)) for ts in sets]
        todo = {k: ts for k, ts in zip(keys, sets, strict=True) if k not in self.memo}
        models = [corrected_model(self.model, ts, self.dt_s) if ts else self.model
                  for ts in todo.values()]
        preds = P.open_loop_many(models, [self.hz] * len(models))
        for k, m, pred in zip(todo, models, preds, strict=True):
            self.memo[k] = _errors(m, self.hz, pred)
        return [self.memo[k] for k in keys]


def holm_pass(p: np.ndarray, alpha: float, m: int) -> np.ndarray:
    """Holm's step-down over ``m`` hypotheses of which ``p`` are those still tested: the i-th
    smallest passes if it and every smaller one lie at or below alpha / (m - i)."""
    order = np.argsort(p, kind="stable")
    ok = np.cumprod([p[j] <= alpha / (m - i) for i, j in enumerate(order)]).astype(bool)
    out = np.zeros(len(p), dtype=bool)
    out[order] = ok
    return out


def consistency_check(model: Any, terms: Sequence[Term], hz: Horizons, dt_s: float,
                      alpha: float) -> tuple[list[Term], list[tuple[Term, str]]]:
    """(kept, [(dropped, reason)]): the held-out tasks' paired test of the module docstring."""
    from scipy.stats import wilcoxon

    errors = _Alternatives(model, hz, dt_s)
    base = _task_sse(errors([[]])[0], hz).sum(axis=0)
    w = np.where(base > 0, 1.0 / np.where(base > 0, base, 1.0), 0.0)
    current, dropped, m0 = list(terms), [], len(terms)
    while current:
        full, *rest = (_task_sse(e, hz) for e in errors(
            [current, *([t for t in current if t is not term] for term in current)]))
        p = np.ones(len(current))
        for i, without in enumerate(rest):
            d = ((without - full) * w).sum(axis=1)
            if np.any(d != 0):
                p[i] = float(wilcoxon(d, alternative="greater").pvalue)
        if holm_pass(p, alpha, m0).all():
            break
        worst = int(np.argmax(p))
        dropped.append((current.pop(worst),
                        f"does not lower the held-out open-loop error consistently across the "
                        f"{len(full)} held-out tasks (Wilcoxon p = {p[worst]:.3f}, Holm over "
                        f"{m0} terms at {alpha:g})"))
    return current, dropped


def held_out_decision(model: Any, terms: Sequence[Term], hz: Horizons, dt_s: float
                      ) -> tuple[list[Term], list[tuple[Term, str]]]:
    """(kept terms, [(dropped term, reason)]) by the rule of the module docstring."""
    errors = _Alternatives(model, hz, dt_s)
    base = _rmse(errors([[]])[0])

    def score(r: dict[str, float]) -> float:
        return sum((r[ch] / base[ch]) ** 2 for ch in CHANNELS if base[ch] > 0)

    current, dropped = list(terms), []
    while current:
        full, *rest = (_rmse(e) for e in errors(
            [current, *([t for t in current if t is not term] for term in current)]))
        best: tuple[float, Term, str] | None = None
        for term, without in zip(current, rest, strict=True):
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
