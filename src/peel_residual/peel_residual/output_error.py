"""Output-error responses: how the model's open-loop rollout changes with a candidate term.

The one-step screen (:func:`~.predict.term_responses`) sees an additive effect that varies
slowly only through its change from one sample to the next: the model is fed the *measured*
forces, which already carry the effect, and carries most of an offset in its history into its
next prediction (docs/residual.md, "Identify"). Over the planner's horizon, fed its *own*
forces (Algorithm 2 line 9), the model lets go of such an effect, and the residual accumulates.
So the open-loop residual is where a slowly varying effect shows, and it is fitted there too
(output error, as system identification calls it):

    r_{n,s} = F_{n,s} - F_hat_{n,s}(c),   F_hat(c) the compensated model's rollout
    (:class:`~peel_model.compensated.CompensatedPredictor`, F = f_theta(x - g, v) + g) from the
    measured history of horizon n, step s = 1 .. S, fed the measured speeds;

    J_{n,s} = dF_hat_{n,s} / dc at c = 0  (through f_theta and the fed-back forces).

The output-error fit is then a linear regression of r on J, which the same selection as one
step ahead (:mod:`.trace`) takes: lasso with cross-validation by task, a Wald test with a
bootstrap over tasks, the held-out decision after it. J is the *secant* of the rollout itself
over a term of :data:`PROBE_N` (one rollout per basis function, all run batched): the rollout
the planner uses, cross-talk's mixing and time terms included, with no second implementation
of it. A secant,
not a derivative: f_theta's rollout is not smooth at small changes (ReLU kinks, the pad's
contact thresholds), so the response to a 0.01 or 0.1 N term is not the response to a 1-2 N
effect (a 1.5 N F_RZ offset on simulator data: one coefficient on the 0.1 N secant explains
22 % of the open-loop residual, on the 1 N secant 72 %, on the exact 1.5 N change 78 %).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from peel_model.compensated import corrected_model
from peel_model.effect_terms import FORCE_CHANNELS, Candidate, Rows, Term

from . import predict as P
from .data import Horizons, Steps

#: Size (N, RMS over the horizons' rows) of the probe term of each secant: the smallest
#: effect the tool is asked to find (docs/residual.md, "Targets").
PROBE_N = 1.0

#: Open-loop steps kept as regression rows: every ``ROW_STEP``-th step of each horizon (the
#: residual changes slowly along a horizon; neighbouring steps add rows, not information).
ROW_STEP = 5


def horizon_rows(hz: Horizons) -> Rows:
    """The measured variables of every row of every horizon, ``[n, h + S]``."""
    return Rows(q=torch.as_tensor(hz.rows[..., 0]), v=torch.as_tensor(hz.rows[..., 1]),
                t=torch.as_tensor(hz.t), f=torch.as_tensor(hz.rows[..., 2:4]))


def _probe_scale(cand: Candidate, rows: Rows, ch: int, valid: np.ndarray) -> np.ndarray:
    """Per basis function the coefficient that makes the probe term :data:`PROBE_N` in RMS."""
    phi = cand.basis(rows, ch).numpy()  # [n, h+S, nb]
    h = phi.shape[1] - valid.shape[1]
    mask = np.concatenate([np.ones((valid.shape[0], h), bool), valid], axis=1)
    rms = np.sqrt(np.mean(phi[mask] ** 2, axis=0))
    return PROBE_N / np.where(rms > 1e-9, rms, np.inf)


def open_loop_responses(model: Any, hz: Horizons, candidates: Sequence[Candidate],
                        dt_s: float) -> tuple[np.ndarray, dict[tuple[str, str],
                                                               tuple[Candidate, np.ndarray]]]:
    """(the rollout without terms ``[n, S, 2]``, ``{(candidate key, channel): (candidate,
    J [n, S, 2 (output), n_basis])}``) for every force candidate on each channel it acts on."""
    base = P.open_loop(model, hz)
    rows = horizon_rows(hz)
    out: dict[tuple[str, str], tuple[Candidate, np.ndarray]] = {}
    probes: list[tuple[tuple[str, str], int, float, Any]] = []
    for cand in candidates:
        for ch_name in FORCE_CHANNELS:
            if ch_name not in cand.spec.channels:
                continue
            scale = _probe_scale(cand, rows, FORCE_CHANNELS.index(ch_name), hz.valid)
            out[(cand.key, ch_name)] = (cand, np.zeros((*base.shape, cand.n_basis)))
            for b in np.flatnonzero(np.isfinite(scale) & (scale > 0)):
                coef = np.zeros(cand.n_basis)
                coef[b] = scale[b]
                probes.append(((cand.key, ch_name), b, scale[b], corrected_model(
                    model, [Term(cand, ch_name, tuple(coef.tolist()))], dt_s)))
    for (key, b, size, _), pred in zip(probes, P.open_loop_many([m for *_, m in probes],
                                                                 [hz] * len(probes)),
                                       strict=True):
        out[key][1][..., b] = (pred - base) / size
    return base, out


def row_mask(hz: Horizons) -> np.ndarray:
    """``[n, S]``: the valid steps kept as rows (every :data:`ROW_STEP`-th, ending at S)."""
    keep = np.zeros(hz.valid.shape, bool)
    keep[:, ROW_STEP - 1::ROW_STEP] = True
    keep[:, -1] = True
    return keep & hz.valid


def row_steps(hz: Horizons, keep: np.ndarray) -> Steps:
    """The kept open-loop rows as :class:`~.data.Steps` (the measured history before each row,
    its speed, force and time): the rows' physical variables for the evidence figures."""
    n, s = np.nonzero(keep)
    h = hz.rows.shape[1] - hz.steps
    hist = np.stack([hz.rows[n, s + j] for j in range(h)], axis=1)
    return Steps(hist=hist, v_next=hz.rows[n, h + s, 1], f_next=hz.rows[n, h + s, 2:4],
                 t_next=hz.t[n, h + s], u=np.full(len(n), np.nan), task=hz.task[n],
                 k=hz.k[n] + s)
