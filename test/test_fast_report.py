"""``peel fast-report`` on hand-made results: the fractions closed at single tasks, task 1's
second-half error ratio, the times, the files; a results file without an arm is one line, exit 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from peel_experiments.fast_report import summarize


def _task(cost: float, fast: bool = False) -> dict:
    rec = {"cost": cost, "outcome": "done", "plan_s": 0.05, "next_update_s": 1.0}
    if fast:
        rec["fast"] = {"steps": 4, "accepted": 2, "fast_s": [0.1, 0.2, 0.3, 0.4],
                       "results": [{"n_samples": 30, "accepted": True}],
                       "error_in_use_second_half_n": 0.6, "error_pretrained_second_half_n": 1.2,
                       "error_in_use_n": [1.0, 0.8, 0.6, 0.6],
                       "error_pretrained_n": [1.0, 1.0, 1.2, 1.2]}
    return rec


def results() -> dict:
    """Two seeds, 3 tasks: B1 14, oracle 10 (headroom 4); fast 12 then 10 (closed 0.5, 1.0),
    ol-mppi 14 then 11, baseline 2 13 throughout."""
    costs = {"baseline1": [14, 14, 14], "oracle": [10, 10, 10], "ol-mppi-fast": [12, 10, 10],
             "ol-mppi": [14, 11, 11], "baseline2": [13, 13, 13]}
    runs = {s: {m: {"tasks": [_task(c, m == "ol-mppi-fast") for c in cs]}
                for m, cs in costs.items()} for s in ("900", "901")}
    return {"runs": runs, "plant": {"name": "level 3"}, "sequence": "stationary",
            "command": "peel experiment ..."}


def test_summary_fractions_ratio_and_times() -> None:
    s = summarize(results(), [1, 2, 3, 5])
    assert s["tasks"] == 3 and set(s["closed"]["ol-mppi-fast"]) == {"1", "2", "3"}
    assert s["closed"]["ol-mppi-fast"]["1"]["pooled"] == pytest.approx(0.5)
    assert s["closed"]["ol-mppi-fast"]["2"]["mean"] == pytest.approx(1.0)
    assert s["closed"]["ol-mppi"]["1"]["pooled"] == pytest.approx(0.0)
    assert s["closed"]["ol-mppi"]["2"]["pooled"] == pytest.approx(0.75)
    assert s["closed"]["baseline2"]["3"]["pooled"] == pytest.approx(0.25)
    assert s["within_task1"]["ratio_of_means"] == pytest.approx(0.5)
    t = s["timing"]
    assert (t["fast_steps"], t["fast_accepted"]) == (4 * 3 * 2, 2 * 3 * 2)
    assert t["fast_s_max"] == pytest.approx(0.4) and t["fast_s_median"] == pytest.approx(0.25)


def test_cli_writes_the_report_and_refuses_a_missing_arm(tmp_path: Path) -> None:
    good = tmp_path / "results.json"
    good.write_text(json.dumps(results()))
    out = tmp_path / "report"
    proc = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "fast-report", str(good),
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    printed = json.loads(proc.stdout)
    assert printed == json.loads((out / "fast_report.json").read_text())
    assert (out / "fast_task1_error.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| ol-mppi-fast |" in (out / "fast_report.md").read_text()
    other = results()
    other["runs"] = {"902": other["runs"]["900"]}
    (tmp_path / "other.json").write_text(json.dumps(other))
    proc = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "fast-report", str(good),
                           str(tmp_path / "other.json"), "--out", str(tmp_path / "both")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["seeds"] == ["900", "901", "902"]
    proc = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "fast-report", str(good),
                           str(good), "--out", str(tmp_path / "twice")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "seed 900 is in two" in proc.stderr, proc.stderr
    bad = results()
    for s in bad["runs"].values():
        del s["baseline2"]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    proc = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "fast-report",
                           str(tmp_path / "bad.json"), "--out", str(tmp_path / "r2")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "baseline2" in proc.stderr


def test_against_the_baselines_task_by_task() -> None:
    """Three seeds, 15 tasks, Baseline 1 at 20 and Baseline 2 at 15: the fast arm 1-2-3 above
    Baseline 2 at task 1 (the interval above 0), 2 below it from task 2 on; ol-mppi at 30 on
    one seed's task 4 (one peel over Baseline 1, not beyond noise over seeds) and 25 at task 5
    on every seed (beyond noise)."""
    n = 15
    runs = {}
    for i, s in enumerate(("910", "911", "912")):
        fast = [16.0 + i] + [13.0] * (n - 1)
        ol = [15.0] * n
        ol[4] = 25.0
        if i == 0:
            ol[3] = 30.0
        costs = {"baseline1": [20.0] * n, "oracle": [12.0] * n, "baseline2": [15.0] * n,
                 "ol-mppi-fast": fast, "ol-mppi": ol}
        runs[s] = {m: {"tasks": [_task(c, m == "ol-mppi-fast") for c in cs]} for m, cs in costs.items()}
    a = summarize({"runs": runs, "plant": {"name": "level 3"}, "sequence": "batch-switch"},
                  [1, 2])["against_baselines"]
    fast, ol = a["ol-mppi-fast"], a["ol-mppi"]
    assert fast["minus_b2"][0]["mean"] == pytest.approx(2.0)
    assert fast["tasks_b2_upper_end_above_0"] == [1] and fast["tasks_above_b1_beyond_noise"] == []
    assert fast["minus_b2_tasks_11_15"]["mean"] == pytest.approx(-2.0)
    assert ol["tasks_b2_upper_end_above_0"] == [4, 5] and ol["tasks_above_b1_beyond_noise"] == [5]
    assert ol["max_above_b1"] == {"seed": "910", "task": 4, "j_minus_b1": 10.0, "relative": 0.5}
