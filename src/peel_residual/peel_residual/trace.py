"""Trace the residual to candidate effects: sparse regression with cross-validation by task.

The regression (docs/residual.md): residuals y, one row per (sample, channel), against the
columns X of every candidate term (a candidate on one channel). For the force channels the rows
of F_RX and F_RZ are stacked, each divided by its channel's RMS residual so that both weigh
alike, and a column is the change of the model's one-step prediction of *both* channels per
unit coefficient of the term (:func:`~.predict.term_responses`): a term on F_RZ also moves the
model's F_RX prediction, and the fit sees it. For the speed channel the columns are the basis
functions themselves. No intercept: a model has no one-step bias on the data it was trained on,
and a constant force is a candidate of its own (sensor offset).

1. **Selection** (scikit-learn ``LassoCV`` on columns scaled to unit RMS, folds =
   ``GroupKFold`` by task, coordinate descent on the Gram matrix): the lasso at the largest
   alpha whose cross-validated error is within one standard error of the minimum (the
   "one-standard-error rule", the sparser of the equivalent models) keeps the terms with a
   non-zero coefficient (above :data:`LASSO_ZERO`). Of several variants of one
   family on one channel (periods, time constants) the one with the lowest held-out error is
   kept.
2. **Significance** (backward elimination): a term stays only if (a) its coefficients differ
   from zero at ``ci_level`` (Wald test with the covariance of a bootstrap over tasks), (b) it
   explains at least ``min_explained`` of the held-out residual -- one step ahead (the increase
   of the cross-validated, by task, sum of squares of its channel's rows when it is left out,
   over that channel's mean square) or open loop over the planner's horizon (the same with the
   corrected model's open-loop error on the held-out fold's tasks, coefficients fitted on the
   other folds, over the uncorrected model's) -- and (c) leaving it out does not lower the
   held-out open-loop error (a term that helps one step ahead but hurts the planner's rollouts
   is not added). The weakest failing term is dropped and the rest refitted until all pass.
3. **Coefficients**: ordinary least squares on all fit rows; standard errors and percentile
   intervals from the bootstrap over tasks (resampling whole tasks keeps the within-task
   correlation of the residual).

Every least-squares fit here is on a set of whole tasks (a fold's training tasks, a bootstrap
resample, all of them), so each task's rows are reduced once to their QR factors
(:class:`TaskLeastSquares`) and a fit solves the stacked factors of its tasks: the same
least-squares problem as on the rows themselves (same normal equations, same singular values),
at the cost of a system of tasks x columns rows instead of every sample.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import lstsq, qr
from scipy.stats import chi2
from sklearn.exceptions import ConvergenceWarning
from sklearn.linear_model import Lasso, LassoCV
from sklearn.model_selection import GroupKFold

from peel_model.effect_terms import Candidate

from .config import ResidualConfig

#: Coordinate-descent iterations of each lasso fit (a fit that needs more is counted as not
#: converged in ``Trace.lasso["unconverged_fits"]`` and warned about by ``peel residual``).
LASSO_MAX_ITER = 20000

#: A lasso coefficient (of a column scaled to unit RMS, rows in units of their channel's RMS
#: residual) at or below this is rounding of the coordinate descent on the Gram matrix, not a
#: kept term.
LASSO_ZERO = 1e-10

#: ``[(terms [(candidate, channel, coefficients)], test task ids), ...] -> the open-loop SSE
#: of each`` (one call scores many, so that their rollouts run batched).
OpenLoopScore = Callable[[list[tuple[list[tuple[Candidate, str, np.ndarray]], np.ndarray]]],
                         list[float]]


@dataclass
class Column:
    """One candidate on one channel and its regression columns ``X [rows, n_basis]``."""

    candidate: Candidate
    channel: str
    X: np.ndarray

    @property
    def key(self) -> str:
        return f"{self.candidate.key}@{self.channel}"


@dataclass
class Problem:
    """The regression: residual rows, their task (group) and channel, the CV folds."""

    y: np.ndarray
    groups: np.ndarray
    channel: np.ndarray  # channel name of each row
    splits: list[tuple[np.ndarray, np.ndarray]]
    score: OpenLoopScore | None = None
    #: :func:`open_loop_sse_many` of each column list scored so far (keys in order): the backward
    #: elimination meets a set again after a drop, and its folds' fits are the same.
    open_loop_memo: dict[tuple[str, ...], float] = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, y: np.ndarray, groups: np.ndarray, channel: np.ndarray, folds: int,
              score: OpenLoopScore | None = None) -> Problem:
        n = len(np.unique(groups))
        splits = list(GroupKFold(n_splits=min(folds, n)).split(y, y, groups))
        return cls(y, groups, channel, splits, score)

    def mean_square(self, channel: str) -> float:
        return float(np.sum(self.y[self.channel == channel] ** 2))


@dataclass
class Finding:
    """A term that passed (or, in ``rejected``, failed) the significance test."""

    candidate: Candidate
    channel: str
    coef: np.ndarray
    coef_std: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    explained_variance: float
    fold_gains: list[float]
    wald: float
    wald_critical: float
    open_loop_share: float | None = None
    reason: str = ""

    @property
    def share(self) -> float:
        """The larger of the one-step and the open-loop held-out shares."""
        ol = self.open_loop_share
        return max(self.explained_variance, ol if ol is not None else -np.inf)

    def to_json(self) -> dict[str, Any]:
        spec = self.candidate.spec
        return {"name": self.candidate.family, "key": self.candidate.key, "label": spec.label,
                "meaning": spec.meaning, "variable": spec.variable, "channel": self.channel,
                "param_name": spec.param, "param": self.candidate.param,
                "basis": list(self.candidate.expressions),
                "coefficients": self.coef.tolist(), "coefficient_std": self.coef_std.tolist(),
                "ci_low": self.ci_low.tolist(), "ci_high": self.ci_high.tolist(),
                "explained_variance": self.explained_variance,
                "explained_variance_per_fold": self.fold_gains,
                "explained_variance_open_loop": self.open_loop_share,
                "wald": self.wald, "wald_critical": self.wald_critical, "reason": self.reason}


@dataclass
class Trace:
    """The outcome of :func:`trace` for one group of channels (``force`` or ``v``)."""

    group: str
    n_rows: int
    n_tasks: int
    findings: list[Finding] = field(default_factory=list)
    rejected: list[Finding] = field(default_factory=list)
    lasso: dict[str, Any] = field(default_factory=dict)
    single: list[dict[str, Any]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"group": self.group, "rows": self.n_rows, "tasks": self.n_tasks,
                "named": [f.to_json() for f in self.findings],
                "rejected": [f.to_json() for f in self.rejected], "lasso": self.lasso,
                "best_single_candidates": self.single}


def _design(cols: Sequence[Column]) -> np.ndarray:
    return np.concatenate([c.X for c in cols], axis=1)


@dataclass
class TaskLeastSquares:
    """Ordinary least squares of ``y`` on ``X`` over any multiset of whole tasks.

    Each task's rows ``X_t = Q_t R_t`` are kept as ``R_t`` and ``z_t = Q_t' y_t`` (the R factor
    of ``[X_t y_t]``, LAPACK ``geqrf`` through scipy, Q never formed); the fit on
    task ``t`` counted ``w_t`` times solves ``[sqrt(w_t) R_t] b = [sqrt(w_t) z_t]`` stacked, whose
    normal equations ``sum w_t X_t'X_t b = sum w_t X_t'y_t`` are those of the rows themselves
    (scipy's ``lstsq``, the minimum-norm solution when the columns are dependent)."""

    ids: np.ndarray
    R: list[np.ndarray]
    z: list[np.ndarray]

    @classmethod
    def of(cls, X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> TaskLeastSquares:
        ids = np.unique(groups)
        k = X.shape[1]
        R, z = [], []
        for g in ids:
            rows = groups == g
            r = qr(np.column_stack([X[rows], y[rows]]), mode="r", overwrite_a=True,
                   check_finite=False)[0][:min(int(rows.sum()), k)]
            R.append(r[:, :k])
            z.append(r[:, k])
        return cls(ids, R, z)

    def fit(self, weight: np.ndarray) -> np.ndarray:
        """Coefficients with task ``ids[i]``'s rows counted ``weight[i]`` times (0: left out)."""
        use = np.flatnonzero(weight > 0)
        root = np.sqrt(weight[use].astype(float))
        A = np.concatenate([w * self.R[i] for w, i in zip(root, use, strict=True)])
        b = np.concatenate([w * self.z[i] for w, i in zip(root, use, strict=True)])
        return lstsq(A, b)[0]

    def fit_tasks(self, tasks: np.ndarray) -> np.ndarray:
        """Coefficients on the rows of ``tasks`` (each once)."""
        return self.fit(np.isin(self.ids, tasks).astype(float))


def _solver(p: Problem, cols: Sequence[Column]) -> tuple[np.ndarray, TaskLeastSquares]:
    X = _design(cols)
    return X, TaskLeastSquares.of(X, p.y, p.groups)


def cv_residual(p: Problem, cols: Sequence[Column],
                solved: tuple[np.ndarray, TaskLeastSquares] | None = None) -> np.ndarray:
    """Held-out residual of every row: OLS on ``cols`` fitted on the other folds
    (``solved``: :func:`_solver` of ``cols``, when the caller has it)."""
    if not cols:
        return p.y.copy()
    X, ls = solved or _solver(p, cols)
    r = np.empty_like(p.y)
    for train, test in p.splits:
        r[test] = p.y[test] - X[test] @ ls.fit_tasks(p.groups[train])
    return r


def _split_coef(cols: Sequence[Column], coef: np.ndarray) -> list[np.ndarray]:
    out, start = [], 0
    for c in cols:
        out.append(coef[start:start + c.X.shape[1]])
        start += c.X.shape[1]
    return out


def open_loop_sse_many(p: Problem, col_lists: Sequence[Sequence[Column]]) -> list[float]:
    """Held-out open-loop SSE of each column list: per fold, OLS on the other folds,
    ``p.score`` on its tasks; every fold of every list not scored before in one call."""
    assert p.score is not None
    keys = [tuple(c.key for c in cols) for cols in col_lists]
    todo = {k: cols for k, cols in zip(keys, col_lists, strict=True) if k not in p.open_loop_memo}
    jobs, owner = [], []
    for k, cols in todo.items():
        ls = _solver(p, cols)[1] if cols else None
        for train, test in p.splits:
            terms = []
            if ls is not None:
                parts = _split_coef(cols, ls.fit_tasks(p.groups[train]))
                terms = [(c.candidate, c.channel, b) for c, b in zip(cols, parts, strict=True)]
            jobs.append((terms, np.unique(p.groups[test])))
            owner.append(k)
    for k in todo:
        p.open_loop_memo[k] = 0.0
    for k, sse in zip(owner, p.score(jobs) if jobs else [], strict=True):
        p.open_loop_memo[k] += sse
    return [p.open_loop_memo[k] for k in keys]


def bootstrap_coefs(p: Problem, cols: Sequence[Column], n: int, rng: np.random.Generator,
                    ls: TaskLeastSquares | None = None) -> np.ndarray:
    """OLS coefficients on ``n`` resamples of whole tasks: ``[n, n_columns]``."""
    ls = ls or _solver(p, cols)[1]
    out = np.empty((n, sum(c.X.shape[1] for c in cols)))
    for b in range(n):
        pick = rng.choice(ls.ids, size=ls.ids.size, replace=True)
        out[b] = ls.fit(np.bincount(np.searchsorted(ls.ids, pick), minlength=ls.ids.size))
    return out


def _one_se_alpha(cv: LassoCV) -> float:
    """The largest alpha whose cross-validated error is within one SE of the minimum."""
    mse = cv.mse_path_  # [n_alphas, n_folds], alphas_ descending
    mean, se = mse.mean(axis=1), mse.std(axis=1) / np.sqrt(mse.shape[1])
    best = int(np.argmin(mean))
    return float(cv.alphas_[int(np.flatnonzero(mean <= mean[best] + se[best])[0])])


def lasso_select(p: Problem, cols: Sequence[Column]) -> tuple[list[int], dict[str, Any]]:
    """Indices of the terms the one-standard-error lasso keeps, and its path summary."""
    X = _design(cols)
    scale = np.sqrt(np.mean(X ** 2, axis=0))
    Xs = X / np.where(scale > 1e-12, scale, 1.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        cv = LassoCV(fit_intercept=False, cv=p.splits, alphas=40, eps=1e-2, precompute=True,
                     max_iter=LASSO_MAX_ITER, tol=1e-4).fit(Xs, p.y)
        coef = Lasso(alpha=_one_se_alpha(cv), fit_intercept=False, precompute=True,
                     max_iter=LASSO_MAX_ITER).fit(Xs, p.y).coef_
    best = int(np.argmin(cv.mse_path_.mean(axis=1)))
    owner = np.concatenate([np.full(c.X.shape[1], i) for i, c in enumerate(cols)])
    keep = sorted({int(owner[j]) for j in np.flatnonzero(np.abs(coef) > LASSO_ZERO)})
    return keep, {"alpha_min": float(cv.alphas_[best]), "alpha_1se": _one_se_alpha(cv),
                  "kept": [cols[i].key for i in keep],
                  "unconverged_fits": sum(issubclass(w.category, ConvergenceWarning)
                                          for w in caught)}


def _best_variants(p: Problem, cols: Sequence[Column], chosen: list[int]) -> list[int]:
    """One variant per family and channel: the lowest held-out error beside the others."""
    groups: dict[tuple[str, str], list[int]] = {}
    for i in chosen:
        groups.setdefault((cols[i].candidate.family, cols[i].channel), []).append(i)
    keep = []
    for key, variants in groups.items():
        others = [i for i in chosen if (cols[i].candidate.family, cols[i].channel) != key]
        sse = [float(np.sum(cv_residual(p, [cols[j] for j in [*others, i]]) ** 2))
               for i in variants]
        keep.append(variants[int(np.argmin(sse))])
    return sorted(keep)


def _assess(p: Problem, cols: Sequence[Column], cfg: ResidualConfig,
            rng: np.random.Generator) -> list[Finding]:
    """Coefficients, intervals, Wald statistics and one-step shares of every term; the
    open-loop shares (the expensive part) only once every term passes the Wald test."""
    solved = _solver(p, cols)
    ls = solved[1]
    r_full = cv_residual(p, cols, solved)
    boots = bootstrap_coefs(p, cols, cfg.bootstrap, rng, ls)
    coefs = _split_coef(cols, ls.fit(np.ones(ls.ids.size)))
    stds = _split_coef(cols, boots.std(axis=0))
    lo = _split_coef(cols, np.quantile(boots, (1 - cfg.ci_level) / 2, axis=0))
    hi = _split_coef(cols, np.quantile(boots, 1 - (1 - cfg.ci_level) / 2, axis=0))
    draws = _split_coef(cols, boots.T)
    out = []
    for i, c in enumerate(cols):
        r_without = cv_residual(p, [cols[j] for j in range(len(cols)) if j != i])
        own = p.channel == c.channel
        b = draws[i].T  # [n_boot, n_basis]
        mu = b.mean(axis=0)
        try:
            wald = float(mu @ np.linalg.solve(np.atleast_2d(np.cov(b, rowvar=False)), mu))
        except np.linalg.LinAlgError:
            wald = 0.0
        folds = []
        for _, test in p.splits:
            t = test[own[test]]
            folds.append(float((np.sum(r_without[t] ** 2) - np.sum(r_full[t] ** 2))
                               / max(np.sum(p.y[t] ** 2), 1e-300)))
        out.append(Finding(
            candidate=c.candidate, channel=c.channel, coef=coefs[i], coef_std=stds[i],
            ci_low=lo[i], ci_high=hi[i],
            explained_variance=float((np.sum(r_without[own] ** 2) - np.sum(r_full[own] ** 2))
                                     / max(p.mean_square(c.channel), 1e-300)),
            fold_gains=folds, wald=wald, wald_critical=float(chi2.ppf(cfg.ci_level, len(mu)))))
    if p.score is not None and all(f.wald >= f.wald_critical for f in out):
        rests = [[cols[j] for j in range(len(cols)) if j != i] for i in range(len(cols))]
        ol_none, ol_full, *ol_rest = open_loop_sse_many(p, [[], cols, *rests])
        if ol_none > 0:
            for f, ol in zip(out, ol_rest, strict=True):
                f.open_loop_share = (ol - ol_full) / ol_none
    return out


def _failure(f: Finding, cfg: ResidualConfig) -> str:
    """Why ``f`` is not significant ('' when it is)."""
    if f.wald < f.wald_critical:
        return (f"coefficients not distinct from 0 at {cfg.ci_level:.0%} (Wald {f.wald:.1f} < "
                f"{f.wald_critical:.1f})")
    if f.open_loop_share is not None and f.open_loop_share < 0:
        return f"makes the held-out open-loop error worse ({f.open_loop_share:+.1%})"
    if f.share < cfg.min_explained:
        ol = "" if f.open_loop_share is None else f", open loop {f.open_loop_share:.1%}"
        return (f"explains {f.explained_variance:.1%} one step ahead{ol} "
                f"< {cfg.min_explained:.0%}")
    return ""


def _singles(p: Problem, cols: Sequence[Column]) -> list[dict[str, Any]]:
    """The five candidates with the largest held-out one-step share alone (evidence when
    nothing is named)."""
    out = []
    for c in cols:
        own = p.channel == c.channel
        gain = np.sum(p.y[own] ** 2) - np.sum(cv_residual(p, [c])[own] ** 2)
        out.append({"key": c.candidate.key, "channel": c.channel,
                    "explained_variance": float(gain / max(p.mean_square(c.channel), 1e-300))})
    return sorted(out, key=lambda d: -d["explained_variance"])[:5]


def trace(group: str, p: Problem, cols: Sequence[Column], cfg: ResidualConfig,
          rng: np.random.Generator) -> Trace:
    """Steps 1-3 of the module docstring."""
    cols = [c for c in cols if np.all(np.isfinite(c.X)) and np.sqrt(np.mean(c.X ** 2)) > 1e-9]
    res = Trace(group, int(p.y.size), len(np.unique(p.groups)))
    if not cols or not np.any(p.y):
        return res
    res.single = _singles(p, cols)
    chosen, res.lasso = lasso_select(p, cols)
    current = [cols[i] for i in _best_variants(p, cols, chosen)]
    while current:
        found = _assess(p, current, cfg, rng)
        for f in found:
            f.reason = _failure(f, cfg)
        failing = [f for f in found if f.reason]
        if not failing:
            res.findings = found
            break
        walds = [f for f in failing if f.wald < f.wald_critical]
        worst = min(walds or failing, key=lambda f: f.share)
        res.rejected.append(worst)
        current = [c for c in current
                   if (c.candidate, c.channel) != (worst.candidate, worst.channel)]
    return res
