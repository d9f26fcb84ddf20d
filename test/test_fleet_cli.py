"""``peel fleet`` and ``peel fleet-report`` without ROS (docs/fleet.md): what each cell is given
(its namespace, its own task-sequence seed, the producer name its bridge waits for, the
learner's ``node.cells``), and bad input refused in one line, exit 2, before anything starts."""

from __future__ import annotations

import json
import subprocess
import sys
import types
from pathlib import Path

import pytest

from peel_bringup import fleet, fleet_report
from peel_msgs_py.errors import PeelError

PEEL = [sys.executable, "-m", "peel_bringup.cli"]


def _args(tmp: Path, **kw: object) -> types.SimpleNamespace:
    base = dict(params=None, cells=3, tasks=2, plant=None, seed=5, record=None, join_after=None,
                out=str(tmp / "run"), force=False, verbose=False)
    return types.SimpleNamespace(**{**base, **kw})


def test_each_cell_has_its_namespace_seed_and_producer_and_the_learner_serves_all(
        tmp_path: Path) -> None:
    run = fleet.resolve(_args(tmp_path))
    sets = run.settings()
    assert run.cells == ["/cell_0", "/cell_1", "/cell_2"]
    seeds = [sets[c]["peel_sim_node"]["node.seed"] for c in run.cells]
    assert seeds[0] == 5 and len(set(seeds)) == 3  # cell 0 is peel graph --seed 5's sequence
    assert seeds == [sets[c]["peel_planner_node"]["node.seed"] for c in run.cells]
    assert fleet.resolve(_args(tmp_path, seed=6)).settings()["/cell_1"]["peel_sim_node"][
        "node.seed"] != seeds[1]
    for c in run.cells:
        assert sets[c]["peel_sim_node"]["node.learner_node"] == f"/model_learner_node@{c}"
    assert sets[""]["model_learner_node"]["node.cells"] == run.cells
    _, cells = fleet.children_of(run)
    for c, kids in cells.items():
        assert [k.cmd[-2:] for k in kids] == [["-r", f"__ns:={c}"]] * 2


@pytest.mark.parametrize(("argv", "word"), [
    (["fleet", "--cells", "0"], "--cells"),
    (["fleet", "--cells", "1", "--join-after", "1"], "--join-after"),
    (["fleet", "--plant", "nachi"], "--plant"),
    (["fleet-report", "/nonexistent/run"], "summary.json"),
])
def test_bad_input_is_one_line_and_exit_2(argv: list[str], word: str, tmp_path: Path) -> None:
    proc = subprocess.run([*PEEL, *argv], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and word in proc.stderr, proc.stderr


def test_the_report_reads_task_and_wait_times_from_the_logs(tmp_path: Path) -> None:
    run = tmp_path / "run"
    logs = run / "logs" / "cell_0"
    logs.mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps({
        "cells": {"/cell_0": {}}, "tasks": 2, "seed": 0, "status": 0,
        "learner_update_s": [3.0, 5.0]}))
    (logs / "peel_planner_node.log").write_text(
        "[INFO] [100.0] [cell_0.peel_planner_node]: task 1 starts at ROS time 0.0 s\n"
        "[INFO] [112.0] [cell_0.peel_planner_node]: task 2 starts at ROS time 40.0 s\n")
    (logs / "peel_sim_node.log").write_text(
        "[INFO] [104.0] [cell_0.peel_sim_node]: task 1: done, T_cpl=5.0 s, model v0\n"
        "[INFO] [118.0] [cell_0.peel_sim_node]: task 2: safety_stop, T_cpl=3.0 s, model v1\n")
    got = fleet_report.run_report(run)
    assert got["per_cell"]["/cell_0"] == {"task_wall_s": [4.0, 6.0], "between_tasks_s": [8.0]}
    assert (got["first_start_to_last_end_s"], got["wall_s_per_peel"]) == (18.0, 9.0)
    assert got["learner_update_s_median"] == 4.0
    with pytest.raises(PeelError, match="summary"):
        fleet_report.run_report(tmp_path / "none")
