"""What the named terms leave: structure in the residual that no candidate explains.

Two checks, each with its evidence in the report:

* **one step**: a flexible regressor (scikit-learn ``HistGradientBoostingRegressor``) of the
  one-step residual after the correction on the physical variables of the sample -- q, v_k,
  v_{k+1}, t, F_RX, F_RZ, the speed change and the command. Its held-out R^2 (folds by task) is
  the share of the residual that *some* function of these variables explains; at or above
  ``min_structure`` the residual "has structure that no candidate explains", and the
  permutation importances name the variables it depends on. A residual that no function of
  the measured state predicts (stick-slip timing, white sensor noise) scores about 0;
* **open loop**: the mean residual at the horizon's end with its standard error over tasks; a
  mean beyond 3 standard errors is a systematic open-loop drift of the model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sklearn.ensemble import HistGradientBoostingRegressor
from sklearn.inspection import permutation_importance
from sklearn.model_selection import GroupKFold

from .data import Steps

VARIABLES: tuple[str, ...] = ("q_mm", "v_mmps", "v_next_mmps", "t_s", "fx_n", "fz_n",
                              "dv_mmps", "u_mmps")


def state_variables(s: Steps) -> np.ndarray:
    """``[n, len(VARIABLES)]``: the sample's physical variables (u = v_next where unknown)."""
    last = s.hist[:, -1]
    u = np.where(np.isfinite(s.u), s.u, s.v_next)
    return np.stack([last[:, 0], last[:, 1], s.v_next, s.t_next, last[:, 2], last[:, 3],
                     s.v_next - last[:, 1], u], axis=1)


@dataclass
class Structure:
    """Held-out R^2 of the flexible regressor and the variables it uses most."""

    channel: str
    heldout_r2: float
    per_fold: list[float]
    importance: dict[str, float] = field(default_factory=dict)
    remains: bool = False

    def to_json(self) -> dict[str, Any]:
        return {"channel": self.channel, "mode": "one_step", "heldout_r2": self.heldout_r2,
                "per_fold": self.per_fold, "importance": self.importance,
                "remains": self.remains}


def one_step_structure(channel: str, y: np.ndarray, X: np.ndarray, groups: np.ndarray,
                       folds: int, min_structure: float, seed: int) -> Structure:
    """Cross-validated (by task) R^2 of a gradient-boosted regressor of ``y`` on ``X``."""
    splits = list(GroupKFold(n_splits=min(folds, len(np.unique(groups)))).split(X, y, groups))
    per, pred = [], np.zeros_like(y)
    model = None
    for train, test in splits:
        model = HistGradientBoostingRegressor(max_iter=150, max_leaf_nodes=15,
                                              learning_rate=0.1, l2_regularization=1.0,
                                              random_state=seed).fit(X[train], y[train])
        pred[test] = model.predict(X[test])
        ss = float(np.sum((y[test] - y[test].mean()) ** 2))
        per.append(1.0 - float(np.sum((y[test] - pred[test]) ** 2)) / max(ss, 1e-300))
    r2 = 1.0 - float(np.sum((y - pred) ** 2)) / max(float(np.sum((y - y.mean()) ** 2)), 1e-300)
    out = Structure(channel, r2, per, remains=r2 >= min_structure)
    if model is not None and out.remains:
        _, test = splits[-1]
        imp = permutation_importance(model, X[test], y[test], n_repeats=5, random_state=seed)
        order = np.argsort(-imp.importances_mean)
        out.importance = {VARIABLES[i]: float(imp.importances_mean[i]) for i in order[:4]}
    return out


def open_loop_drift(resid_end: np.ndarray, groups: np.ndarray) -> dict[str, Any]:
    """Mean residual at the horizon end, its standard error over tasks, and whether |mean| >
    3 SE (a systematic drift of the open-loop prediction)."""
    ids = np.unique(groups)
    per_task = np.array([resid_end[groups == g].mean() for g in ids])
    mean = float(resid_end.mean())
    se = float(per_task.std(ddof=1) / np.sqrt(len(ids))) if len(ids) > 1 else float("nan")
    return {"mean_n": mean, "se_n": se, "tasks": len(ids),
            "drift": bool(np.isfinite(se) and abs(mean) > 3 * se)}


def drift_across_tasks(per_task: np.ndarray, order: np.ndarray, alpha: float,
                       covariate: np.ndarray | None = None) -> dict[str, Any]:
    """Whether a per-task force changes with the task order (a between-task drift).

    Ordinary least squares of ``per_task`` (one value per task, N) on an intercept, ``order``
    (the tasks' position in the recording) and, when given, ``covariate`` (per task: the other
    channel's value, which takes out the task-to-task variation both channels share); the order
    coefficient's t statistic with n - p degrees of freedom; flagged when its two-sided p-value
    is below ``alpha``. A force offset that changes from one task to the next but is constant
    within each (pad wear, a sensor zero that moves between tasks) is invisible to every
    within-task candidate and shows here."""
    from scipy.stats import t as student_t

    cols = [np.ones(per_task.size), order.astype(float) - order.mean()]
    if covariate is not None:
        cols.append(covariate - covariate.mean())
    X = np.column_stack(cols)
    dof = per_task.size - X.shape[1]
    if dof < 2:
        return {"slope_n_per_task": None, "se": None, "p": None, "tasks": int(per_task.size),
                "drift": False}
    b, *_ = np.linalg.lstsq(X, per_task, rcond=None)
    r = per_task - X @ b
    se = float(np.sqrt(np.linalg.pinv(X.T @ X)[1, 1] * (r @ r) / dof))
    p = float(2 * student_t.sf(abs(b[1]) / se, dof)) if se > 0 else 0.0
    return {"slope_n_per_task": float(b[1]), "se": se, "p": p, "tasks": int(per_task.size),
            "drift": p < alpha}
