"""``peel_nachi_bridge``: the bridge to the Nachi controller as a ROS 2 node (rclpy; docs/nachi.md).

It stands in for ``peel_sim_node`` in the graph and publishes exactly its topics and trajectory
message: every controller sample as ``/clock`` + ``/peel/wrench``, ``/peel/twist``,
``/peel/pose`` (SI, stamped ``task k * node.task_slot_s`` + the controller's t, frame
``peel_task_<k>``), each finished task on ``/peel/trajectory`` with its outcome; it forwards
``/peel/cmd_vel`` of the running task to the controller as ``V`` (mm/s on the line:
:mod:`peel_msgs_py.units` converts). The link, its safety rules and the task state machine are
the ROS-free :class:`~peel_nachi_bridge.bridge.NachiBridge`; which task runs when is
:class:`~peel_nachi_bridge.sequencer.TaskSequencer`. This module only wires them to rclpy.
"""

from __future__ import annotations

import queue
import sys
import time

from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64MultiArray, Int64, String

from peel_msgs_py import codec, topics
from peel_msgs_py.diagnostics import RecentRises, Status
from peel_msgs_py.errors import PeelError
from peel_msgs_py.modelinfo import ModelRecord, UpdateReport, UpdateWait
from peel_msgs_py.ros.diagnostics import publish_diagnostics
from peel_msgs_py.ros.main import run_node
from peel_msgs_py.ros.messages import stamp, trajectory_msg
from peel_msgs_py.ros.parameters import NamedRefusals, declare
from peel_msgs_py.ros.qos import to_profile
from peel_msgs_py.units import mm_to_m, mmps_to_mps, mps_to_mmps
from peel_msgs_py.wire import DropLog

from . import protocol as p
from .bridge import NachiBridge
from .config import BridgeConfig
from .health import bridge_status
from .parameters import NODE_NAME, SPECS
from .sequencer import Readiness, TaskSequencer
from .task import TaskResult

#: Wall s between two looks at the task sequence (finished tasks, what to start next).
TICK_S = 0.05
#: Nanoseconds per second (stamps are integer ns: task slot + controller time).
NS = 1_000_000_000


