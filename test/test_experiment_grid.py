"""The grid report's arithmetic (docs/experiments.md, "Plant levels and sequences"):
confidence intervals and the fraction of headroom closed, on hand-made results."""

import math

import pytest

from peel_experiments.grid import ci95, closed_fraction, grid_targets


def _runs(costs_by_seed):
    return {s: {m: {"tasks": [{"cost": c} for c in cs]} for m, cs in ms.items()}
            for s, ms in costs_by_seed.items()}


def test_ci95_is_the_t_interval():
    c = ci95([1.0, 2.0, 3.0])
    assert c["mean"] == 2.0 and c["n"] == 3
    assert c["ci95"] == pytest.approx(4.303 * 1.0 / math.sqrt(3), rel=1e-3)
    assert ci95([5.0])["ci95"] is None
    assert ci95([])["mean"] is None


def test_closed_fraction_windows_and_pools():
    # headroom 2 per task; OL closes 1 of it on seed "0" and all of it on seed "1"
    runs = _runs({
        "0": {"baseline1": [10.0] * 10, "oracle": [8.0] * 10, "ol-mppi": [9.0] * 10},
        "1": {"baseline1": [10.0] * 10, "oracle": [8.0] * 10, "ol-mppi": [8.0] * 10},
    })
    f = closed_fraction(runs, "ol-mppi", 5, window=2)
    assert f["values"] == [0.5, 1.0] and f["pooled"] == pytest.approx(0.75)
    assert f["window"] == [3, 7] and f["headroom_in_window"] == pytest.approx(2.0)
    # window clipped at the run's end; tasks beyond the run are not reported
    assert closed_fraction(runs, "ol-mppi", 10)["pooled"] == pytest.approx(0.75)
    assert closed_fraction(runs, "ol-mppi", 11)["n"] == 0
    # only the window counts: OL equal to Baseline 1 on tasks 1-2, to the oracle on 3-7
    runs2 = _runs({"0": {"baseline1": [10.0] * 10, "oracle": [8.0] * 10,
                         "ol-mppi": [10.0, 10.0] + [8.0] * 8}})
    assert closed_fraction(runs2, "ol-mppi", 5)["pooled"] == pytest.approx(1.0)
    assert closed_fraction(runs2, "ol-mppi", 2, window=1)["pooled"] == pytest.approx(1 / 3)


def test_targets_read_the_strongest_level():
    summary = {"levels": [1, 3], "cells": {
        "L3_stationary": {"headroom_rel": {"mean": 0.5},
                          "closed": {"ol-mppi": {"5": {"pooled": 0.8}, "10": {"pooled": 0.6}}},
                          "metrics": {"ol-mppi": {"safety_stops": 0}}},
        "L3_drift": {"ol_minus_b2_last5": {"mean": -0.3, "ci95": 0.5}}}}
    t = grid_targets(summary)
    assert t["level"] == 3 and t["baseline1_30pct_above_oracle"]
    assert t["ol_closed_task5_met"] and not t["ol_closed_task10_met"]
    assert t["drift_ol_ahead_of_b2"] and not t["drift_ol_ahead_of_b2_significant"]
