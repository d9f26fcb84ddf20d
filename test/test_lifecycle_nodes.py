"""The planner and both plant bridges as managed nodes (docs/graph.md "Lifecycle"), each a real
process started unconfigured (``node.autostart:=false``) on the test's ROS domain, driven by an
outside rclpy node (lifecycle_rig.Outside) only through the standard ``change_state`` /
``get_state`` services:

* every transition and the state it leads to; an inactive planner publishes no command and an
  inactive bridge executes or forwards none (counted while inactive; then activated, they flow);
* deactivating the Nachi bridge during a task sends STOP (the controller emulator sees it) and
  the task ends ``aborted`` (``deactivated``);
* a configure that fails (a model file that does not exist, no controller listening) leaves the
  node unconfigured with one line naming why, and a later configure can succeed.

Waits are for events (a sample re-sent, a status published), bounded by timeouts only a hang
reaches.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from graph_helpers import node_env
from lifecycle_rig import Outside, wait
from nachi_rig import bridge_cmd
from std_msgs.msg import Header

from peel_msgs_py import topics
from peel_msgs_py.codec import trajectory_from_msg
from peel_msgs_py.diagnostics import ERROR
from peel_nachi_emulator.emulator import ControllerEmulator, EmulatorOptions
from peel_nachi_emulator.robot import Robot
from peel_sim_node.config import load_sim_config

pytestmark = pytest.mark.process  # starts processes: scripts/flaky.sh

ROOT = Path(__file__).resolve().parents[1]
SLOT_S = 100.0
T = 120.0  # s: only a hang reaches it
#: Readers and waits that let a bridge start at once (the test stands in for the planner).
EAGER = {"node.autostart": False, "node.wait_planner_s": 0.0, "node.min_subscribers": 0,
         "node.min_traj_subscribers": 0, "node.wait_model_s": 0.0, "node.task_slot_s": SLOT_S}


def _p(**values: object) -> list[str]:
    out = []
    for key, value in values.items():
        out += ["-p", f"{key}:={str(value).lower() if isinstance(value, bool) else value}"]
    return out


def _node(name: str, log: Path, **values: object) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", f"{name}.node", "--ros-args", "--params-file",
           str(ROOT / "config" / f"{name}.yaml"), *_p(**values)]
    with open(log, "wb") as out:
        return subprocess.Popen(cmd, env=node_env(), stdout=out, stderr=subprocess.STDOUT)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        proc.wait(30)


@pytest.fixture
def procs() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for proc in started:
        _stop(proc)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _inactive_status_twice(out: Outside, node: str) -> None:
    """Wait for two more ``inactive`` statuses of ``node`` on /diagnostics (1 Hz): its executor
    has run its callbacks of the moment before them (a command sent then included)."""
    name = f"{node}: lifecycle"
    seen = len(out.statuses(name))
    wait(lambda: sum(1 for _, m in out.statuses(name)[seen:] if m == "inactive") >= 2, T,
         f"two 'inactive' statuses of {node}")


def test_planner_and_sim_bridge_every_transition_and_nothing_while_inactive(
        tmp_path: Path, ros_domain: str, procs: list) -> None:
    procs += [_node("peel_planner_node", tmp_path / "planner.log", use_sim_time=True,
                    **{"node.autostart": False, "node.min_cmd_subscribers": 0}),
              _node("peel_sim_node", tmp_path / "sim.log", use_sim_time=True, **EAGER,
                    **{"node.tasks": 2, "node.cmd_timeout_s": 0.3, "node.seed": 3})]
    out = Outside(ros_domain, SLOT_S)
    try:
        for node in ("peel_planner_node", "peel_sim_node"):
            assert out.state(node) == "unconfigured"
            assert out.change(node, "activate") is False  # not from unconfigured
            assert out.change(node, "configure") is True
            assert out.state(node) == "inactive"
        wait(lambda: out.publishers(topics.CMD_VEL) >= 2, T, "the planner's command publisher")
        _inactive_status_twice(out, "peel_sim_node")
        assert out.count("wrenches") == 0  # configured, inactive: no task started

        # the bridge runs its first task; the inactive planner answers none of its samples
        assert out.change("peel_sim_node", "activate") is True
        wait(lambda: out.resent() >= 3, T, "the first sample re-sent twice")
        assert out.count("commands") == 0 and len({w for w in out.wrenches}) == 1

        assert out.change("peel_planner_node", "activate") is True
        assert out.state("peel_planner_node") == "active"
        wait(lambda: out.count("commands") >= 3 and len(set(out.wrenches)) >= 10, T,
             "commands answering the samples")

        # deactivated, the planner stops: the bridge re-sends its sample, nothing answers it
        assert out.change("peel_planner_node", "deactivate") is True
        wait(lambda: out.resent() >= 3, T, "the waiting sample re-sent")
        answered = out.count("commands")
        wait(lambda: out.resent() >= 6, T, "the waiting sample re-sent three more times")
        assert out.count("commands") == answered

        # deactivated, the bridge ends the task (aborted) and executes no command
        assert out.change("peel_sim_node", "deactivate") is True
        wait(lambda: out.count("trajectories") == 1, T, "the aborted task's trajectory")
        assert trajectory_from_msg(out.trajectories[0]).outcome == "aborted"
        samples = out.count("wrenches")
        stamp, frame = out.wrenches[-1]
        header = Header(frame_id=frame)
        header.stamp.sec, header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        out.command(header, 2.0)
        _inactive_status_twice(out, "peel_sim_node")
        assert out.count("wrenches") == samples

        # active again: the next task starts
        assert out.change("peel_sim_node", "activate") is True
        wait(lambda: out.wrenches[-1][1] == "peel_task_1", T, "task 2's first sample")

        for node in ("peel_sim_node", "peel_planner_node"):
            if out.state(node) == "active":
                assert out.change(node, "deactivate") is True
            assert out.change(node, "cleanup") is True
            assert out.state(node) == "unconfigured"
        wait(lambda: out.publishers(topics.WRENCH) == 0 and out.publishers(topics.CMD_VEL) == 1,
             T, "the cleaned-up nodes' publishers gone")
        for node, proc in zip(("peel_planner_node", "peel_sim_node"), procs, strict=True):
            assert out.change(node, "shutdown") is True
            assert proc.wait(T) == 0, (tmp_path / "planner.log").read_text()[-2000:]
    finally:
        out.close()
    for log in ("planner.log", "sim.log"):
        assert "Traceback" not in (tmp_path / log).read_text()


def _emulator(port: int = 0) -> ControllerEmulator:
    cfg = load_sim_config({"task.q_ter_mm": 20.0})
    opts = EmulatorOptions(port=port, speed=1.0, seed=3, source="sim")
    return ControllerEmulator(opts, robot=Robot(source="sim", seed=3, cfg=cfg),
                              log=lambda text: None).start()


def _bridge(port: int, log: Path, **values: object) -> subprocess.Popen[bytes]:
    with open(log, "wb") as out:
        return subprocess.Popen(bridge_cmd(port, **EAGER, **values), env=node_env(), stdout=out,
                                stderr=subprocess.STDOUT)


def test_nachi_bridge_connects_on_configure_forwards_only_while_active_and_stops_on_deactivate(
        tmp_path: Path, ros_domain: str, procs: list) -> None:
    emu = _emulator()
    out = Outside(ros_domain, SLOT_S, answer=3.0, announce=True)
    try:
        procs.append(_bridge(emu.port, tmp_path / "bridge.log", **{"node.tasks": 2}))
        node = "peel_nachi_bridge"
        assert out.state(node) == "unconfigured" and not emu.of_kind("connect")
        assert out.change(node, "configure") is True
        assert out.state(node) == "inactive" and len(emu.of_kind("connect")) == 1

        # inactive: a command for task 1 is not forwarded, no task starts
        out.command(Header(frame_id="peel_task_0"), 2.0)
        _inactive_status_twice(out, node)
        assert not emu.of_kind("v") and not emu.of_kind("start") and out.count("wrenches") == 0

        assert out.change(node, "activate") is True
        wait(lambda: len(emu.of_kind("v")) >= 3, T, "commands forwarded as V")

        assert out.change(node, "deactivate") is True
        wait(lambda: out.count("trajectories") == 1, T, "the stopped task's trajectory")
        assert len(emu.of_kind("stop")) == 1
        traj = trajectory_from_msg(out.trajectories[0])
        assert (traj.outcome, traj.meta["end_reason"]) == ("aborted", "deactivated")
        forwarded = len(emu.of_kind("v"))
        out.command(Header(frame_id="peel_task_1"), 2.0)
        _inactive_status_twice(out, node)
        assert len(emu.of_kind("v")) == forwarded and len(emu.of_kind("start")) == 1

        assert out.change(node, "cleanup") is True
        assert out.state(node) == "unconfigured"
        wait(lambda: len(emu.of_kind("disconnect")) == 1, T, "the link closed by cleanup")
        assert out.change(node, "shutdown") is True
        assert procs[0].wait(T) == 0
    finally:
        out.close()
        emu.close()
    assert "Traceback" not in (tmp_path / "bridge.log").read_text()


def test_a_failed_configure_leaves_the_node_unconfigured_naming_why(
        tmp_path: Path, ros_domain: str, procs: list) -> None:
    missing = tmp_path / "missing.safetensors"
    port = _free_port()
    procs += [_node("peel_planner_node", tmp_path / "planner.log",
                    **{"node.autostart": False, "model.path": str(missing)}),
              _bridge(port, tmp_path / "bridge.log", **{"link.configure_timeout_s": 0.5,
                                                        "link.backoff_max_s": 0.2})]
    out = Outside(ros_domain, SLOT_S)
    emu = None
    try:
        for node in ("peel_planner_node", "peel_nachi_bridge"):
            assert out.change(node, "configure") is False
            assert out.state(node) == "unconfigured"
        planner_log = (tmp_path / "planner.log").read_text()
        (line,) = [ln for ln in planner_log.splitlines() if "configure failed" in ln]
        assert "parameter 'model.path'" in line and "missing" in line
        wait(lambda: any(lvl == ERROR and "configure failed" in m
                         for lvl, m in out.statuses("peel_planner_node: lifecycle")), T,
             "the planner's ERROR status")
        bridge_log = (tmp_path / "bridge.log").read_text()
        (line,) = [ln for ln in bridge_log.splitlines() if "configure failed" in ln]
        assert f"giving up: no controller at 127.0.0.1:{port}" in line

        emu = _emulator(port)  # the controller is there now: configure succeeds (peel lifecycle)
        res = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "lifecycle", "set",
                              "configure", "peel_nachi_bridge"], env=node_env(),
                             capture_output=True, text=True, timeout=T)
        assert res.returncode == 0, res.stdout + res.stderr
        assert json.loads(res.stdout) == {
            "action": "set", "error": None, "nodes": {"/peel_nachi_bridge": "inactive"},
            "steps": [{"node": "peel_nachi_bridge", "transition": "configure", "success": True}]}
        assert out.state("peel_nachi_bridge") == "inactive"
        # shut down after its failed configure, the planner exits with that error (exit 2)
        assert out.change("peel_planner_node", "shutdown") is True
        assert procs[0].wait(T) == 2
        last = (tmp_path / "planner.log").read_text().strip().splitlines()[-1]
        assert last.startswith("peel_planner_node: error: parameter 'model.path'"), last
    finally:
        out.close()
        if emu is not None:
            emu.close()
