"""``peel_sim_node``: the simulator / plant bridge node of the graph (docs/graph.md).

Runs ``node.tasks`` consecutive tasks (:class:`~peel_sim_node.lockstep.TaskSequence` on
:class:`~peel_sim_node.env.PeelEnv`, ``sim`` or ``plant``) and owns the clock: every sample
(dt = 0.1 s, section 4.2) it publishes ``/clock`` and the measured state on ``/peel/wrench``,
``/peel/twist``, ``/peel/pose`` (SI, stamped with the sample's ROS time, frame
``peel_task_<k>``); each control sample waits for the ``/peel/cmd_vel`` that answers its stamp
(lockstep); each finished task goes out on ``/peel/trajectory``. A wall-clock timer re-sends an
unanswered sample every ``node.cmd_timeout_s``, aborts the task after ``node.cmd_give_up_s``,
and between tasks waits (``node.wait_model_s``) for the learner's update of the last task, as
the paper's loop does (Algorithm 2 line 20): by its identity
(:class:`~peel_msgs_py.modelinfo.UpdateWait`): the planner's ``/peel/model_info`` record of
``node.learner_node``'s update after task k, or the learner's ``/peel/model_update`` report
that it failed, was refused or skipped (then the next task starts at once). A model swapped in
by anyone else does not end the wait. ``node.effects`` adds user effects (``module:function``,
:func:`~peel_sim_node.effects.load_effects`) to the plant; a name that does not import is
refused (exit 2) before any topic exists. A command is executed only inside
``[node.u_min_mmps, node.u_max_mmps]`` (default the Nachi controller's 0-20 mm/s,
:class:`~peel_msgs_py.wire.SpeedLimits`): a faster or negative one is clamped, a non-finite one
dropped, both counted and logged (:class:`~peel_msgs_py.wire.DropLog`) and counted in the
trajectory's meta (``cmd_limits_mmps``, ``cmd_clamped``, ``cmd_dropped``).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64MultiArray, String

from peel_msgs_py import codec, topics
from peel_msgs_py.diagnostics import Status
from peel_msgs_py.errors import PeelError
from peel_msgs_py.modelinfo import SWAPPED, ModelRecord, UpdateReport, UpdateWait
from peel_msgs_py.ros.diagnostics import publish_diagnostics
from peel_msgs_py.ros.main import run_node
from peel_msgs_py.ros.messages import stamp, stamp_ns, trajectory_msg
from peel_msgs_py.ros.parameters import NamedRefusals, declare
from peel_msgs_py.ros.qos import to_profile
from peel_msgs_py.units import mm_to_m, mmps_to_mps, mps_to_mmps
from peel_msgs_py.wire import DropLog, SpeedLimits

from .config import SimConfig
from .effects import load_effects
from .health import sim_status
from .lockstep import Sample, TaskSequence
from .parameters import LIBRARY_SPECS, NODE_NAME, SPECS

#: Period (s, wall clock) of the timer that drives waiting, re-sending and giving up.
TICK_S = 0.05


def library_params(values: dict[str, Any]) -> dict[str, Any]:
    """The declared values the library reads (not the node's, nor rclpy's own)."""
    names = {s.name for s in LIBRARY_SPECS}
    return {k: v for k, v in values.items() if k in names}


class SimNode(NamedRefusals, Node):
    """Publishers, subscriptions and a wall-clock timer around a :class:`TaskSequence`."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        values = declare(self, SPECS)
        self.p = {k: v for k, v in values.items() if k.startswith("node.")}
        try:
            self.limits = SpeedLimits(self.p["node.u_min_mmps"], self.p["node.u_max_mmps"])
        except PeelError as exc:
            raise PeelError(f"parameters 'node.u_min_mmps', 'node.u_max_mmps': {exc}") from None
        self.seq = TaskSequence(SimConfig.from_params(library_params(values)),
                                source=self.p["node.source"], seed=self.p["node.seed"],
                                task_slot_s=self.p["node.task_slot_s"],
                                effects=load_effects(self.p["node.effects"]))
        qos = topics.qos_profile
        self.pub_clock = self.create_publisher(ClockMsg, topics.CLOCK, qos(topics.CLOCK))
        self.pub_wrench = self.create_publisher(WrenchStamped, topics.WRENCH, qos(topics.WRENCH))
        self.pub_twist = self.create_publisher(TwistStamped, topics.TWIST, qos(topics.TWIST))
        self.pub_pose = self.create_publisher(PoseStamped, topics.POSE, qos(topics.POSE))
        self.pub_traj = self.create_publisher(Float64MultiArray, topics.TRAJECTORY,
                                              qos(topics.TRAJECTORY))
        self.create_subscription(TwistStamped, topics.CMD_VEL, self.on_cmd,
                                 qos(topics.CMD_VEL, subscriber=True))
        self.create_subscription(String, topics.MODEL_INFO, self.on_model_info,
                                 to_profile(topics.topic(topics.MODEL_INFO).sub_qos))
        self.create_subscription(String, topics.MODEL_UPDATE, self.on_model_update,
                                 to_profile(topics.topic(topics.MODEL_UPDATE).sub_qos))
        self.updates = UpdateWait(self.p["node.learner_node"])
        self.drops = DropLog()
        self.clamped = self.dropped = 0  # commands of the running task
        self.create_timer(TICK_S, self.on_tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.model_version: int | None = None
        self.versions_seen: set[int] = set()
        self.version_at_start: int | None = None
        self.finished_tasks = 0
        self.phase, self.since = "wait_graph", time.monotonic()
        self.sent = self.asked = self.since  # last publication; first sending of the waiting one
        self.done, self.exit_status = False, 0
        self.last_outcome: str | None = None
        publish_diagnostics(self, self.diagnostics)
        self.get_logger().info(f"{self.p['node.source']} ready: {self.p['node.tasks']} tasks, "
                               f"seed {self.p['node.seed']}, commands limited to "
                               f"{self.limits.describe()}")

    # -- callbacks ---------------------------------------------------------------------------
    def on_cmd(self, msg: TwistStamped) -> None:
        """A command answering the waiting sample, executed inside the limits."""
        u = float(mps_to_mmps(msg.twist.linear.x))
        if not math.isfinite(u):
            self.dropped += 1
            self.log_drop(self.drops.drop(topics.CMD_VEL, "twist.linear.x",
                                          f"is not finite ({u!r})"))
            return
        held = self.limits.clamp(u)
        samples = self.seq.apply(stamp_ns(msg.header.stamp), held)
        if samples is None:
            return
        if held != u:
            self.clamped += 1
            self.log_drop(self.drops.drop(
                topics.CMD_VEL, "twist.linear.x", f"= {u:g} mm/s is outside "
                f"{self.limits.describe()}; executed {held:g} mm/s", action="clamped"))
        for s in samples:
            self.publish(s)
        self.asked = time.monotonic()
        if self.seq.ended:
            self.end_task(None)

    def log_drop(self, line: str | None) -> None:
        if line is not None:
            self.get_logger().warn(line)

    def on_model_info(self, msg: String) -> None:
        """The planner's active model (version and identity)."""
        try:
            rec = ModelRecord.from_json(msg.data)
        except PeelError as exc:
            self.log_drop(self.drops.drop(topics.MODEL_INFO, "data", f"is not a model record: "
                                                                     f"{exc}"))
            return
        self.updates.add_record(rec)
        self.model_version = rec.version
        self.versions_seen.add(rec.version)

    def on_model_update(self, msg: String) -> None:
        """The learner's report on its update after a task."""
        try:
            self.updates.add_report(UpdateReport.from_json(msg.data))
        except PeelError as exc:
            self.log_drop(self.drops.drop(topics.MODEL_UPDATE, "data",
                                          f"is not an update report: {exc}"))

    def on_tick(self) -> None:
        waited = time.monotonic() - self.since
        if self.phase == "wait_graph":
            self.wait_graph(waited)
        elif self.phase == "running":
            self.check_lockstep(waited)
        elif self.phase == "between":
            self.wait_model(waited)

    def diagnostics(self) -> list[Status]:
        """The lockstep's health (:func:`~peel_sim_node.health.sim_status`), 1 Hz."""
        waiting = time.monotonic() - self.asked if self.phase == "running" else None
        return [sim_status(self.p["node.source"], self.phase, self.finished_tasks,
                           self.p["node.tasks"], self.model_version, waiting,
                           self.p["node.cmd_timeout_s"], self.last_outcome)]

    # -- phases ------------------------------------------------------------------------------
    def set_phase(self, phase: str) -> None:
        self.phase, self.since = phase, time.monotonic()

    def wait_graph(self, waited: float) -> None:
        """Before task 1: the planner's model version and enough subscribers (or time out)."""
        missing = []
        if self.model_version is None:
            missing.append(f"{topics.MODEL_INFO} from the planner")
        state = self.p["node.min_subscribers"]
        for pub, want, name in ((self.pub_wrench, state, topics.WRENCH),
                                (self.pub_twist, state, topics.TWIST),
                                (self.pub_pose, state, topics.POSE),
                                (self.pub_traj, self.p["node.min_traj_subscribers"],
                                 topics.TRAJECTORY)):
            if pub.get_subscription_count() < want:
                missing.append(f"{want} subscribers of {name}")
        if missing and waited < self.p["node.wait_planner_s"]:
            return
        if missing:
            self.get_logger().warn(f"starting without {', '.join(missing)}")
        self.start_task()

    def start_task(self) -> None:
        self.version_at_start = self.model_version
        self.publish(self.seq.start(self.finished_tasks))
        self.set_phase("running")
        self.asked = time.monotonic()

    def check_lockstep(self, _: float) -> None:
        """No answer to the waiting sample: re-send it, or abort the task after the give-up."""
        if time.monotonic() - self.sent < self.p["node.cmd_timeout_s"]:
            return
        last, waited = self.seq.last(), time.monotonic() - self.asked
        if waited >= self.p["node.cmd_give_up_s"]:
            self.get_logger().error(f"no {topics.CMD_VEL} for t={last.stamp_ns / 1e9:.1f} s "
                                    f"after {waited:.1f} s; aborting the task")
            self.end_task("aborted")
            return
        self.get_logger().warn(f"lockstep: no {topics.CMD_VEL} answering t="
                               f"{last.stamp_ns / 1e9:.1f} s; re-sending the sample")
        self.publish(last)

    def end_task(self, outcome: str | None) -> None:
        traj = self.seq.finish({"model_version": self.version_at_start,
                                "model_versions": sorted(self.versions_seen),
                                "cmd_limits_mmps": [self.limits.u_min_mmps,
                                                    self.limits.u_max_mmps],
                                "cmd_clamped": self.clamped, "cmd_dropped": self.dropped},
                               outcome)
        self.clamped = self.dropped = 0
        self.pub_traj.publish(trajectory_msg(traj))
        self.finished_tasks += 1
        self.last_outcome = traj.outcome
        self.get_logger().info(f"task {self.finished_tasks}: {traj.outcome}, "
                               f"T_cpl={traj.t_cpl:.1f} s, model v{self.version_at_start}")
        self.set_phase("between")

    def wait_model(self, waited: float) -> None:
        """Between tasks: the learner's update of the last task (Algorithm 2 line 20), known by
        its identity; a failed, refused or skipped update ends the wait at once."""
        task = self.finished_tasks
        wait_s = self.p["node.wait_model_s"]
        outcome = self.updates.outcome(task) if wait_s > 0 else None
        all_done = 0 < self.p["node.tasks"] <= self.finished_tasks
        if outcome is None and wait_s > 0 and waited < wait_s:
            return
        if outcome is None and wait_s > 0:
            self.get_logger().warn(f"the learner's update after task {task} did not arrive "
                                   f"within {wait_s:g} s; going on with model "
                                   f"v{self.model_version}")
        elif outcome is not None and outcome.status != SWAPPED:
            self.get_logger().warn(f"the learner's update after task {task} {outcome.status}"
                                   f"{': ' + outcome.reason if outcome.reason else ''}; going on "
                                   f"with model v{self.model_version}")
        if not all_done:
            self.start_task()
            return
        self.get_logger().info(f"all {self.finished_tasks} tasks done")
        self.set_phase("finished")
        # ros2 launch: exit; peel graph: stay up until stopped, so the bag gets everything
        self.done = bool(self.p["node.exit_when_done"])

    # -- publishing --------------------------------------------------------------------------
    def publish(self, s: Sample) -> None:
        """``/clock`` and the state of one sample (SI, REP-103)."""
        t = stamp(s.stamp_ns)
        frame = codec.task_frame_id(s.task)
        wrench, twist, pose = WrenchStamped(), TwistStamped(), PoseStamped()
        for msg in (wrench, twist, pose):
            msg.header.stamp, msg.header.frame_id = t, frame
        wrench.wrench.force.x, wrench.wrench.force.z = s.fx_n, s.fz_n
        twist.twist.linear.x = mmps_to_mps(s.v_mmps)
        pose.pose.position.x = mm_to_m(s.q_mm)
        self.pub_clock.publish(ClockMsg(clock=t))
        self.pub_wrench.publish(wrench)
        self.pub_twist.publish(twist)
        self.pub_pose.publish(pose)
        self.sent = time.monotonic()

    def destroy_node(self) -> None:
        self.seq.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``peel_sim_node`` (``--ros-args --params-file ... -p ...``)."""
    return run_node(NODE_NAME, SimNode, args)


if __name__ == "__main__":
    sys.exit(main())
