"""``peel_nachi_bridge``: the bridge to the Nachi controller as a ROS 2 node (rclpy; docs/nachi.md).

A managed node (:class:`~peel_msgs_py.ros.lifecycle.ManagedNode`, docs/graph.md "Lifecycle"):
configure checks the parameters, connects to the controller and checks its HELLO
(:func:`~peel_nachi_bridge.connect.connect_checked`; no controller within
``link.configure_timeout_s`` leaves it unconfigured); activate starts the tasks and the
forwarding; deactivate sends ``STOP`` to a running task and forwards nothing more; cleanup
closes the link. It stands in for ``peel_sim_node`` in the graph and publishes exactly its
topics and trajectory message: every controller sample as ``/clock`` + ``/peel/wrench``,
``/peel/twist``, ``/peel/pose`` (SI, stamped ``task k * node.task_slot_s`` + the controller's t,
frame ``peel_task_<k>``), each finished task on ``/peel/trajectory`` with its outcome; it
forwards ``/peel/cmd_vel`` of the running task to the controller as ``V`` (mm/s on the line:
:mod:`peel_msgs_py.units` converts). The link, its safety rules and the task state machine are
the ROS-free :class:`~peel_nachi_bridge.bridge.NachiBridge`; which task runs when is
:class:`~peel_bridge.loop.TaskLoop`, and the publishers, the command subscription and model
following (``/peel/model_info``, ``/peel/model_update``) are
:class:`~peel_bridge.plant_node.PlantTopics`, both shared with ``peel_sim_node``. This module
only wires them to rclpy.
"""

from __future__ import annotations

import queue
import sys
import time

from geometry_msgs.msg import TwistStamped
from rclpy.clock import Clock, ClockType

from peel_bridge.loop import LoopParams, TaskLoop, task_stamp_ns, to_ns
from peel_bridge.plant_node import PlantTopics
from peel_msgs_py import codec, topics
from peel_msgs_py.diagnostics import RecentRises, Status
from peel_msgs_py.errors import PeelError
from peel_msgs_py.lifecycle import AUTOSTART
from peel_msgs_py.ros.diagnostics import publish_diagnostics
from peel_msgs_py.ros.lifecycle import ManagedNode
from peel_msgs_py.ros.main import run_node
from peel_msgs_py.ros.parameters import NamedRefusals, declare
from peel_msgs_py.task import Sample
from peel_msgs_py.units import mps_to_mmps

from . import protocol as p
from .bridge import NachiBridge
from .config import BridgeConfig
from .connect import connect_checked
from .health import bridge_status
from .parameters import NODE_NAME, SPECS
from .task import TaskResult

#: Wall s between two looks at the task loop (finished tasks, what to start next).
TICK_S = 0.05


