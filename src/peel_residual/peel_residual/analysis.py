"""The residual analysis end to end: split, residual, trace, correction, error before and after.

1. Split the tasks, seeded, into fit tasks and held-out tasks (``holdout`` share, at least one
   each); everything is fitted on the fit tasks and every reported error is on the held-out
   ones.
2. **Residual** of the model on the fit tasks, one step ahead (:mod:`.predict`); the samples
   whose history reaches before the task start (padded, :mod:`peel_model.windows`) are
   left out of the fit: their input is the padding convention, not a measurement.
3. **Trace** each channel (:mod:`.trace`): force channels against the candidates' one-step
   responses, then -- with ``residual.open_loop_fit`` -- what the one-step terms leave of the
   open-loop residual against the candidates' open-loop responses (:mod:`.output_error`); the
   speed channel (v_{k+1} - u_k) against the velocity candidates.
4. **Held-out decision** (:mod:`.decide`): a term that makes the held-out open-loop error worse
   is dropped; **add** the rest: :class:`~peel_model.compensated.CompensatedPredictor`.
5. **Remains** (:mod:`.structure`): one-step structure on the fit tasks, a drift across tasks
   (the per-task mean open-loop residual against the task order, every task), and **error
   before / after** on the held-out tasks (:mod:`.evaluate`), one step and open loop over the
   planner's horizon.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from peel_model.compensated import corrected_model
from peel_model.effect_terms import FORCE_CHANNELS, VELOCITY_CHANNEL, Rows, Term
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from . import evaluate as E
from . import output_error as OE
from . import predict as P
from .config import ResidualConfig
from .data import Horizons, Steps, horizons, one_step_samples
from .decide import consistency_check, held_out_decision
from .structure import (
    Structure,
    drift_across_tasks,
    one_step_structure,
    open_loop_drift,
    state_variables,
)
from .trace import Column, OpenLoopScore, Problem, Trace, trace

#: The trace group of the output-error fit (:mod:`.output_error`).
OPEN_LOOP = "force_open_loop"


@dataclass
class Result:
    """Everything the report shows (:mod:`.report`)."""

    traces: dict[str, Trace]
    terms: list[Term]
    corrected: Any | None
    fit_tasks: list[int]
    holdout_tasks: list[int]
    rmse_before: dict[str, dict[str, float | None]]
    rmse_after: dict[str, dict[str, float | None]]
    by_step_before: dict[str, list[float | None]]
    by_step_after: dict[str, list[float | None]]
    structure: list[Structure]
    drift: dict[str, dict[str, Any]]
    shares: list[dict[str, Any]]
    samples: dict[str, int]
    task_drift: dict[str, dict[str, Any]] = field(default_factory=dict)
    plots: dict[str, Any] = field(default_factory=dict)


def split_tasks(n: int, fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """(fit, held-out) task indices: a seeded permutation, ``round(fraction n)`` held out."""
    if n < 3:
        raise PeelError(f"{n} task(s): the split needs at least 3 (2 to fit, 1 to hold out)")
    n_hold = min(n - 2, max(1, round(fraction * n)))
    order = np.random.default_rng(seed).permutation(n)
    return sorted(order[n_hold:].tolist()), sorted(order[:n_hold].tolist())


def open_loop_scorer(model: Any, hz: Horizons, weights: dict[str, float],
                     dt_s: float) -> OpenLoopScore:
    """Held-out open-loop SSE, summed over the channels in ``weights`` (each times its weight),
    on the horizons of some tasks, for terms added to ``model`` (:mod:`.trace`, criteria b, c);
    the force rollouts of one call run batched (:func:`~.predict.open_loop_many`)."""

    def corrected(terms: list) -> Any:
        if not terms:
            return model
        try:
            return corrected_model(model, [Term(c, ch, tuple(float(x) for x in coef))
                                           for c, ch, coef in terms], dt_s)
        except PeelError:  # e.g. an unstable lag fitted on one fold: no better than nothing
            return model

    def score(jobs: list) -> list[float]:
        models = [corrected(terms) for terms, _ in jobs]
        subs = [hz.subset(np.isin(hz.task, test_tasks)) for _, test_tasks in jobs]
        out = [0.0] * len(jobs)
        if VELOCITY_CHANNEL in weights:
            for j, (m, sub) in enumerate(zip(models, subs, strict=True)):
                err = sub.rows[:, -sub.steps:, 1] - P.speed_open_loop(m, sub)
                out[j] += weights[VELOCITY_CHANNEL] * _masked_sse(err, sub.valid)
        forces = [ch for ch in FORCE_CHANNELS if ch in weights]
        if forces:
            for j, (sub, pred) in enumerate(zip(subs, P.open_loop_many(models, subs),
                                                strict=True)):
                for ch in forces:
                    i = FORCE_CHANNELS.index(ch)
                    err = sub.rows[:, -sub.steps:, 2 + i] - pred[:, :, i]
                    out[j] += weights[ch] * _masked_sse(err, sub.valid)
        return out

    return score


def _masked_sse(err: np.ndarray, valid: np.ndarray) -> float:
    return float(np.sum(np.where(valid & np.isfinite(err), err, 0.0) ** 2))


def _force_trace(model: Any, s: Steps, hz: Horizons, cfg: ResidualConfig,
                 rng: np.random.Generator, dt_s: float) -> tuple[Trace, dict[str, Any]]:
    """Both force channels in one stacked regression, rows scaled by their RMS residual."""
    pred = P.one_step(model, s)
    grad = P.history_gradient(model, s)
    force = [c for c in cfg.candidates if set(c.spec.channels) & set(FORCE_CHANNELS)]
    resp = P.term_responses(s, pred, grad, force, dt_s)
    y = s.f_next - pred
    rms = np.sqrt(np.mean(y ** 2, axis=0))
    rms = np.where(rms > 1e-12, rms, 1.0)
    ys = np.concatenate([y[:, 0] / rms[0], y[:, 1] / rms[1]])
    cols = [_stacked(c, ch, J, rms) for (_, ch), (c, J) in resp.items()]
    n = len(s)
    weights = {ch: 1.0 / float(rms[i]) ** 2 for i, ch in enumerate(FORCE_CHANNELS)}
    prob = Problem.build(ys, np.concatenate([s.task, s.task]),
                         np.array(["fx"] * n + ["fz"] * n), cfg.folds,
                         open_loop_scorer(model, hz, weights, dt_s))
    tr = trace("force", prob, cols, cfg, rng)
    plot = {"y": y, "rms": rms, "cols": {(c.candidate.key, c.channel): c.X for c in cols}}
    return tr, plot


def _stacked(cand: Any, ch: str, J: np.ndarray, rms: np.ndarray) -> Column:
    """A candidate's column from its responses ``J [rows, 2 (output), n_basis]``: the F_RX
    rows over F_RX's RMS residual above the F_RZ rows over F_RZ's."""
    return Column(cand, ch, np.concatenate([J[:, 0, :] / rms[0], J[:, 1, :] / rms[1]]))


def _open_loop_force_trace(model: Any, hz: Horizons, hz_score: Horizons, cfg: ResidualConfig,
                           rng: np.random.Generator, dt_s: float, named: set[tuple[str, str]]
                           ) -> tuple[Trace, dict[str, Any]]:
    """The output-error fit (:mod:`.output_error`) of what the one-step fit left: both force
    channels' open-loop residual over the horizons ``hz`` of ``model`` (with the one-step
    terms) against each candidate's response, rows scaled by their RMS residual; the families
    the one-step fit named on a channel (``named``) are left out; the open-loop criteria of
    the selection score the planner's horizons ``hz_score``."""
    force = [c for c in cfg.candidates if set(c.spec.channels) & set(FORCE_CHANNELS)
             and not all((c.family, ch) in named for ch in FORCE_CHANNELS)]
    base, resp = OE.open_loop_responses(model, hz, force, dt_s)
    keep = OE.row_mask(hz)
    y = (hz.rows[:, -hz.steps:, 2:4] - base)[keep]
    rms = np.sqrt(np.mean(y ** 2, axis=0))
    rms = np.where(rms > 1e-12, rms, 1.0)
    task = np.broadcast_to(hz.task[:, None], keep.shape)[keep]
    cols = [_stacked(c, ch, J[keep], rms) for (_, ch), (c, J) in resp.items()
            if (c.family, ch) not in named]
    plot = {"y": y, "rms": rms, "steps": OE.row_steps(hz, keep),
            "cols": {(c.candidate.key, c.channel): c.X for c in cols}}
    n = len(y)
    weights = {ch: 1.0 / float(rms[i]) ** 2 for i, ch in enumerate(FORCE_CHANNELS)}
    prob = Problem.build(np.concatenate([y[:, 0] / rms[0], y[:, 1] / rms[1]]),
                         np.concatenate([task, task]), np.array(["fx"] * n + ["fz"] * n),
                         cfg.folds, open_loop_scorer(model, hz_score, weights, dt_s))
    return trace(OPEN_LOOP, prob, cols, cfg, rng), plot


