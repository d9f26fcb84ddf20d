"""The learner dies and comes back (docs/fleet.md): ``peel graph --keep-going`` with its learner
killed after its first swap, and a second learner started by hand with the same parameters. The
second one goes on from the first one's state (weights, replay pool, meta-optimiser:
model_learner_node.resume), gets the task it missed from the bridge's transient-local history
of ``/peel/trajectory``, drops the one it had learned, and every later task plans with the update
of the task before it: no peel is lost to learning and no model goes back.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from graph_helpers import Lines, node_env
from test_graph_run import graph_cmd, read_bag

from peel_model.checkpoint import read_checkpoint_config

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

ROOT = Path(__file__).resolve().parents[1]


def _learner_cmd(tmp: Path) -> list[str]:
    """The learner as the launcher starts it (its parameter files and settings), one meta step
    per update."""
    return [sys.executable, "-m", "model_learner_node.node", "--ros-args",
            "--params-file", str(ROOT / "config" / "model_learner_node.yaml"),
            "--params-file", str(tmp / "override.yaml"), "-p", "use_sim_time:=true",
            "-p", f"node.out_dir:={(tmp / 'run' / 'models').resolve()}",
            "-p", "maml.meta_steps:=1"]


def test_a_restarted_learner_goes_on_from_its_state_and_learns_the_missed_task(
        tmp_path: Path, ros_domain: str) -> None:
    bag = tmp_path / "bag"
    # the first learner is slow (many meta steps), so that the kill lands seconds before it
    # could write its second update; the bridge waits for every update as long as a hang
    proc = subprocess.Popen(graph_cmd(tmp_path, "--record", str(bag), "--keep-going",
                                      wait_model_s=300.0, meta_steps=150),
                            env=node_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    log = (tmp_path / "second_learner.log").open("w")
    second = None
    try:
        out = Lines(proc)
        pid = int(out.wait_for(r"started model_learner_node \(pid (\d+)\)", 60).group(1))
        out.wait_for(r"planner model v1 active", 300)  # the first update is in; its state too
        os.kill(pid, signal.SIGKILL)
        second = subprocess.Popen(_learner_cmd(tmp_path), env=node_env(), stdout=log,
                                  stderr=subprocess.STDOUT, text=True)
        rc = proc.wait(timeout=400)
    finally:
        if proc.poll() is None:
            proc.kill()
        if second is not None:
            second.send_signal(signal.SIGINT)
            second.wait(timeout=60)
        log.close()
    stdout, stderr = out.join(), proc.stderr.read() if proc.stderr else ""
    text = (tmp_path / "second_learner.log").read_text()
    assert rc == 1 and "model_learner_node" in stderr, stdout + stderr  # the death is named
    assert "resumed from learner_state.safetensors (1 tasks seen, 1 in the replay pool, " \
           "weights model_v0001.safetensors)" in text, text
    assert "task 1: learned before the restart; dropped" in text, text  # from the history

    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["dead_nodes"] == ["model_learner_node"]
    # every task after the first planned with the update of the task before it: task 2 with
    # the first learner's, task 3 with the second learner's update on task 2 (which it got
    # from the bridge's history or live, whichever came first)
    assert [r["model_version"] for r in summary["results"]] == [0, 1, 2], summary["results"]
    models = tmp_path / "run" / "models"
    meta = read_checkpoint_config(models / "model_v0002.safetensors")["meta"]
    assert (meta["producer"], meta["task"]) == ("/model_learner_node", 2)
    infos = [json.loads(m.data) for _, m in read_bag(bag)["/peel/model_info"]]
    swapped = {rec["version"]: rec["sha256"] for rec in infos}
    assert swapped[2] == read_checkpoint_config(models / "model_v0002.safetensors")[
        "safetensors_sha256"]
    assert sorted(swapped) == list(range(len(swapped)))  # versions only go up, none twice
