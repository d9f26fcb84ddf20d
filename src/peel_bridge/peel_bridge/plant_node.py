"""The rclpy side both plant bridge nodes share (docs/graph.md): publishers, model following and
per-sample publishing.

:class:`PlantTopics` is created by ``peel_sim_node`` and ``peel_nachi_bridge`` when they are
configured (and destroyed, :meth:`PlantTopics.destroy`, at their cleanup); it holds

* the publishers of a plant: ``/clock`` and the measured state of every sample on
  ``/peel/wrench``, ``/peel/twist``, ``/peel/pose`` (SI, REP-103; stamped with the sample's ROS
  time, frame ``peel_task_<k>``; :meth:`PlantTopics.publish_sample`) and each finished task on
  ``/peel/trajectory`` (:meth:`PlantTopics.publish_trajectory`);
* the subscription to the planner's commands ``/peel/cmd_vel`` (the node's callback);
* model following, the same for both: the planner's ``/peel/model_info`` (version and identity
  of every model it plans with) and the learner's ``/peel/model_update`` reports, collected in an
  :class:`~peel_msgs_py.modelinfo.UpdateWait` that the task loop asks between tasks
  (:meth:`PlantTopics.readiness`), and the version each task started with
  (:meth:`PlantTopics.task_started`, :meth:`PlantTopics.model_meta`: also the identity of every
  model the planner announced during the task, a fast step inside the peel named by its
  ``fast`` field);
* the planner's guard of the force limit, ``/peel/planner_safety`` (JSON after each plan): the
  last report of each task becomes its trajectory's ``planner_guard``, so both bridges carry the
  same safety fields (:meth:`PlantTopics.graph_meta` = model following + ``planner_guard``).

A message that does not parse is dropped, counted and logged (:class:`~peel_msgs_py.wire.DropLog`).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64MultiArray, String

from peel_msgs_py import codec, inbox, topics
from peel_msgs_py.modelinfo import ModelRecord, UpdateWait
from peel_msgs_py.ros.messages import stamp, trajectory_msg
from peel_msgs_py.ros.qos import to_profile
from peel_msgs_py.task import Sample
from peel_msgs_py.trajectory import Trajectory
from peel_msgs_py.units import mm_to_m, mmps_to_mps
from peel_msgs_py.wire import DropLog

from .loop import Readiness


class PlantTopics:
    """Publishers, command subscription and model following of one plant bridge node."""

    def __init__(self, node: Node, learner_node: str,
                 on_cmd: Callable[[TwistStamped], None]) -> None:
        self.node = node
        qos = topics.qos_profile
        self.pub_clock = node.create_publisher(ClockMsg, topics.CLOCK, qos(topics.CLOCK))
        self.pub_wrench = node.create_publisher(WrenchStamped, topics.WRENCH, qos(topics.WRENCH))
        self.pub_twist = node.create_publisher(TwistStamped, topics.TWIST, qos(topics.TWIST))
        self.pub_pose = node.create_publisher(PoseStamped, topics.POSE, qos(topics.POSE))
        self.pub_traj = node.create_publisher(Float64MultiArray, topics.TRAJECTORY,
                                              qos(topics.TRAJECTORY))
        self.subs = [
            node.create_subscription(TwistStamped, topics.CMD_VEL, on_cmd,
                                     qos(topics.CMD_VEL, subscriber=True)),
            node.create_subscription(String, topics.MODEL_INFO, self.on_model_info,
                                     to_profile(topics.topic(topics.MODEL_INFO).sub_qos)),
            node.create_subscription(String, topics.MODEL_UPDATE, self.on_model_update,
                                     to_profile(topics.topic(topics.MODEL_UPDATE).sub_qos)),
            node.create_subscription(String, topics.PLANNER_SAFETY, self.on_planner_safety,
                                     qos(topics.PLANNER_SAFETY, subscriber=True))]
        #: task index -> the planner's last guard report of that task (``/peel/planner_safety``)
        self.guard_reports: dict[int, dict[str, Any]] = {}
        self.updates = UpdateWait(learner_node)
        self.drops = DropLog()
        self.model_version: int | None = None
        self.versions_seen: set[int] = set()
        self.records: dict[int, ModelRecord] = {}
        self.version_at_start: dict[int, int | None] = {}

    def destroy(self) -> None:
        """Destroy the publishers and subscriptions (the managed bridge's cleanup)."""
        for pub in (self.pub_clock, self.pub_wrench, self.pub_twist, self.pub_pose,
                    self.pub_traj):
            self.node.destroy_publisher(pub)
        for sub in self.subs:
            self.node.destroy_subscription(sub)

    # -- model following ------------------------------------------------------------------
    def on_model_info(self, msg: String) -> None:
        """The planner's active model (version and identity)."""
        rec = inbox.take(self.drops, topics.MODEL_INFO, inbox.model_record, msg, self.log_drop)
        if rec is None:
            return
        self.updates.add_record(rec)
        self.model_version = rec.version
        self.versions_seen.add(rec.version)
        self.records[rec.version] = rec

    def on_model_update(self, msg: String) -> None:
        """The learner's report on its update after a task."""
        rep = inbox.take(self.drops, topics.MODEL_UPDATE, inbox.update_report, msg, self.log_drop)
        if rep is not None:
            self.updates.add_report(rep)

    def on_planner_safety(self, msg: String) -> None:
        """The planner's guard after a plan: kept as the latest of its task."""
        try:
            report = json.loads(msg.data)
            task = int(report.pop("task"))
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            self.log_drop(self.drops.drop(topics.PLANNER_SAFETY, "data",
                                          f"is not a guard report: {exc}"))
            return
        self.guard_reports[task] = report
        for old in [k for k in self.guard_reports if k < task - 10]:
            del self.guard_reports[old]

    def readiness(self) -> Readiness:
        """What the task loop needs to see of the graph: model, readers, the learner's updates."""
        state = min(pub.get_subscription_count()
                    for pub in (self.pub_wrench, self.pub_twist, self.pub_pose))
        return Readiness(self.model_version, state, self.pub_traj.get_subscription_count(),
                         update=self.updates.outcome)

    def task_started(self, index: int) -> None:
        """Task ``index`` starts with the planner's current model."""
        self.version_at_start[index] = self.model_version

    def model_meta(self, index: int) -> dict[str, Any]:
        """The trajectory meta of model following: the version task ``index`` started with,
        every version seen so far, and the identity (``/peel/model_info`` JSON) of each model
        announced from the task's start on."""
        start = self.version_at_start.get(index)
        models = [json.loads(r.to_json()) for v, r in sorted(self.records.items())
                  if start is None or v >= start]
        return {"model_version": start, "model_versions": sorted(self.versions_seen),
                "models": models}

    def graph_meta(self, index: int) -> dict[str, Any]:
        """The trajectory meta a bridge takes from the graph for task ``index``: model following
        (:meth:`model_meta`) and ``planner_guard``, the planner's last guard report of the task
        (None when none arrived)."""
        return {**self.model_meta(index), "planner_guard": self.guard_reports.get(index)}

    def log_drop(self, line: str | None) -> None:
        if line is not None:
            self.node.get_logger().warning(line)

    # -- publishing -----------------------------------------------------------------------
    def publish_sample(self, s: Sample) -> None:
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

    def publish_trajectory(self, traj: Trajectory, number: int, reason: str = "") -> None:
        """Task ``number`` (1-based) on ``/peel/trajectory``, and its line in the log."""
        self.pub_traj.publish(trajectory_msg(traj))
        why = f" ({reason})" if reason else ""
        self.node.get_logger().info(f"task {number}: {traj.outcome}{why}, T_cpl={traj.t_cpl:.1f} "
                                    f"s, model v{traj.meta.get('model_version')}")
