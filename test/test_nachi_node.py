"""The bridge node as a real process on real rclpy, against the emulator, with a bag read back by
``rosbags``: a full run with the real planner and learner nodes on the other side, every fault
of the issue in one run (each with its recorded outcome), and the node's exits.

The test process holds the emulator (a thread) and a rig (rclpy: recorder to a bag written with
peel_bag.bag from ``serialize_message`` bytes, and, where no planner runs, a commander).
Every test runs on a ROS domain of its own (the ``ros_domain`` fixture of conftest.py); the
processes it starts inherit it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from graph_helpers import SMALL_MAML, node_env
from nachi_rig import SLOT_S, Rig, bridge_cmd

from peel_bag import bagread
from peel_msgs_py import topics
from peel_nachi_emulator.emulator import ControllerEmulator, EmulatorOptions
from peel_nachi_emulator.faults import parse_fault
from peel_nachi_emulator.robot import Robot
from peel_sim_node.config import load_sim_config

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

ROOT = Path(__file__).resolve().parents[1]

#: One fault per task (the emulator's task k = the node's task k), plus a first connection
#: that gets no HELLO.
SCENARIO = (
    "no-hello:conn=0",
    "drop:t=0.5,task=0",
    "garbage:t=0.2,n=2,task=1", "oversize:t=0.4,task=1", "nan:t=0.6,task=1", "inf:t=0.8,task=1",
    "spike:t=0.5,f=22,task=2",
    "stall:t=0.6,s=3,task=3",
    # task 4: the commander sends 25 mm/s once (the bridge clamps it to the controller's 20);
    # task 5: it falls silent (watchdog)
    "garbage:t=0.5,n=3,task=6",
)
EXPECTED = [
    ("aborted", "connection_lost"), ("done", "reached"), ("safety_stop", "prewarning"),
    ("aborted", "stalled"), ("done", "reached"), ("aborted", "alarm"), ("aborted", "bad_lines"),
]


def speed(task: int, t: float) -> float | None:
    if task == 4 and 0.4 < t < 0.6:
        return 25.0
    if task == 5 and t > 0.4:
        return None
    return 4.0


def emulator(faults: tuple[str, ...], speed_x: float, q_ter_mm: float | None,
             source: str = "sim") -> ControllerEmulator:
    cfg = load_sim_config({"task.q_ter_mm": q_ter_mm} if q_ter_mm else None)
    robot = Robot(source=source, seed=3, cfg=cfg)
    opts = EmulatorOptions(port=0, speed=speed_x, seed=3, source=source,
                           faults=tuple(parse_fault(f) for f in faults))
    return ControllerEmulator(opts, robot=robot, log=lambda text: None).start()


def test_every_fault_has_its_outcome_in_a_readable_bag(tmp_path: Path, ros_domain: str) -> None:
    emu = emulator(SCENARIO, 1.0, 6.0)
    rig = Rig(ros_domain, tmp_path / "bag", speed=speed)
    try:
        cmd = bridge_cmd(emu.port, **{
            "node.tasks": 7, "node.exit_when_done": True, "node.wait_model_s": 0.0,
            "node.wait_planner_s": 60.0, "link.hello_timeout_s": 1.0})
        out = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=300)
    finally:
        rig.close()
        emu.close()
    assert out.returncode == 0, out.stderr[-3000:]
    log = out.stderr
    assert "no HELLO" in log and "retrying in" in log  # connection 0
    assert "link lost" in log and "(reconnected)" in log  # task 0's drop
    assert "Traceback" not in log

    trajs = bagread.read_trajectories(tmp_path / "bag")
    assert [(t.outcome, t.meta["end_reason"]) for t in trajs] == EXPECTED
    assert [t.meta["task_index"] for t in trajs] == list(range(7))
    assert trajs[1].meta["bad_lines"] == {"oversize": 1, "malformed": 2, "non_finite": 2}
    spike = trajs[2]
    assert spike.fx[-1] == pytest.approx(22.0) and spike.t[-1] == pytest.approx(0.5)
    assert spike.meta["stop_delay_s"] > 0
    assert emu.of_kind("stop")[0].data["sample_t"] == pytest.approx(0.5)  # the same sample
    # 25 mm/s went out as 20 mm/s: the controller had nothing to refuse
    assert trajs[4].meta.get("refused_v", []) == [] and max(trajs[4].u) == 20.0
    assert all(t.meta["cmd_limits_mmps"] == [0.0, 20.0] for t in trajs)
    assert "clamped a /peel/cmd_vel message: twist.linear.x = 25 mm/s is outside 0-20 mm/s; " \
           "forwarding 20 mm/s" in log
    assert trajs[5].meta["alarm"] == "10 watchdog"
    assert trajs[6].meta["bad_lines"]["malformed"] == 3

    arrays = bagread.read_topics(tmp_path / "bag")
    w, pose, clock = arrays[topics.WRENCH], arrays[topics.POSE], arrays[topics.CLOCK]
    assert len(w["t_s"]) == sum(len(t) for t in trajs)  # each good sample once, no bad one
    assert np.all(np.isfinite(w["fx_n"])) and np.all(np.isfinite(w["fz_n"]))
    for k, traj in enumerate(trajs):
        mine = w["task"] == k
        np.testing.assert_allclose(w["t_s"][mine], k * SLOT_S + traj.t, atol=1e-6)
        np.testing.assert_allclose(pose["q_mm"][pose["task"] == k], traj.q, atol=1e-9)
    assert np.all(np.diff(clock["t_s"]) > 0)  # /clock from controller time, never back
    assert float(np.max(pose["q_mm"])) < 10.0  # mm after bagread: the wire held metres


OVERRIDE = "model_learner_node:\n  ros__parameters:\n" + SMALL_MAML


def _node(name: str, *args: str) -> list[str]:
    return [sys.executable, "-m", f"{name}.node", "--ros-args", "--params-file",
            str(ROOT / "config" / f"{name}.yaml"), *args]


def test_the_rig_waits_for_writers_of_other_nodes_not_its_own(tmp_path: Path,
                                                             ros_domain: str) -> None:
    """The rig's recorder also matches the rig's own /peel/cmd_vel writer; a wait for the
    planner's writer must not be satisfied by it (the bag would miss the planner's first
    commands)."""
    import rclpy
    from geometry_msgs.msg import TwistStamped
    from rclpy.node import Node

    rig = Rig(ros_domain, tmp_path / "bag", model_version=None)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_domain))
    try:
        with pytest.raises(AssertionError, match="1 publishers of /peel/cmd_vel not matched"):
            rig.wait_matched(topics.CMD_VEL, 1, timeout_s=2.0)  # only its own writer exists
        other = Node("peel_test_planner", context=ctx)
        other.create_publisher(TwistStamped, topics.CMD_VEL, topics.qos_profile(topics.CMD_VEL))
        rig.wait_matched(topics.CMD_VEL, 1)  # another participant's writer: matched
        other.destroy_node()
    finally:
        ctx.try_shutdown()
        rig.close()


@pytest.mark.slow
def test_full_tasks_with_the_planner_and_the_learner(tmp_path: Path, ros_domain: str) -> None:
    """The graph with the bridge in the simulator bridge's place: the real planner and learner
    nodes (their own processes on rclpy) plan and learn on the controller's data."""
    override = tmp_path / "override.yaml"
    override.write_text(OVERRIDE)
    env = node_env()
    # half real time (the controller's 1 s watchdog is 2 s of wall time: the planner's first
    # plan, torch warming up, took over 1 s under load) and a 1 s stall rule: five processes
    # share two cores here; the 300 ms rule and the watchdog have their own tests. The
    # controller ends each task at 10 mm: 2-3 s of controller time, five or more commands
    emu = emulator((), 0.5, 10.0, source="plant")
    rig = Rig(ros_domain, tmp_path / "bag", model_version=None)
    procs = [subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True) for cmd in (
        _node("peel_planner_node", "-p", "use_sim_time:=true", "-p", "node.seed:=3"),
        _node("model_learner_node", "--params-file", str(override), "-p", "use_sim_time:=true",
              "-p", f"node.out_dir:={tmp_path / 'models'}"))]
    try:
        rig.wait_matched(topics.CMD_VEL, 1)  # the planner's commands all reach the bag
        cmd = bridge_cmd(emu.port, **{
            "node.tasks": 2, "node.exit_when_done": True, "node.wait_model_s": 120.0,
            "node.wait_planner_s": 120.0, "node.min_subscribers": 2,
            "node.min_traj_subscribers": 2, "use_sim_time": True,
            "safety.stall_timeout_s": 1.0})
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    finally:
        for proc in procs:
            proc.terminate()
        logs = [proc.communicate(timeout=30)[1] for proc in procs]
        rig.close()
        emu.close()
    assert out.returncode == 0, out.stderr[-3000:] + "\n".join(x[-1500:] for x in logs)

    trajs = bagread.read_trajectories(tmp_path / "bag")
    assert len(trajs) == 2
    ends = [(t.outcome, t.meta["end_detail"]) for t in trajs]
    assert all(t.outcome in ("done", "safety_stop") for t in trajs), ends
    assert [t.meta["model_version"] for t in trajs] == [0, 1]  # the learner's v1 for task 2
    arrays = bagread.read_topics(tmp_path / "bag")
    assert set(arrays[topics.MODEL_VERSION]["version"]) >= {0, 1, 2}
    cmd_vel = arrays[topics.CMD_VEL]
    accepted = emu.of_kind("v")
    for k in (0, 1):
        planned = [round(u, 4) for u in cmd_vel["u_mmps"][cmd_vel["task"] == k]]
        sent = [round(e.data["u"], 4) for e in accepted if e.data["task"] == k]
        # the V lines the controller got are the planner's commands (m/s on the wire, mm/s on
        # the line), in order; the planner's last command (after DONE) is not forwarded
        assert len(sent) >= 4 and len(planned) >= 4
        body = planned[:-1]
        assert any(sent[i:i + len(body)] == body for i in range(len(sent))), (sent, planned)
    assert not emu.of_kind("refused_v") and not emu.of_kind("alarm")