def _speed_trace(model: Any, s: Steps, hz: Horizons, cfg: ResidualConfig,
                 rng: np.random.Generator, dt_s: float) -> tuple[Trace | None, dict[str, Any]]:
    ok = np.isfinite(s.u)
    if ok.sum() < 10 or len(np.unique(s.task[ok])) < 2:
        return None, {}
    v_k = s.hist[ok, -1, 1]
    rows = Rows(q=torch.zeros(int(ok.sum()), dtype=torch.float64),
                v=torch.as_tensor(v_k), u=torch.as_tensor(s.u[ok]))
    y = s.v_next[ok] - P.speed_one_step(model, v_k, s.u[ok])
    cols = [Column(c, VELOCITY_CHANNEL, c.basis(rows).numpy()) for c in cfg.candidates
            if VELOCITY_CHANNEL in c.spec.channels]
    prob = Problem.build(y, s.task[ok], np.array([VELOCITY_CHANNEL] * len(y)), cfg.folds,
                         open_loop_scorer(model, hz, {VELOCITY_CHANNEL: 1.0}, dt_s))
    tr = trace(VELOCITY_CHANNEL, prob, cols, cfg, rng)
    return tr, {"y": y, "cols": {(c.candidate.key, c.channel): c.X for c in cols}, "ok": ok}


