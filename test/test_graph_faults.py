"""Faults of the learner and outside model swaps in the running graph (docs/graph.md, "Failure
handling" and "The model swap").

* a learner whose starting checkpoint predicts non-finite forces refuses to start: one line,
  exit 2, and ``peel graph`` stops at once with exit 2 (it does not sit out its waits);
* a failed update (Algorithm 1 producing a model with non-finite outputs) is reported at once
  by the learner, the launcher prints it and exits 3, the planner keeps its model and the next
  task starts without waiting out ``node.wait_model_s``;
* a model swapped in from outside the learner (an unversioned file name) takes the next version;
  the learner's update after it takes the one after, and the simulator waits for the learner's
  update by its identity, so the outside model does not end its wait.

Each run sets the waits (``node.wait_model_s``, ``graph.final_model_wait_s``) far longer than
the test's own timeout, so a graph that waited them out fails the test.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import torch
from graph_helpers import Lines, assert_clean_logs, node_env
from test_graph_run import graph_cmd, read_bag

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

LONG_WAIT_S = 900.0  # longer than any timeout below


def _long_waits(tmp: Path, **maml: float) -> None:
    """Rewrite ``override.yaml`` (written by ``graph_cmd``) with long waits and ``maml.*``."""
    path = tmp / "override.yaml"
    text = path.read_text().replace("final_model_wait_s: 120.0",
                                    f"final_model_wait_s: {LONG_WAIT_S}")
    extra = "".join(f"      {k}: {v:.1e}\n" for k, v in maml.items())  # 1.0e+30: a YAML float
    path.write_text(text.replace("      m: 2\n", "      m: 2\n" + extra))


def _cmd(tmp: Path, *extra: str, tasks: int, meta_steps: int = 1, **maml: float) -> list[str]:
    cmd = graph_cmd(tmp, *extra, tasks=tasks, wait_model_s=LONG_WAIT_S, meta_steps=meta_steps)
    _long_waits(tmp, **maml)
    return cmd


def _huge_model(tmp: Path) -> Path:
    """The initial model's weights x 1e30, saved: finite weights, non-finite forces."""
    from peel_model.checkpoint import load_checkpoint, save_checkpoint

    pred = load_checkpoint(tmp / "init.safetensors")
    with torch.no_grad():
        for p in pred.parameters():
            p.mul_(1e30)
    return save_checkpoint(tmp / "huge.safetensors", pred)


def test_learner_refuses_a_starting_model_with_non_finite_outputs(tmp_path: Path,
                                                                  ros_domain: str) -> None:
    cmd = _cmd(tmp_path, tasks=1)
    huge = _huge_model(tmp_path)
    override = tmp_path / "override.yaml"
    learner = f"      init_model: {tmp_path / 'init.safetensors'}\n"
    assert learner in override.read_text()
    override.write_text(override.read_text().replace(learner, f"      init_model: {huge}\n"))
    res = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stdout + res.stderr
    assert "model_learner_node" in res.stderr and "exit status 2" in res.stderr
    log = (tmp_path / "run" / "logs" / "model_learner_node.log").read_text()
    last = log.strip().splitlines()[-1]
    assert last.startswith("model_learner_node: error: parameter 'node.init_model': "), log
    assert "non-finite" in last and "huge.safetensors" in last, last
    assert_clean_logs(tmp_path / "run")


def test_failed_update_is_reported_and_the_tasks_go_on(tmp_path: Path, ros_domain: str) -> None:
    """maml.beta = 1e30: every update leaves a model with non-finite outputs."""
    cmd = _cmd(tmp_path, tasks=2, beta=1e30)
    res = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=400)
    out = res.stdout + res.stderr
    assert res.returncode == 3, out  # the exit status says that an update failed
    for k in (1, 2):
        assert f"update {k}/2: failed" in res.stdout, out
    run = tmp_path / "run"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["failed_updates"] == [1, 2] and summary["status"] == 3
    assert [r["update"]["status"] for r in summary["results"]] == ["failed", "failed"]
    assert "non-finite" in summary["results"][0]["update"]["reason"]
    # the planner kept its model; no model with non-finite outputs was offered or written
    assert summary["model_versions"] == [0]
    assert [r["model_version"] for r in summary["results"]] == [0, 0]
    assert not list((run / "models").glob("model_v*.safetensors"))
    learner = (run / "logs" / "model_learner_node.log").read_text()
    assert "update after task 1 failed" in learner and "non-finite" in learner
    sim = (run / "logs" / "peel_sim_node.log").read_text()
    assert "update after task 1 failed" in sim  # reported at once, and the sequence went on
    assert "did not arrive" not in sim
    assert_clean_logs(run)


def test_outside_swap_gets_the_next_version_and_does_not_end_the_wait(
        tmp_path: Path, ros_domain: str) -> None:
    """Versions 0 (start), 1 (outside, unversioned name, swapped in when task 1 has ended and
    the learner is still at its update), 2 and 3 (the learner's updates after tasks 1 and 2);
    task 2 runs with version 2."""
    import rclpy
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from rclpy.node import Node

    from peel_model.checkpoint import save_checkpoint
    from peel_model.config import ModelConfig
    from peel_model.predictor import ForcePredictor

    bag = tmp_path / "bag"
    # a slow learner (many meta steps) leaves seconds between task 1's end and its update
    cmd = _cmd(tmp_path, "--record", str(bag), tasks=2, meta_steps=150)
    torch.manual_seed(1)
    outside = save_checkpoint(tmp_path / "tuned_by_hand.safetensors",
                              ForcePredictor(ModelConfig()))
    rclpy.init(args=None)
    node = Node("outside_swapper")
    client = node.create_client(SetParameters, "/peel_planner_node/set_parameters")
    proc = subprocess.Popen(cmd, env=node_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        lines = Lines(proc)
        lines.wait_for(r"task 1/2: ", 300)  # the learner has just received task 1
        assert client.wait_for_service(timeout_sec=60), lines.lines
        assert not any(line.startswith("update 1/2") for line in lines.lines), lines.lines
        req = SetParameters.Request(parameters=[Parameter(name="model.path", value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=str(outside)))])
        fut = client.call_async(req)
        rclpy.spin_until_future_complete(node, fut, timeout_sec=60)
        assert fut.result() is not None and fut.result().results[0].successful, fut.result()
        rc = proc.wait(timeout=400)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        if proc.poll() is None:
            proc.kill()
    out = lines.join()
    assert rc == 0, out
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["model_versions"] == [0, 1, 2, 3], out
    # task 1 started with the starting model; the simulator waited for the learner's update
    # after task 1 (version 2), not for "any version above 0" (the outside model, version 1)
    assert [r["model_version"] for r in summary["results"]] == [0, 2], out
    assert [r["update"]["status"] for r in summary["results"]] == ["swapped", "swapped"]
    msgs = read_bag(bag)
    versions = [int(m.data) for _, m in msgs["/peel/model_version"]]
    assert versions == [0, 1, 2, 3]
    infos = [json.loads(m.data) for _, m in msgs["/peel/model_info"]]
    assert [i["version"] for i in infos] == versions
    assert [(i["producer"], i["task"]) for i in infos] == [
        (None, None), (None, None), ("/model_learner_node", 1), ("/model_learner_node", 2)]
    assert Path(infos[1]["path"]).name == "tuned_by_hand.safetensors"
    assert len({i["sha256"] for i in infos}) == 4
    assert_clean_logs(tmp_path / "run")