def test_no_hello_ever_makes_the_node_exit_1(tmp_path: Path, ros_domain: str) -> None:
    emu = emulator(("no-hello",), 1.0, 6.0)
    try:
        cmd = bridge_cmd(emu.port, **{
            "node.wait_planner_s": 0.0, "node.min_subscribers": 0, "node.min_traj_subscribers": 0,
            "link.hello_timeout_s": 0.3, "link.give_up_s": 1.0, "link.backoff_max_s": 0.3})
        out = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=120)
    finally:
        emu.close()
    assert out.returncode == 1, out.stderr[-2000:]
    assert "giving up: no controller at 127.0.0.1:" in out.stderr and "no HELLO" in out.stderr
    assert len(emu.of_kind("connect")) >= 2


@pytest.mark.parametrize(("param", "value", "message"), [
    ("link.port", "0", "parameter 'link.port'"),
    ("link.backoff_max_s", "0.05", "parameter 'link.backoff_max_s' = 0.05 is below "
                                   "'link.backoff_initial_s' = 0.2"),
    ("safety.stall_timeout_s", "'fast'",
     "parameter 'safety.stall_timeout_s': wrong type, expected DOUBLE got STRING (fast)"),
    ("safety.f_prewarn_n", "20",
     "parameter 'safety.f_prewarn_n': wrong type, expected DOUBLE got INTEGER (20) "
     "(write a float, e.g. 1.0)"),
    ("link.hots", "'x'", "unknown parameter 'link.hots' for peel_nachi_bridge (-p link.hots)"),
])
def test_bad_parameters_are_refused_with_a_named_error(param: str, value: str, message: str,
                                                       ros_domain: str) -> None:
    cmd = bridge_cmd(1, **{param: value})
    out = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr[-2000:]
    (line,) = out.stderr.strip().splitlines()
    assert line.startswith("peel_nachi_bridge: error: ") and message in line, line


def test_a_parameter_file_with_an_unknown_name_or_section_is_refused(tmp_path: Path,
                                                                     ros_domain: str) -> None:
    """The bridge's section is registered (``peel.parameters``): its names are checked, and a
    misspelled node section is refused too."""
    cases = {
        "peel_nachi_bridge:\n  ros__parameters:\n    link:\n      hots: x\n":
            "unknown parameter 'link.hots' for peel_nachi_bridge",
        "peel_nachi_bridg:\n  ros__parameters:\n    link:\n      host: x\n":
            "unknown node section 'peel_nachi_bridg'",
    }
    for body, message in cases.items():
        path = tmp_path / "bad.yaml"
        path.write_text(body)
        cmd = [*bridge_cmd(1), "--params-file", str(path)]
        out = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=60)
        assert out.returncode == 2, out.stderr[-2000:]
        (line,) = out.stderr.strip().splitlines()
        assert line.startswith("peel_nachi_bridge: error: ") and message in line, line