def terms_of(traces: dict[str, Trace]) -> list[Term]:
    """The named findings as compensation terms."""
    return [Term(f.candidate, f.channel, tuple(float(c) for c in f.coef),
                 tuple(float(c) for c in f.coef_std))
            for tr in traces.values() for f in tr.findings]


def apply_decision(traces: dict[str, Trace], dropped: Sequence[tuple[Term, str]]) -> None:
    """Move the findings the held-out decision dropped to their trace's ``rejected``."""
    reasons = {(t.candidate.key, t.channel): why for t, why in dropped}
    for tr in traces.values():
        for f in list(tr.findings):
            why = reasons.get((f.candidate.key, f.channel))
            if why is not None:
                f.reason = why
                tr.findings.remove(f)
                tr.rejected.append(f)


def _end_residual(model: Any, hz: Horizons) -> tuple[np.ndarray, np.ndarray]:
    """Force residual at each horizon's last valid step ``[m, 2]`` and the horizons kept."""
    end = np.array([np.flatnonzero(v)[-1] if v.any() else -1 for v in hz.valid])
    keep = np.flatnonzero(end >= 0)
    err = hz.rows[:, -hz.steps:, 2:4] - P.open_loop(model, hz)
    return err[keep, end[keep]], keep


def start_force_drift(start: np.ndarray, alpha: float) -> list[dict[str, Any]]:
    """Per force channel (columns of ``start``, one row per task in recording order, N): does
    the measured force at each task's first sample change with the task order? The blade is
    at rest at C there, the same state in every task, so an offset shows whole
    (:func:`~.structure.drift_across_tasks`): on the task order alone, and, when the other
    channel shows no drift of its own, also with the other channel's first sample as covariate
    (it takes out the task-to-task variation both share; with a drifting covariate it would lend
    this channel the other's drift); the smaller p-value, Bonferroni-corrected for the two
    tests."""
    order = np.arange(len(start))
    plain = [drift_across_tasks(start[:, i], order, alpha) for i in range(2)]
    out = []
    for i in range(2):
        flag = dict(plain[i], statistic="start_force")
        other_p = plain[1 - i]["p"]
        if other_p is not None and other_p >= alpha:
            cov = drift_across_tasks(start[:, i], order, alpha, start[:, 1 - i])
            if cov["p"] is not None and cov["p"] < (plain[i]["p"] or 1.0):
                flag = dict(cov, statistic="start_force_with_other_channel")
            flag["p"] = min(1.0, 2 * flag["p"])
            flag["drift"] = flag["p"] < alpha
        out.append(flag)
    return out


def task_drift(model: Any, tasks: Sequence[Trajectory], h: int, cfg: ResidualConfig
               ) -> dict[str, dict[str, Any]]:
    """Per force channel: does the force change with the task order (every task, in recording
    order)? The flag is :func:`start_force_drift` on each task's first sample. Beside it, for
    the record, the same test on the per-task mean open-loop residual at the horizon end (the
    model, fed its own forces, lets go of part of an offset in its history; noisier on the
    plant)."""
    start = np.array([[tr.fx[0], tr.fz[0]] for tr in tasks])
    flags = start_force_drift(start, cfg.drift_alpha)
    hz = horizons(tasks, h, cfg.horizon_steps, 2 * cfg.stride)
    err, keep = _end_residual(model, hz)
    ids = np.unique(hz.task[keep])
    out = {}
    for i, ch in enumerate(FORCE_CHANNELS):
        per_task = np.array([err[hz.task[keep] == g, i].mean() for g in ids])
        out[ch] = {**flags[i], "open_loop_residual": drift_across_tasks(per_task, ids,
                                                                        cfg.drift_alpha)}
    return out