class NachiBridgeNode(NamedRefusals, Node):
    """Publishes the controller's samples and tasks; forwards the planner's commands."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        self.cfg = BridgeConfig.from_params(declare(self, SPECS))
        qos = topics.qos_profile
        self.pub_clock = self.create_publisher(ClockMsg, topics.CLOCK, qos(topics.CLOCK))
        self.pub_wrench = self.create_publisher(WrenchStamped, topics.WRENCH, qos(topics.WRENCH))
        self.pub_twist = self.create_publisher(TwistStamped, topics.TWIST, qos(topics.TWIST))
        self.pub_pose = self.create_publisher(PoseStamped, topics.POSE, qos(topics.POSE))
        self.pub_traj = self.create_publisher(Float64MultiArray, topics.TRAJECTORY,
                                              qos(topics.TRAJECTORY))
        self.create_subscription(TwistStamped, topics.CMD_VEL, self.on_cmd_vel,
                                 qos(topics.CMD_VEL, subscriber=True))
        self.create_subscription(Int64, topics.MODEL_VERSION, self.on_model_version,
                                 qos(topics.MODEL_VERSION, subscriber=True))
        self.create_subscription(String, topics.MODEL_INFO, self.on_model_info,
                                 to_profile(topics.topic(topics.MODEL_INFO).sub_qos))
        self.create_subscription(String, topics.MODEL_UPDATE, self.on_model_update,
                                 to_profile(topics.topic(topics.MODEL_UPDATE).sub_qos))
        self.updates = UpdateWait(self.cfg.node.learner_node)
        self.drops = DropLog()
        self.model_version: int | None = None
        self.versions_seen: set[int] = set()
        self.version_at_start: dict[int, int | None] = {}
        self.ended: queue.SimpleQueue[TaskResult] = queue.SimpleQueue()
        self.done, self.exit_status = False, 0
        self.sequencer = TaskSequencer(self.cfg.node, self.on_log)
        self.bridge = NachiBridge(self.cfg.link, self.cfg.safety, self).start()
        self.create_timer(TICK_S, self.on_tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.faults = RecentRises()
        publish_diagnostics(self, self.diagnostics)
        self.get_logger().info(f"bridge to the controller at {self.cfg.link.host}:"
                               f"{self.cfg.link.port} ({p.PROTOCOL} {p.VERSION}), commands "
                               f"limited to {self.bridge.limits.describe()}")

    # -- ROS callbacks ------------------------------------------------------------------------
    def on_cmd_vel(self, msg: TwistStamped) -> None:
        try:
            index = codec.task_from_frame_id(msg.header.frame_id)
        except PeelError as exc:
            self.log_drop(self.drops.drop(topics.CMD_VEL, "header.frame_id", f"is bad: {exc}"))
            return
        self.bridge.command(float(mps_to_mmps(msg.twist.linear.x)), index)

    def on_model_version(self, msg: Int64) -> None:
        if msg.data < 0:
            self.log_drop(self.drops.drop(topics.MODEL_VERSION, "data",
                                          f"is negative ({msg.data})"))
            return
        self.model_version = int(msg.data)
        self.versions_seen.add(int(msg.data))

    def on_model_info(self, msg: String) -> None:
        try:
            self.updates.add_record(ModelRecord.from_json(msg.data))
        except PeelError as exc:
            self.log_drop(self.drops.drop(topics.MODEL_INFO, "data",
                                          f"is not a model record: {exc}"))

    def on_model_update(self, msg: String) -> None:
        try:
            self.updates.add_report(UpdateReport.from_json(msg.data))
        except PeelError as exc:
            self.log_drop(self.drops.drop(topics.MODEL_UPDATE, "data",
                                          f"is not an update report: {exc}"))

    def log_drop(self, line: str | None) -> None:
        if line is not None:
            self.get_logger().warning(line)

    def on_tick(self) -> None:
        while not self.ended.empty():
            self.publish_task(self.ended.get())
        state_readers = min(pub.get_subscription_count()
                            for pub in (self.pub_wrench, self.pub_twist, self.pub_pose))
        seen = Readiness(self.model_version, state_readers, self.pub_traj.get_subscription_count(),
                         update_known=lambda task: self.updates.outcome(task) is not None)
        index = self.sequencer.poll(time.monotonic(), seen)
        if index is not None:
            self.version_at_start[index] = self.model_version
            self.bridge.request_task(index)
        if self.bridge.gave_up and self.bridge.busy:
            self.get_logger().error(f"giving up: {self.bridge.gave_up}")
            self.done, self.exit_status = True, 1
        elif self.sequencer.exit_now:
            self.done = True

    def diagnostics(self) -> list[Status]:
        """The link's health (:func:`~peel_nachi_bridge.health.bridge_status`), 1 Hz."""
        b = self.bridge
        return [bridge_status(b.stats, b.state, b.gave_up, f"{self.cfg.link.host}:{self.cfg.link.port}",
                              b.controller_id, self.faults, time.monotonic())]

    # -- bridge listener (called from the bridge thread) ----------------------------------------
    def on_sample(self, index: int, s: p.Sample) -> None:
        t = stamp(round(index * self.cfg.node.task_slot_s * NS) + round(s.t * NS))
        frame = codec.task_frame_id(index)
        wrench, twist, pose = WrenchStamped(), TwistStamped(), PoseStamped()
        for msg in (wrench, twist, pose):
            msg.header.stamp, msg.header.frame_id = t, frame
        wrench.wrench.force.x, wrench.wrench.force.z = s.fx, s.fz
        twist.twist.linear.x = mmps_to_mps(s.v)
        pose.pose.position.x = mm_to_m(s.q)
        self.pub_clock.publish(ClockMsg(clock=t))
        self.pub_wrench.publish(wrench)
        self.pub_twist.publish(twist)
        self.pub_pose.publish(pose)

    def on_task_end(self, result: TaskResult) -> None:
        self.ended.put(result)

    def on_log(self, level: str, text: str) -> None:
        # one call site per severity: rclpy's logger refuses a call site that changes severity
        log = self.get_logger()
        if level == "error":
            log.error(text)
        elif level == "warn":
            log.warning(text)
        else:
            log.info(text)

    # -- tasks ----------------------------------------------------------------------------------
    def publish_task(self, result: TaskResult) -> None:
        traj = result.trajectory
        published = result.started and traj is not None and len(traj) > 0
        if published:
            assert traj is not None
            traj.meta.update({
                "task_index": result.index, "t0_ros_s": result.index * self.cfg.node.task_slot_s,
                "model_version": self.version_at_start.get(result.index),
                "model_versions": sorted(self.versions_seen),
                "cmd_limits_mmps": [self.bridge.limits.u_min_mmps, self.bridge.limits.u_max_mmps]})
            self.pub_traj.publish(trajectory_msg(traj))
            self.get_logger().info(f"task {result.index + 1}: {result.outcome} ({result.reason}), "
                                   f"T_cpl={traj.t_cpl:.1f} s, model "
                                   f"v{traj.meta['model_version']}")
        elif result.started:
            self.get_logger().warn(f"task {result.index + 1}: {result.reason} before its first "
                                   "sample; nothing to publish")
        self.sequencer.task_ended(time.monotonic(), result, published)

    def destroy_node(self) -> None:
        self.bridge.close()
        while self.context.ok() and not self.ended.empty():  # a task the shutdown stopped
            self.publish_task(self.ended.get())
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``peel_nachi_bridge`` (``--ros-args --params-file ... -p ...``)."""
    return run_node(NODE_NAME, NachiBridgeNode, args)


if __name__ == "__main__":
    sys.exit(main())
