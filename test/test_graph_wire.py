"""Faults on the wire of a running graph (docs/graph.md "Failure handling", docs/runtime.md).

* bad messages from a stranger on the domain: a NaN and a 1e9 m/s command for the very sample
  the simulator waits for (the planner held with SIGSTOP meanwhile, so that the stranger's are
  the only answers), a NaN wrench, a trajectory holding NaN: each dropped or clamped where it
  enters, logged with topic and field, and the run completes with its summary; the bridge
  executed 20 mm/s at most; the learner's report on the last update is in the bag. The
  stranger takes over early in a task (the simulator held with SIGSTOP at a sample 20 mm short
  of the end while the planner drops the NaN wrench), so that the simulator waits for the
  stranger's answer, never for the learner's update that the held planner cannot swap in;
* a second ``peel graph`` on the domain of a running one (its planner held with SIGSTOP from
  its start, so that it runs however long the second takes to look) is refused before it starts anything
  (exit 5, one line naming the domain), and the first run's bag holds its own data only;
* a second node of one name on a domain is warned about by both;
* a recording onto a full disk (the bag file's writes fail with ENOSPC past 12 000 bytes:
  :data:`peel_bag.bag.FAIL_AFTER_ENV`) ends the run with exit 4, the recorder named dead
  in summary.json and the repair command printed; the repaired bag reads back.

Every wait waits for the event it needs, with a timeout only a hang reaches.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from graph_helpers import Lines, assert_clean_logs, node_env
from test_graph_run import graph_cmd, read_bag

from peel_bag.bag import FAIL_AFTER_ENV

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh


HOLD_Q_MM = 5.0  # the simulator is held at a sample nearer the start than this (q_ter 25 mm)


class Stranger:
    """A node of nobody's graph. It subscribes /peel/wrench and /peel/pose from the start (a
    reader is not a graph: the launcher's look for other graphs does not see it). Once asked
    (:meth:`hold_sim`), it stops the simulator (SIGSTOP) at the next sample with q below
    :data:`HOLD_Q_MM`; :meth:`take_over` then stops the planner and lets the simulator go on,
    and the stranger answers every sample with its own commands until disarmed."""

    def __init__(self) -> None:
        import rclpy
        from geometry_msgs.msg import PoseStamped, WrenchStamped
        from rclpy.node import Node

        from peel_msgs_py import topics

        rclpy.init(args=None)
        self.node = Node("stranger")
        self.node.create_subscription(WrenchStamped, topics.WRENCH, self.on_wrench,
                                      topics.qos_profile(topics.WRENCH, subscriber=True))
        self.node.create_subscription(PoseStamped, topics.POSE, self.on_pose,
                                      topics.qos_profile(topics.POSE, subscriber=True))
        self.stamps: list[tuple[int, str]] = []  # (stamp ns, frame) of the simulator's samples
        self.planner: int | None = None
        self.sim: int | None = None  # the simulator to hold, once asked
        self.armed = self.stopped = self.held = False
        self._last_bad = -math.inf
        self.cmd = self.wrench = self.traj = None
        self._stop = threading.Event()
        self._spin = threading.Thread(target=self._run, daemon=True)
        self._spin.start()

    def add_publishers(self, planner_pid: int) -> None:
        from geometry_msgs.msg import TwistStamped, WrenchStamped
        from std_msgs.msg import Float64MultiArray

        from peel_msgs_py import topics

        qos = topics.qos_profile
        self.cmd = self.node.create_publisher(TwistStamped, topics.CMD_VEL, qos(topics.CMD_VEL))
        self.wrench = self.node.create_publisher(WrenchStamped, topics.WRENCH, qos(topics.WRENCH))
        self.traj = self.node.create_publisher(Float64MultiArray, topics.TRAJECTORY,
                                               qos(topics.TRAJECTORY))
        self.planner = planner_pid

    def matched(self) -> bool:
        """The simulator and recorder read its commands, the planner and recorder its wrenches
        (and its own reader of the samples, which DDS matches too), the learner, launcher and
        recorder its trajectories."""
        return (self.traj is not None and self.traj.get_subscription_count() >= 3
                and self.cmd.get_subscription_count() >= 2
                and self.wrench.get_subscription_count() >= 3)

    def _run(self) -> None:
        import rclpy

        while not self._stop.is_set() and rclpy.ok():
            rclpy.spin_once(self.node, timeout_sec=0.05)

    def on_wrench(self, msg) -> None:
        t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if not (msg.header.frame_id.startswith("peel_task_") and math.isfinite(msg.wrench.force.x)):
            return
        self.stamps.append((t, msg.header.frame_id))
        if self.armed:
            self.answer(msg.header)

    def on_pose(self, msg) -> None:
        early = msg.header.frame_id.startswith("peel_task_") and \
            msg.pose.position.x * 1000.0 < HOLD_Q_MM
        if early and self.sim is not None and not self.held:
            os.kill(self.sim, signal.SIGSTOP)  # 20 mm or more left: commands to answer
            self.held = True

    def hold_sim(self, sim_pid: int) -> None:
        """Stop the simulator at its next sample with q below :data:`HOLD_Q_MM`."""
        self.sim = sim_pid

    def take_over(self) -> None:
        """Stop the planner (its answers in flight are its last ones), answer every sample from
        now on, and let the held simulator go on."""
        os.kill(self.planner, signal.SIGSTOP)
        self.stopped = self.armed = True
        os.kill(self.sim, signal.SIGCONT)

    def answer(self, header) -> None:
        """NaN (stamped, then unstamped) and 1e9 m/s for the sample of ``header``."""
        from geometry_msgs.msg import TwistStamped

        for value, stamped in ((float("nan"), True), (float("nan"), False), (1e9, True)):
            msg = TwistStamped()
            if stamped:
                msg.header = header
            msg.twist.linear.x = value
            self.cmd.publish(msg)

    def send_bad_wrench(self) -> None:
        """A NaN wrench stamped like the last sample seen."""
        from geometry_msgs.msg import WrenchStamped

        t, frame = self.stamps[-1]
        bad = WrenchStamped()
        bad.header.stamp.sec, bad.header.stamp.nanosec = divmod(t, 1_000_000_000)
        bad.header.frame_id = frame
        bad.wrench.force.x = float("nan")
        self.wrench.publish(bad)

    def send_bad_wrench_every(self, period_s: float) -> bool:
        """:meth:`send_bad_wrench` unless one went out less than ``period_s`` ago; True."""
        now = time.monotonic()
        if now - self._last_bad >= period_s:
            self.send_bad_wrench()
            self._last_bad = now
        return True

    def send_bad_wrench_and_trajectory(self) -> None:
        from peel_msgs_py.ros.messages import trajectory_msg
        from peel_msgs_py.trajectory import Trajectory

        self.send_bad_wrench()
        n = 5
        traj = Trajectory(t=np.arange(n) * 0.1, q=np.full(n, np.nan), v=np.zeros(n),
                          u=np.zeros(n), fx=np.zeros(n), fz=np.zeros(n), psi=np.zeros(n),
                          outcome="done", meta={"task_index": 0})
        self.traj.publish(trajectory_msg(traj))

    def flush(self, timeout_s: float) -> bool:
        """Wait until every reader matched to its publishers has acknowledged what they sent
        (a writer destroyed earlier takes its unacknowledged samples with it); True if all
        did within ``timeout_s``."""
        from rclpy.duration import Duration

        pubs = [p for p in (self.cmd, self.wrench, self.traj) if p is not None]
        return all(p.wait_for_all_acked(Duration(seconds=timeout_s)) for p in pubs)

    def resume_planner(self) -> None:
        self.armed = False
        for pid in (self.planner if self.stopped else None, self.sim if self.held else None):
            if pid is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGCONT)

    def close(self) -> None:
        import rclpy

        if self._spin is None:
            return
        self.resume_planner()
        self._stop.set()
        self._spin.join(timeout=10)
        self._spin = None
        self.node.destroy_node()
        rclpy.try_shutdown()


def _wait(cond, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def test_bad_commands_wrench_and_trajectory_are_refused_and_the_run_completes(
        tmp_path: Path, ros_domain: str) -> None:
    bag = tmp_path / "bag"
    cmd = graph_cmd(tmp_path, "--record", str(bag), tasks=2)
    override = tmp_path / "override.yaml"  # longer tasks: many control periods to answer,
    override.write_text(override.read_text().replace(  # at real time: seconds to match in
        "q_ter_mm: 6.0", "q_ter_mm: 25.0").replace(
        "      cmd_timeout_s: 5.0\n", "      cmd_timeout_s: 5.0\n      real_time_factor: 1.0\n"))
    stranger = Stranger()
    proc = subprocess.Popen(cmd, env=node_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    sim_log = tmp_path / "run" / "logs" / "peel_sim_node.log"
    try:
        lines = Lines(proc)
        planner = int(lines.wait_for(r"started peel_planner_node \(pid (\d+)\)", 120).group(1))
        stranger.add_publishers(planner)  # the launcher has looked for other graphs
        sim = int(lines.wait_for(r"started peel_sim_node \(pid (\d+)\)", 120).group(1))
        _wait(stranger.matched, 300, "the stranger's publishers to match")
        stranger.hold_sim(sim)
        _wait(lambda: stranger.held, 300, "an early sample of a task")
        # the NaN wrench first, while the planner runs and the task is held: one a second
        # until the planner logs its drop
        plan_log = tmp_path / "run" / "logs" / "peel_planner_node.log"
        _wait(lambda: bool(stranger.stamps) and stranger.send_bad_wrench_every(1.0)
              and "dropped a /peel/wrench message" in plan_log.read_text(), 300,
              "the planner to drop the NaN wrench")
        stranger.take_over()
        stranger.send_bad_wrench_and_trajectory()
        # the simulator re-sends a waiting sample every node.cmd_timeout_s; it logs a clamp
        # only for a command it executed
        _wait(lambda: "clamped a /peel/cmd_vel" in sim_log.read_text(), 300,
              "the simulator to execute the stranger's command")
        stranger.resume_planner()  # before the flush: a stopped node acknowledges nothing
        assert stranger.flush(300), "the stranger's messages were not acknowledged"
        stranger.close()  # done: it leaves the graph before the recorder is stopped
        rc = proc.wait(timeout=400)
    finally:
        stranger.close()
        if proc.poll() is None:
            proc.kill()
    out = lines.join()
    assert rc == 0, out
    assert "peel graph: 2 of 2 tasks finished" in out, out
    assert "dropped a /peel/trajectory message: 'q' holds non-finite values" in out, out
    run = tmp_path / "run"
    summary = json.loads((run / "summary.json").read_text())
    assert len(summary["results"]) == 2 and summary["dead_nodes"] == []
    logs = run / "logs"
    sim = (logs / "peel_sim_node.log").read_text()
    assert "commands limited to 0-20 mm/s" in sim
    assert "dropped a /peel/cmd_vel message: twist.linear.x is not finite (nan)" in sim, sim
    assert "clamped a /peel/cmd_vel message: twist.linear.x = 1e+12 mm/s is outside 0-20 mm/s; " \
           "executed 20 mm/s" in sim, sim
    planner_log = (logs / "peel_planner_node.log").read_text()
    assert "dropped a /peel/wrench message: wrench.force.x is not finite (nan)" in planner_log
    learner = (logs / "model_learner_node.log").read_text()
    assert "dropped a /peel/trajectory message: 'q' holds non-finite values" in learner
    assert "the planner refused" not in learner and "no answer" not in learner, learner
    msgs = read_bag(bag)
    from peel_msgs_py.codec import trajectory_from_msg

    trajs = [trajectory_from_msg(m) for _, m in msgs["/peel/trajectory"]]
    ours = [t for t in trajs if np.all(np.isfinite(t.q))]
    assert len(ours) == 2 and len(trajs) == 3  # the stranger's NaN one is recorded, not used
    assert all(t.meta["cmd_limits_mmps"] == [0.0, 20.0] for t in ours)
    assert sum(t.meta["cmd_clamped"] for t in ours) >= 1
    assert sum(t.meta["cmd_dropped"] for t in ours) >= 1
    assert max(float(np.max(t.u)) for t in ours) <= 20.0
    assert all(np.all(np.isfinite(t.fx)) and t.sum_fx < 1e4 for t in ours)
    # the learner's report on every update, the last one included, is in the bag
    reports = [json.loads(m.data) for _, m in msgs["/peel/model_update"]]
    assert [(r["task"], r["status"]) for r in reports] == [(1, "swapped"), (2, "swapped")]
    assert [r["update"]["status"] for r in summary["results"]] == ["swapped", "swapped"]
    assert_clean_logs(run)


def test_a_second_graph_on_the_domain_is_refused_and_nothing_mixes(
        tmp_path: Path, ros_domain: str) -> None:
    a_dir, b_dir = tmp_path / "a", tmp_path / "b"
    a_dir.mkdir()
    b_dir.mkdir()
    bag = a_dir / "bag"
    a = subprocess.Popen(graph_cmd(a_dir, "--record", str(bag), tasks=2), env=node_env(),
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    planner = None
    try:
        lines = Lines(a)
        planner = int(lines.wait_for(r"started peel_planner_node \(pid (\d+)\)", 120).group(1))
        # A's planner held before it can announce a model: A's simulator waits for it
        # (node.wait_planner_s), so A runs, its launcher and other nodes on the domain, however
        # long B takes to look
        os.kill(planner, signal.SIGSTOP)
        b_cmd = graph_cmd(b_dir, tasks=2)
        override = b_dir / "override.yaml"  # B looks long enough for any discovery delay
        override.write_text(override.read_text().replace("alone_wait_s: 0.5",
                                                         "alone_wait_s: 300.0"))
        b = subprocess.run(b_cmd, env=node_env(), capture_output=True, text=True, timeout=400)
        os.kill(planner, signal.SIGCONT)
        rc = a.wait(timeout=400)
    finally:
        if planner is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(planner, signal.SIGCONT)
        if a.poll() is None:
            a.kill()
    out = lines.join()
    assert b.returncode == 5, b.stdout + b.stderr
    err = b.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("peel graph: error: ROS domain "
                                               f"{ros_domain} already holds a peel graph ("), err
    assert "ROS_DOMAIN_ID" in err[0]
    assert "started" not in b.stdout and not (b_dir / "run").exists()
    assert rc == 0, out
    assert "peel graph: 2 of 2 tasks finished" in out, out
    msgs = read_bag(bag)
    infos = [json.loads(m.data) for _, m in msgs["/peel/model_info"]]
    assert [i["version"] for i in infos] == [0, 1, 2]
    assert len(msgs["/peel/trajectory"]) == 2
    assert all(Path(i["path"]).is_relative_to(a_dir) for i in infos)


def test_a_second_node_of_one_name_is_warned_about(tmp_path: Path, ros_domain: str) -> None:
    """Two simulator nodes started by hand on one domain (each waiting for a planner)."""
    cmd = [sys.executable, "-m", "peel_sim_node.node", "--ros-args", "-p", "node.tasks:=1"]
    procs = [subprocess.Popen(cmd, env=node_env(), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for _ in range(2)]
    try:
        for proc in procs:
            Lines(proc).wait_for(r"a second node named /peel_sim_node is on ROS domain "
                                 f"{ros_domain}", 300)
    finally:
        for proc in procs:
            proc.send_signal(signal.SIGINT)
        for proc in procs:
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
    assert [p.returncode for p in procs] == [0, 0]


def test_a_full_disk_under_record_exits_4_with_the_repair_command(
        tmp_path: Path, ros_domain: str) -> None:
    bag = tmp_path / "bag"
    cmd = graph_cmd(tmp_path, "--record", str(bag), tasks=2)
    # a 2-task bag of this run holds about 10 KB of chunks and 15 KB of summary (index,
    # schemas): the disk fills while the recorder closes the bag, its chunks are complete
    env = dict(node_env(), **{FAIL_AFTER_ENV: "12000"})
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    out = res.stdout + res.stderr
    assert res.returncode == 4, out
    repair = f"peel record --repair {bag}"
    assert f"repair it with: {repair}" in res.stderr, out
    recorder = (tmp_path / "run" / "logs" / "recorder.log").read_text()
    assert "No space left on device (ENOSPC)" in recorder and repair in recorder, recorder
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert "recorder" in summary["dead_nodes"] and summary["status"] == 4
    assert summary["bag_repair"] == repair
    assert summary["status_meaning"].startswith("the recording failed")
    fixed = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "record", "--repair",
                            str(bag)], env=node_env(), capture_output=True, text=True,
                           timeout=120)
    assert fixed.returncode == 0, fixed.stdout + fixed.stderr
    assert read_bag(bag)["/peel/model_info"]  # rosbags opens the repaired bag