def _held_out(model: Any, corrected: Any | None, hold: list[Trajectory], h: int,
              cfg: ResidualConfig) -> tuple[E.Errors, E.Errors, dict[str, Any], list[Any]]:
    """Errors before and after on the held-out tasks, the open-loop drift left after the
    correction (mean residual at each horizon's last valid step), each term's share."""
    s_h, hz_h = E.held_out(hold, h, cfg.horizon_steps, cfg.stride)
    before = E.errors(model, s_h, hz_h)
    after = E.errors(corrected, s_h, hz_h) if corrected is not None else before
    end = np.array([np.flatnonzero(v)[-1] if v.any() else -1 for v in hz_h.valid])
    keep = np.flatnonzero(end >= 0)
    drift = {ch: open_loop_drift(after.open_loop[keep, end[keep], i], hz_h.task[keep])
             for i, ch in enumerate(FORCE_CHANNELS)}
    shares = E.term_shares(corrected, before, s_h, hz_h) if corrected is not None else []
    return before, after, drift, shares


#: The stages :func:`analyse` reports to its ``progress`` callback.
STAGES: tuple[str, ...] = ("residual and trace (forces)", "trace (speed)", "held-out decision",
                           "what remains", "error before/after")


def analyse(tasks: Sequence[Trajectory], model: Any, cfg: ResidualConfig, *,
            dt_s: float = 0.1, progress: Callable[[str], None] | None = None) -> Result:
    """Steps 1-5 of the module docstring; ``dt_s`` is the model's sample period;
    ``progress(stage)`` is called after each of :data:`STAGES`."""
    tick = progress or (lambda stage: None)
    h = int(model.h)
    fit_idx, hold_idx = split_tasks(len(tasks), cfg.holdout, cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    fit_tasks = [tasks[i] for i in fit_idx]
    fit_all = one_step_samples(fit_tasks, h)
    fit = fit_all.subset(fit_all.k >= h - 1)
    if len(np.unique(fit.task)) < 2:
        raise PeelError("fewer than 2 fit tasks have samples past the first h - 1")
    # the open-loop criteria of the trace score every second control period of the fit tasks
    hz_fit = horizons(fit_tasks, h, cfg.horizon_steps, 2 * cfg.stride)
    traces: dict[str, Trace] = {}
    plots: dict[str, Any] = {}
    traces["force"], plots["force"] = _force_trace(model, fit, hz_fit, cfg, rng, dt_s)
    if cfg.open_loop_fit:
        one_step = terms_of(traces)
        base = corrected_model(model, one_step, dt_s) if one_step else model
        hz_oe = horizons(fit_tasks, h, cfg.open_loop_fit_steps or cfg.horizon_steps,
                         cfg.open_loop_fit_stride)
        traces[OPEN_LOOP], plots[OPEN_LOOP] = _open_loop_force_trace(
            base, hz_oe, hz_fit, cfg, rng, dt_s, {(t.candidate.family, t.channel) for t in one_step})
    tick(STAGES[0])
    speed, vplot = _speed_trace(model, fit, hz_fit, cfg, rng, dt_s)
    if speed is not None:
        traces[VELOCITY_CHANNEL], plots[VELOCITY_CHANNEL] = speed, vplot
    tick(STAGES[1])
    hold = [tasks[i] for i in hold_idx]
    hz_hold = horizons(hold, h, cfg.horizon_steps, cfg.stride)
    terms, dropped = held_out_decision(model, terms_of(traces), hz_hold, dt_s)
    if cfg.heldout_alpha > 0:
        terms, inconsistent = consistency_check(model, terms, hz_hold, dt_s, cfg.heldout_alpha)
        dropped = [*dropped, *inconsistent]
    apply_decision(traces, dropped)
    corrected = corrected_model(model, terms, dt_s) if terms else None
    after_model = corrected if corrected is not None else model
    tick(STAGES[2])

    y_after = fit.f_next - P.one_step(after_model, fit)
    X = state_variables(fit)
    structure = [one_step_structure(ch, y_after[:, i], X, fit.task, cfg.folds,
                                    cfg.min_structure, cfg.seed)
                 for i, ch in enumerate(FORCE_CHANNELS)]
    drift_tasks = task_drift(after_model, tasks, h, cfg)
    tick(STAGES[3])

    before, after, drift, shares = _held_out(model, corrected, hold, h, cfg)
    tick(STAGES[4])
    return Result(
        traces=traces, terms=terms, corrected=corrected, fit_tasks=fit_idx,
        holdout_tasks=hold_idx, rmse_before=before.rmse(), rmse_after=after.rmse(),
        by_step_before=before.by_step(), by_step_after=after.by_step(),
        structure=structure, drift=drift, shares=shares, task_drift=drift_tasks,
        samples={"fit_one_step": len(fit), "holdout_one_step": len(before.one_step),
                 "holdout_open_loop_runs": len(before.open_loop),
                 "horizon_steps": cfg.horizon_steps},
        plots={"traces": plots, "fit": fit, "X": X, "y_after": y_after})
