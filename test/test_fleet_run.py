"""``peel fleet`` (docs/fleet.md): cells under their own namespaces and one learner, as separate
processes on real rclpy.

* two cells and a learner: each cell finishes its tasks, both planners receive every update
  (each cell's planner announces every update, whichever cell's task it was learned from),
  an outside rclpy node finds each cell's topics under its namespace only, and each cell's
  bag holds that cell's topics under the one-cell names, the learner's reports naming it;
* one cell's planner killed mid-run: the other cell and the learner go on, the launcher
  names the dead cell and exits 1;
* a cell started after two updates plans its first task with the current model.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
import rclpy
from graph_helpers import SMALL_MAML, Lines, node_env, read_bag_mcap_ros2

from peel_msgs_py import topics

pytestmark = pytest.mark.process  # starts processes: scripts/flaky.sh

LEARNER = "/model_learner_node"
RUN_S = 400.0  # only a hang reaches it: a fleet run takes 20-60 s on the loaded 2-core machine


def _params(tmp: Path) -> Path:
    path = tmp / "small.yaml"
    path.write_text("model_learner_node:\n  ros__parameters:\n" + SMALL_MAML
                    + "    node:\n      cell_wait_s: 60.0\n")
    return path


def _fleet(tmp: Path, *extra: str) -> tuple[subprocess.Popen[str], Lines]:
    cmd = [sys.executable, "-m", "peel_bringup.fleet", "--params", str(_params(tmp)),
           "--out", str(tmp / "run"), *extra]
    proc = subprocess.Popen(cmd, env=node_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    return proc, Lines(proc)


def _summary(proc: subprocess.Popen[str], lines: Lines) -> tuple[int, dict[str, Any], str]:
    code = proc.wait(timeout=RUN_S)
    text = lines.join()
    last = [line for line in text.splitlines() if line.startswith("{")]
    assert last, text
    return code, json.loads(last[-1]), text


def _updates(summary: dict[str, Any]) -> set[tuple[str, int]]:
    """(producer, task) of every update swapped in at the cell it came from."""
    return {(f"{LEARNER}@{cell}", r["task"]) for cell, c in summary["cells"].items()
            for r in c["results"] if r["update"] and r["update"]["status"] == "swapped"}


class Lister:
    """An outside rclpy node that collects the topic names seen while the fleet runs."""

    def __init__(self) -> None:
        self.seen: set[str] = set()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        rclpy.init()
        node = rclpy.create_node("peel_test_lister")
        try:
            while not self.stop.wait(0.5):
                self.seen |= {t for t, _ in node.get_topic_names_and_types()}
        finally:
            node.destroy_node()
            rclpy.shutdown()

    def close(self) -> set[str]:
        self.stop.set()
        self.thread.join(timeout=30)
        return self.seen


def test_two_cells_finish_every_planner_gets_every_update_topics_under_namespaces(
        tmp_path: Path, ros_domain: str) -> None:
    lister = Lister()
    bag = tmp_path / "bag"
    proc, lines = _fleet(tmp_path, "--cells", "2", "--tasks", "2", "--record", str(bag))
    try:
        code, summary, text = _summary(proc, lines)
    finally:
        seen = lister.close()
    assert code == 0, text
    updates = _updates(summary)
    assert updates == {(f"{LEARNER}@/cell_{c}", k) for c in (0, 1) for k in (1, 2)}, text
    for cell, c in summary["cells"].items():
        assert [r["task"] for r in c["results"]] == [1, 2], (cell, text)
        assert {(m["producer"], m["task"]) for m in c["models"]} >= updates, (cell, c["models"])
        assert f"{cell} task 1/2:" in text and f"{cell} task 2/2:" in text
    assert summary["cells"]["/cell_0"]["seed"] != summary["cells"]["/cell_1"]["seed"]
    peel = {t for t in seen if "peel/" in t or t.endswith("/clock") or t == topics.CLOCK}
    expected = {topics.under(cell, n) for cell in ("/cell_0", "/cell_1") for n in topics.TOPICS}
    assert peel == expected, sorted(peel ^ expected)
    for cell in ("/cell_0", "/cell_1"):  # a bag per cell, in the one-cell layout
        recorded = read_bag_mcap_ros2(bag / cell.strip("/"))
        assert set(recorded) <= set(topics.TOPICS), sorted(recorded)
        assert len(recorded[topics.TRAJECTORY]) == 2 and recorded[topics.WRENCH], cell
        reports = [json.loads(m.data) for m in recorded[topics.MODEL_UPDATE]]
        assert {r["cell"] for r in reports} == {cell}, reports


def test_a_killed_cell_is_reported_and_the_other_cell_and_the_learner_go_on(
        tmp_path: Path, ros_domain: str) -> None:
    proc, lines = _fleet(tmp_path, "--cells", "2", "--tasks", "2")
    pid = int(lines.wait_for(r"started /cell_1/peel_planner_node \(pid (\d+)\)", RUN_S).group(1))
    lines.wait_for(r"^/cell_1 task 1/2:", RUN_S)
    os.kill(pid, signal.SIGKILL)
    code, summary, text = _summary(proc, lines)
    assert code == 1, text
    assert summary["dead"] == ["/cell_1"], text
    assert "cell /cell_1: node /cell_1/peel_planner_node" in text
    cell0 = summary["cells"]["/cell_0"]
    assert [r["task"] for r in cell0["results"]] == [1, 2], text
    assert cell0["results"][1]["update"]["status"] == "swapped", text  # the learner went on


def test_a_cell_that_joins_after_two_updates_starts_on_the_current_model(
        tmp_path: Path, ros_domain: str) -> None:
    proc, lines = _fleet(tmp_path, "--cells", "3", "--tasks", "1", "--join-after", "2")
    code, summary, text = _summary(proc, lines)
    assert code == 0, text
    late = summary["cells"]["/cell_2"]
    # the two early cells run at once, so either cell's update may be the learner's second:
    # the current model is the newer of the two at an early planner (its highest version)
    early = {f"{LEARNER}@/cell_0", f"{LEARNER}@/cell_1"}
    assert {m["producer"] for m in summary["cells"]["/cell_1"]["models"]} >= early, text
    current = max((m for m in summary["cells"]["/cell_1"]["models"] if m["producer"] in early),
                  key=lambda m: m["version"])
    first = late["results"][0]
    # the model the late cell's task 1 started with, by its bridge's record in the trajectory
    assert first["model_sha256"] == current["sha256"], (late, summary["cells"]["/cell_1"], text)
    assert first["model_version"] >= 1, (late, text)
    assert text.index("/cell_2 joins") < text.index("/cell_2 task 1/1:")
