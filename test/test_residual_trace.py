"""The selection of ``peel residual`` on regression problems whose answer is known.

Residual rows built from known columns plus task-correlated noise: the true candidate is named
with an interval that covers its coefficient, a decoy is not; pure noise names nothing; a term
that helps one step ahead but hurts the open-loop score is rejected with that reason. And the
tasks of a bag rebuilt from its streams equal its /peel/trajectory messages.
"""

from __future__ import annotations

import numpy as np
import pytest
from residual_helpers import generate_tasks, write_bag
from scipy.linalg import lstsq

from peel_model.effect_terms import Candidate
from peel_residual import trace as trace_module
from peel_residual.cli import warn_unconverged
from peel_residual.config import load_residual_config
from peel_residual.tasks import tasks_from_bag
from peel_residual.trace import Column, Problem, TaskLeastSquares, lasso_select, trace

CFG = load_residual_config(bootstrap=100)


def _problem(coef: dict[str, float], n_tasks: int = 12, per: int = 150, seed: int = 0,
             score=None) -> tuple[Problem, list[Column]]:
    rng = np.random.default_rng(seed)
    groups = np.repeat(np.arange(n_tasks), per)
    n = groups.size
    cols = {
        "viscous_drag": rng.normal(size=(n, 1)),
        "sensor_offset": rng.normal(size=(n, 1)),
        "periodic_adhesion": rng.normal(size=(n, 2)),
    }
    y = rng.normal(size=n) + 0.3 * rng.normal(size=n_tasks)[groups]  # within-task correlation
    for name, c in coef.items():
        y = y + cols[name][:, 0] * c
    columns = [Column(Candidate(k, 6.0 if k == "periodic_adhesion" else None), "fx", X)
               for k, X in cols.items()]
    return Problem.build(y, groups, np.array(["fx"] * n), 5, score), columns


def test_least_squares_by_task_equals_least_squares_on_the_rows() -> None:
    """Fits from the tasks' stacked QR factors equal scipy's lstsq on the rows themselves: on
    every task, on a fold's tasks, on a bootstrap resample (a task drawn twice counts twice),
    with a task shorter than the number of columns, and with a dependent column (the
    minimum-norm solution)."""
    rng = np.random.default_rng(5)
    groups = np.concatenate([np.repeat(np.arange(7), 40), [7, 7]])  # task 7: 2 rows, 4 columns
    X = rng.normal(size=(groups.size, 4)) * [1.0, 1e3, 1e-3, 1.0]
    y = X @ [0.5, -2e-3, 300.0, 0.0] + rng.normal(size=groups.size)
    for design in (X, np.column_stack([X, X[:, 0] - X[:, 3]])):
        ls = TaskLeastSquares.of(design, y, groups)
        assert [r.shape[0] for r in ls.R] == [design.shape[1]] * 7 + [2]
        np.testing.assert_allclose(ls.fit(np.ones(8)), lstsq(design, y)[0], rtol=1e-9, atol=1e-12)
        fold = np.isin(groups, [0, 2, 3, 7])
        np.testing.assert_allclose(ls.fit_tasks(np.array([0, 2, 3, 7])),
                                   lstsq(design[fold], y[fold])[0], rtol=1e-9, atol=1e-12)
        pick = np.array([1, 1, 4, 5, 7, 0, 0, 0])
        rows = np.concatenate([np.flatnonzero(groups == g) for g in pick])
        np.testing.assert_allclose(ls.fit(np.bincount(pick, minlength=8)),
                                   lstsq(design[rows], y[rows])[0], rtol=1e-9, atol=1e-12)


def test_the_true_term_is_named_with_its_coefficient() -> None:
    p, cols = _problem({"viscous_drag": 0.6})
    res = trace("force", p, cols, CFG, np.random.default_rng(1))
    assert [f.candidate.family for f in res.findings] == ["viscous_drag"]
    f = res.findings[0]
    assert f.ci_low[0] < 0.6 < f.ci_high[0]
    assert f.explained_variance > 0.1 and f.coef_std[0] > 0
    assert "viscous_drag@fx" in res.lasso["kept"]


def test_noise_names_nothing() -> None:
    for seed in range(3):
        p, cols = _problem({}, seed=seed)
        res = trace("force", p, cols, CFG, np.random.default_rng(seed))
        assert res.findings == [], [f.candidate.key for f in res.findings]


def test_a_term_that_hurts_the_open_loop_is_rejected() -> None:
    def score(jobs):  # any term makes the "rollouts" worse
        return [100.0 + 10.0 * len(terms) for terms, _ in jobs]

    p, cols = _problem({"viscous_drag": 0.6}, score=score)
    res = trace("force", p, cols, CFG, np.random.default_rng(1))
    assert res.findings == []
    assert any("open-loop error worse" in f.reason for f in res.rejected)


def test_lasso_fits_that_do_not_converge_are_counted_and_warned(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    p, cols = _problem({"viscous_drag": 0.6})
    _, ok = lasso_select(p, cols)
    assert ok["unconverged_fits"] == 0
    assert warn_unconverged({"force": trace("force", p, cols, CFG, np.random.default_rng(1))}) \
        == []
    monkeypatch.setattr(trace_module, "LASSO_MAX_ITER", 1)
    _, bad = lasso_select(p, cols)
    assert bad["unconverged_fits"] > 0
    res = trace("force", p, cols, CFG, np.random.default_rng(1))
    lines = warn_unconverged({"force": res, "v": res})
    err = capsys.readouterr().err.splitlines()
    assert err == lines and len(lines) == 2
    assert f"{res.lasso['unconverged_fits']} lasso fit(s) on channel(s) fx, fz" in lines[0]
    assert "on channel(s) v did not converge" in lines[1]


@pytest.mark.parametrize("source", ["plant"])
def test_tasks_rebuilt_from_streams_equal_the_trajectories(tmp_path, source) -> None:
    trajs = generate_tasks(source, n=2, seed=5, u_max=4.0)
    a = tasks_from_bag(write_bag(tmp_path / "traj", trajs))
    b = tasks_from_bag(write_bag(tmp_path / "streams", trajs, trajectory=False, streams=True))
    assert len(a) == len(b) == 2
    for x, y in zip(a, b, strict=True):
        for name in ("t", "q", "v", "fx", "fz"):
            assert np.allclose(getattr(x, name), getattr(y, name), atol=1e-9), name
        # the streams carry the command of each control period, held
        assert np.allclose(x.u[:-1], y.u[:-1], atol=1e-12)
