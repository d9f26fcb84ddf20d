"""``peel graph --plant nachi``: the whole graph against ``peel nachi-emulator`` as real processes
(the emulator, the launcher, the Nachi bridge, the planner, the learner and the recorder, all on
rclpy, on the test's own ROS domain from the ``ros_domain`` fixture), with the bag read back by
``rosbags`` (:mod:`peel_bag.bagread`) and by mcap's own ROS 2 decoder; the launcher's exit
codes when the bridge gives up (1) and for bad bridge parameters (2, before anything starts).
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from graph_helpers import ALONE, FAST, node_env, override_yaml, read_bag_mcap_ros2

from peel_bag import bagread
from peel_msgs_py import topics
from peel_planner_node.guard import GuardStats

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

# six processes on two cores; the 300 ms rule has its own tests
BRIDGE = {"peel_nachi_bridge": {"safety": {"stall_timeout_s": 1.0}}}
OVERRIDE = override_yaml(ALONE, FAST, BRIDGE)


def _graph(tmp: Path, *args: str, override: str = OVERRIDE) -> list[str]:
    path = tmp / "override.yaml"
    path.write_text(override)
    return [sys.executable, "-m", "peel_bringup.cli", "graph", "--plant", "nachi",
            "--params", str(path), "--out", str(tmp / "run"), *args]


def _logs(run_dir: Path) -> dict[str, str]:
    return {p.stem: p.read_text(errors="replace") for p in sorted((run_dir / "logs").glob("*.log"))}


def test_graph_runs_against_the_emulator(tmp_path: Path, ros_domain: str) -> None:
    """Two full plant tasks through the graph: the learner's update plans task 2, the bag holds
    every topic, stamps from controller time, and every log is free of tracebacks. The emulator
    runs at half real time (its 1 s watchdog is 2 s of wall time: the planner's first plan
    warms torch up, which took over 1 s on this loaded machine)."""
    emu = subprocess.Popen([sys.executable, "-m", "peel_bringup.cli", "nachi-emulator", "--port",
                            "0", "--plant", "plant", "--seed", "4", "--speed", "0.5"], env=node_env(),
                           stdout=subprocess.PIPE, text=True)
    try:
        first = emu.stdout.readline()  # type: ignore[union-attr]
        port = first.split(":")[1].split()[0]
        cmd = _graph(tmp_path, "--nachi-host", "127.0.0.1", "--nachi-port", port, "--tasks", "2",
                     "--seed", "4", "--record", str(tmp_path / "bag"))
        out = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=400)
    finally:
        emu.terminate()
        emu_log = emu.communicate(timeout=30)[0]
    logs = _logs(tmp_path / "run")
    bridge_log = logs.get("peel_nachi_bridge", "")
    assert out.returncode == 0, out.stdout + out.stderr + bridge_log[-2000:]
    assert "started peel_nachi_bridge" in out.stdout and "peel_sim_node" not in out.stdout
    assert "task 2/2:" in out.stdout
    assert "connected to controller EMU-MZ04" in bridge_log
    assert set(logs) == {"peel_nachi_bridge", "peel_planner_node", "model_learner_node",
                         "recorder"}
    for name, text in logs.items():
        assert "Traceback" not in text and "KeyboardInterrupt" not in text, (name, text[-2000:])
    assert "Traceback" not in emu_log

    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["plant"] == "nachi" and summary["status"] == 0
    assert [r["outcome"] for r in summary["results"]] == \
        [t.outcome for t in bagread.read_trajectories(tmp_path / "bag")]
    trajs = bagread.read_trajectories(tmp_path / "bag")
    assert len(trajs) == 2
    assert [t.meta["source"] for t in trajs] == ["nachi", "nachi"]
    assert [t.meta["controller_task_id"] for t in trajs] == [0, 1]
    assert all(t.outcome in ("done", "safety_stop") for t in trajs), \
        [(t.outcome, t.meta["end_detail"]) for t in trajs]
    assert trajs[0].meta["model_version"] == 0
    assert trajs[1].meta["model_version"] >= 1  # the learner's update planned task 2
    for traj in trajs:  # the real planner's guard report (/peel/planner_safety) in the meta
        guard = traj.meta["planner_guard"]
        assert set(guard) == set(GuardStats().as_dict()) and guard["plans"] >= 4, guard

    arrays = bagread.read_topics(tmp_path / "bag")
    assert set(arrays[topics.MODEL_VERSION]["version"]) >= {0, 1, 2}
    for k, traj in enumerate(trajs):  # every sample of a task once, stamped slot + controller t
        w = arrays[topics.WRENCH]
        mine = w["task"] == k
        assert sorted(w["t_s"][mine] - 100.0 * k) == pytest.approx(list(traj.t), abs=1e-6)
        cmds = arrays[topics.CMD_VEL]["u_mmps"][arrays[topics.CMD_VEL]["task"] == k]
        assert len(cmds) >= 4
    assert len(arrays[topics.CLOCK]["t_s"]) > 0
    counts = {topic: len(msgs) for topic, msgs in read_bag_mcap_ros2(tmp_path / "bag").items()}
    assert counts[topics.TRAJECTORY] == 2 and counts[topics.WRENCH] == len(arrays[topics.WRENCH]
                                                                            ["t_s"])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_graph_exits_1_naming_the_bridge_when_no_controller_answers(tmp_path: Path,
                                                                     ros_domain: str) -> None:
    """No controller at the port: the bridge's configure retries with backoff, gives up after
    ``link.configure_timeout_s``; the graph shuts it down, it exits 1, and the graph stops the
    others and exits 1 naming it."""
    override = override_yaml(ALONE, FAST, BRIDGE, {"peel_nachi_bridge": {"link": {
        "give_up_s": 1.0, "backoff_max_s": 0.3, "configure_timeout_s": 1.0}}})
    cmd = _graph(tmp_path, "--nachi-port", str(_free_port()), "--tasks", "1", override=override)
    out = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=300)
    assert out.returncode == 1, out.stdout + out.stderr
    assert "node peel_nachi_bridge" in out.stderr and "exit status 1" in out.stderr
    bridge_log = _logs(tmp_path / "run")["peel_nachi_bridge"]
    assert "giving up: no controller at 127.0.0.1:" in bridge_log and "retrying in" in bridge_log
    assert "Traceback" not in bridge_log
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["status"] == 1 and "peel_nachi_bridge" in summary["dead_nodes"]


@pytest.mark.parametrize(("args", "section", "message"), [
    (["--plant", "sim", "--nachi-port", "48100"], "",
     "--nachi-host / --nachi-port need --plant nachi"),
    (["--plant", "nachi", "--nachi-port", "0"], "", "parameter 'link.port' = 0 is below its "
                                                    "minimum 1"),
    (["--plant", "nachi", "--nachi-host", ""], "", "parameter 'link.host' = '' must be a "
                                                   "non-empty address"),
    (["--plant", "nachi"], "peel_nachi_bridge:\n  ros__parameters:\n    link:\n      hots: x\n",
     "unknown parameter 'link.hots' for peel_nachi_bridge"),
    (["--plant", "nachi"], "peel_nachi_bridge:\n  ros__parameters:\n    safety:\n"
                           "      f_prewarn_n: 20\n",
     "parameter 'safety.f_prewarn_n': wrong type, expected DOUBLE got INTEGER (20)"),
])
def test_bad_nachi_options_and_parameters_exit_2_before_anything_starts(
        tmp_path: Path, args: list[str], section: str, message: str) -> None:
    path = tmp_path / "override.yaml"
    path.write_text(section or "{}\n")
    cmd = [sys.executable, "-m", "peel_bringup.cli", "graph", "--params", str(path), "--out",
           str(tmp_path / "run"), *args]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stdout + out.stderr
    (line,) = out.stderr.strip().splitlines()
    assert line.startswith("peel graph: error: ") and message in line, line
    assert not (tmp_path / "run").exists()  # nothing started


def test_bench_nachi_graph_compares_both_bridges_on_one_seed(tmp_path: Path,
                                                             ros_domain: str) -> None:
    """``peel bench nachi-graph``: a simulator-bridge graph and a Nachi-bridge graph against the
    emulator, same seed and parameters, side by side as JSON (one task each here)."""
    params = tmp_path / "params.yaml"
    params.write_text(OVERRIDE)
    out = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "bench", "nachi-graph",
                          "--tasks", "1", "--seed", "5", "--speed", "0.5", "--params",
                          str(params), "--out", str(tmp_path / "cmp")],
                         env=node_env(), capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    result = json.loads(out.stdout)
    assert (result["benchmark"], result["seed"], result["tasks"]) == ("nachi-graph", 5, 1)
    for bridge, run in (("simulator_bridge", "sim"), ("nachi_bridge", "nachi")):
        (task,) = result[bridge]
        summary = json.loads((tmp_path / "cmp" / run / "summary.json").read_text())
        assert task["J"] == summary["results"][0]["J"] and task["model_version"] == 0
        assert task["outcome"] in ("done", "safety_stop", "timeout")
        assert result["mean_J"][bridge] == pytest.approx(task["J"], abs=1e-4)
        assert result["model_versions"][bridge][:2] == [0, 1]
    assert json.loads((tmp_path / "cmp" / "nachi" / "summary.json").read_text())["plant"] == \
        "nachi"
    assert len(result["load_average_1_5_15"]["before"]) == 3