class NachiBridgeNode(NamedRefusals, ManagedNode):
    """Publishes the controller's samples and tasks; forwards the planner's commands. A managed
    node: configure connects and checks HELLO, activate runs the tasks, deactivate sends STOP
    (docs/graph.md "Lifecycle")."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        values = declare(self, SPECS)
        self.bridge: NachiBridge | None = None  # None while unconfigured
        self.ended: queue.SimpleQueue[TaskResult] = queue.SimpleQueue()
        self.done, self.exit_status = False, 0
        self.faults = RecentRises()
        publish_diagnostics(self, self.diagnostics)
        self.autostart(values[AUTOSTART.name])

    def setup(self) -> None:
        """configure: the parameters checked, the controller connected and its HELLO checked
        (:func:`~peel_nachi_bridge.connect.connect_checked`), the topics made."""
        values = {n: v.value for n, v in self.get_parameters_by_prefix("").items()}
        self.cfg = BridgeConfig.from_params(values)
        self.slot_ns = to_ns(self.cfg.node.task_slot_s)
        self.plant = PlantTopics(self, self.cfg.node.learner_node, self.on_cmd_vel)
        self.loop = TaskLoop(LoopParams.from_params(values), self.on_log)
        conn = connect_checked(self.cfg.link, self.get_logger().warning)
        self.bridge = NachiBridge(self.cfg.link, self.cfg.safety, self).start(conn)
        self.own(self.create_timer(TICK_S, self.on_tick,
                                   clock=Clock(clock_type=ClockType.STEADY_TIME)))
        self.get_logger().info(f"bridge to the controller at {self.cfg.link.host}:"
                               f"{self.cfg.link.port} ({p.PROTOCOL} {p.VERSION}), commands "
                               f"limited to {self.bridge.limits.describe()}")

    def stop(self) -> None:
        """deactivate: ``STOP`` to a running task (it ends ``aborted``), no command forwarded
        and no task started; the stopped task's trajectory still goes out."""
        assert self.bridge is not None
        self.bridge.stop_task("deactivated")

    def release(self) -> None:
        """cleanup / shutdown: the link closed (a running task stopped first), the ended tasks
        published, the topics destroyed."""
        if self.bridge is not None:
            self.bridge.close()
            self.publish_ended()
            self.bridge = None
        if getattr(self, "plant", None) is not None:
            self.plant.destroy()
        self.plant = None

    def publish_ended(self) -> None:
        """Publish the tasks the link's thread has ended."""
        while self.context.ok() and not self.ended.empty():
            self.publish_task(self.ended.get())

    # -- ROS callbacks ------------------------------------------------------------------------
    def on_cmd_vel(self, msg: TwistStamped) -> None:
        """A command of the running task, forwarded as ``V`` (only while active)."""
        if not self.active or self.bridge is None:
            return
        try:
            index = codec.task_from_frame_id(msg.header.frame_id)
        except PeelError as exc:
            self.plant.log_drop(self.plant.drops.drop(topics.CMD_VEL, "header.frame_id",
                                                      f"is bad: {exc}"))
            return
        self.bridge.command(float(mps_to_mmps(msg.twist.linear.x)), index)

    def on_tick(self) -> None:
        """Publish ended tasks; active, start the next one when the task loop says so."""
        assert self.bridge is not None
        self.publish_ended()
        if not self.active:
            return
        index = self.loop.poll(time.monotonic(), self.plant.readiness())
        if index is not None:
            self.plant.task_started(index)
            self.bridge.request_task(index)
        if self.bridge.gave_up and self.bridge.busy:
            self.get_logger().error(f"giving up: {self.bridge.gave_up}")
            self.done, self.exit_status = True, 1
        elif self.loop.exit_now:
            self.done = True

    def diagnostics(self) -> list[Status]:
        """The link's health (:func:`~peel_nachi_bridge.health.bridge_status`), 1 Hz; the
        lifecycle state while not active."""
        b = self.bridge
        if b is None:
            return self.lifecycle_status()
        return [*self.lifecycle_status(),
                bridge_status(b.stats, b.state, b.gave_up,
                              f"{self.cfg.link.host}:{self.cfg.link.port}", b.controller_id,
                              self.faults, time.monotonic())]

    # -- bridge listener (called from the bridge thread) ----------------------------------------
    def on_sample(self, index: int, s: p.Sample) -> None:
        self.plant.publish_sample(Sample(task_stamp_ns(index, self.slot_ns, s.t), index,
                                         s.q, s.v, s.fx, s.fz))

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
                **self.plant.graph_meta(result.index),
                "cmd_limits_mmps": [self.bridge.limits.u_min_mmps, self.bridge.limits.u_max_mmps]})
            self.plant.publish_trajectory(traj, result.index + 1, result.reason)
        elif result.started:
            self.get_logger().warn(f"task {result.index + 1}: {result.reason} before its first "
                                   "sample; nothing to publish")
        self.loop.task_ended(time.monotonic(), result.index, started=result.started,
                             published=published)


def main(args: list[str] | None = None) -> int:
    """Console entry point ``peel_nachi_bridge`` (``--ros-args --params-file ... -p ...``)."""
    return run_node(NODE_NAME, NachiBridgeNode, args)


if __name__ == "__main__":
    sys.exit(main())
