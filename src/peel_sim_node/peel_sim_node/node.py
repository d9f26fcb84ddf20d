"""``peel_sim_node``: the simulator / plant bridge node of the graph (issue 7, docs/graph.md).

Runs ``node.tasks`` consecutive peeling tasks on :class:`peel_sim_node.env.PeelEnv` (``sim`` or
``plant``) and owns the clock:

* every sample (dt = 0.1 s, section 4.2) it publishes ``/clock`` and the measured state on
  ``/peel/wrench``, ``/peel/twist``, ``/peel/pose`` (SI, stamped with the sample's ROS time);
* at every control instant (every 5th sample, 0.5 s) it waits for the ``/peel/cmd_vel`` whose
  ``header.stamp`` equals the stamp of that sample (lockstep), then applies it with
  ``PeelEnv.step`` for the next control period. A missing answer is logged and the sample is
  sent again every ``node.cmd_timeout_s``; after ``node.cmd_give_up_s`` the task is aborted;
* each finished task goes out on ``/peel/trajectory`` (trajectory codec) with its outcome.

Task ``i`` occupies ROS time ``[i * node.task_slot_s, (i + 1) * node.task_slot_s)``; inside the
trajectory the time restarts at 0. Between tasks the node waits (``node.wait_model_s``) for the
learner's new model version, as the paper's loop does (Algorithm 2 line 20).

This module is a thin adapter: the physics is the library's, units go through
:mod:`peel_msgs_py.units` / :mod:`peel_msgs_py.codec`.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from peel_msgs_py.params import ParamSpec, validate_group
from peel_msgs_py.trajectory import Trajectory
from peel_msgs_py.units import mm_to_m, mmps_to_mps, mps_to_mmps

NODE_NAME = "peel_sim_node"

#: Node-only parameters (``node:`` group of config/peel_sim_node.yaml); wall-clock timeouts.
NODE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("node.source", str, "sim", "run the simulator or the plant", choices=("sim", "plant")),
    ParamSpec("node.tasks", int, 3, "consecutive tasks to run; 0 = until stopped", min=0),
    ParamSpec("node.seed", int, 0, "seed of the task sequence (as peel experiment's)", min=0),
    ParamSpec("node.task_slot_s", float, 100.0, "ROS time reserved per task, s", min=1.0),
    ParamSpec("node.cmd_timeout_s", float, 2.0, "wall s before the sample is re-sent", min=0.01),
    ParamSpec("node.cmd_give_up_s", float, 120.0, "wall s before the task is aborted", min=0.1),
    ParamSpec("node.wait_model_s", float, 120.0,
              "wall s to wait for the learner's new model between tasks; 0 = do not", min=0.0),
    ParamSpec("node.wait_planner_s", float, 120.0,
              "wall s to wait for the planner's /peel/model_version before task 1", min=0.0),
    ParamSpec("node.min_subscribers", int, 1,
              "wait for this many subscribers of /peel/wrench before task 1", min=0),
    ParamSpec("node.min_traj_subscribers", int, 1,
              "wait for this many subscribers of /peel/trajectory before task 1 (learner, "
              "launcher, recorder)", min=0),
    ParamSpec("node.exit_when_done", bool, False,
              "exit after the last task (and its model update); for ros2 launch"),
    ParamSpec("node.effects", list, [],
              "user effects module:function added to the plant (peel_sim_node.effects)"),
)


def node_params(flat: dict[str, Any]) -> dict[str, Any]:
    """Validate the ``node.*`` parameters of a flat parameter dict (others are ignored)."""
    return validate_group(NODE_SPECS, flat, "node")


def library_params(flat: dict[str, Any]) -> dict[str, Any]:
    """The flat dict without the node-only and ROS-only names, for the library's config."""
    return {k: v for k, v in flat.items() if not k.startswith("node.") and k != "use_sim_time"}


def all_parameters(node: Any) -> dict[str, Any]:
    """Every declared parameter of ``node`` as a flat ``name -> value`` dict (rclpy API)."""
    return {name: p.value for name, p in node.get_parameters_by_prefix("").items()}


def task_seed(seed: int, k: int) -> int:
    """Sensor-noise and planner-noise seed of task ``k``; the same derivation as ``peel
    experiment`` (peel_bringup.experiment.task_seed, stream 0), so a graph run and an experiment
    with the same seed peel the same substrates with the same noise."""
    return int(np.random.SeedSequence([seed, 0, k]).generate_state(1)[0])


def task_params(cfg: Any, seed: int, k: int, source: str) -> dict[str, float]:
    """Physical parameters of task ``k`` (3.2.1 intervals), as peel_bringup.experiment.substrates."""
    from .env import sample_params

    return dict(sample_params(cfg, np.random.default_rng([seed, 0, k]), source))


def to_ns(t_s: float) -> int:
    """Seconds of ROS time -> integer nanoseconds (exact comparisons of stamps)."""
    return round(t_s * 1e9)


class SimNode:
    """The node: publishers, subscriptions and the task loop (run from :func:`main`)."""

    def __init__(self, args: list[str] | None = None) -> None:
        from peel_msgs_py import codec, topics
        from peel_msgs_py.runtime import Node
        from peel_msgs_py.runtime.msg import (
            Clock,
            Float64MultiArray,
            Int64,
            PoseStamped,
            TwistStamped,
            WrenchStamped,
        )

        from .config import SimConfig
        from .env import PeelEnv

        self.codec, self.topics = codec, topics
        self.msg = {"clock": Clock, "wrench": WrenchStamped, "twist": TwistStamped,
                    "pose": PoseStamped}
        self.node = Node(NODE_NAME, automatically_declare_parameters_from_overrides=True)
        flat = all_parameters(self.node)
        self.p = node_params(flat)
        self.cfg = SimConfig.from_params(library_params(flat))
        self.steps = self.cfg.samples_per_control
        from .effects import load_effects

        effects = load_effects([str(e) for e in self.p["node.effects"]])
        self.env = PeelEnv(self.cfg, source=self.p["node.source"],
                           seed=task_seed(self.p["node.seed"], 0), effects=effects)
        n = self.node
        qos = topics.qos_profile
        self.pub_clock = n.create_publisher(Clock, topics.CLOCK, qos(topics.CLOCK))
        self.pub_wrench = n.create_publisher(WrenchStamped, topics.WRENCH, qos(topics.WRENCH))
        self.pub_twist = n.create_publisher(TwistStamped, topics.TWIST, qos(topics.TWIST))
        self.pub_pose = n.create_publisher(PoseStamped, topics.POSE, qos(topics.POSE))
        self.pub_traj = n.create_publisher(
            Float64MultiArray, topics.TRAJECTORY, qos(topics.TRAJECTORY))
        self.cmds: dict[int, float] = {}  # stamp (ns) -> command (mm/s)
        self.model_version: int | None = None
        self.frame_id = codec.task_frame_id(0)
        self.versions_seen: list[int] = []
        n.create_subscription(TwistStamped, topics.CMD_VEL, self._on_cmd,
                              qos(topics.CMD_VEL, subscriber=True))
        n.create_subscription(Int64, topics.MODEL_VERSION, self._on_version,
                              qos(topics.MODEL_VERSION, subscriber=True))
        self.log = n.get_logger()

    # -- callbacks ---------------------------------------------------------------------------
    def _on_cmd(self, msg: Any) -> None:
        stamp = msg.header.stamp
        self.cmds[int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)] = float(
            mps_to_mmps(msg.twist.linear.x))
        if len(self.cmds) > 64:
            for key in sorted(self.cmds)[:-32]:
                del self.cmds[key]

    def _on_version(self, msg: Any) -> None:
        self.model_version = int(msg.data)
        self.versions_seen.append(int(msg.data))

    # -- helpers -----------------------------------------------------------------------------
    def spin_until(self, cond: Callable[[], bool], timeout_s: float) -> bool:
        """Process callbacks until ``cond()`` holds or ``timeout_s`` (wall) passes."""
        from peel_msgs_py.runtime import rclpy

        deadline = time.monotonic() + timeout_s
        while not cond():
            left = deadline - time.monotonic()
            if left <= 0:
                return cond()
            rclpy.spin_once(self.node, timeout_sec=min(0.05, left))
        return True

    def publish_sample(self, t0_s: float, k: int) -> int:
        """Publish /clock and the state of sample ``k`` of the current task; return its stamp.

        ``header.frame_id`` = ``peel_task_<i>`` (:func:`peel_msgs_py.codec.task_frame_id`) tells
        subscribers which task the sample belongs to."""
        h = self.env.history
        stamp_ns = to_ns(t0_s + float(h.t[k]))
        m = self.msg
        clock, wrench, twist, pose = m["clock"](), m["wrench"](), m["twist"](), m["pose"]()
        clock.clock.sec, clock.clock.nanosec = divmod(stamp_ns, 1_000_000_000)
        for msg in (wrench, twist, pose):
            msg.header.stamp.sec, msg.header.stamp.nanosec = clock.clock.sec, clock.clock.nanosec
            msg.header.frame_id = self.frame_id
        wrench.wrench.force.x = float(h.fx[k])
        wrench.wrench.force.z = float(h.fz[k])
        twist.twist.linear.x = float(mmps_to_mps(float(h.v[k])))
        pose.pose.position.x = float(mm_to_m(float(h.q[k])))
        self.pub_clock.publish(clock)
        self.pub_wrench.publish(wrench)
        self.pub_twist.publish(twist)
        self.pub_pose.publish(pose)
        return stamp_ns


    def wait_command(self, t0_s: float, k: int) -> float | None:
        """Lockstep: wait for the command answering sample ``k``; re-send the sample on timeout."""
        stamp_ns = to_ns(t0_s + float(self.env.history.t[k]))
        start = time.monotonic()
        while True:
            if self.spin_until(lambda: stamp_ns in self.cmds, self.p["node.cmd_timeout_s"]):
                return self.cmds.pop(stamp_ns)
            waited = time.monotonic() - start
            if waited >= self.p["node.cmd_give_up_s"]:
                self.log.error(f"no /peel/cmd_vel for t={stamp_ns / 1e9:.1f} s after "
                               f"{waited:.1f} s; aborting the task")
                return None
            self.log.warn(f"lockstep: no /peel/cmd_vel answering t={stamp_ns / 1e9:.1f} s after "
                          f"{waited:.1f} s (wall); re-sending the sample")
            self.publish_sample(t0_s, k)

    def run_task(self, index: int) -> Trajectory:
        """One task in lockstep with the planner; returns the finished trajectory."""
        t0_s = index * self.p["node.task_slot_s"]
        version_at_start = self.model_version
        seed, source = self.p["node.seed"], self.p["node.source"]
        self.env.reset(seed=task_seed(seed, index),
                       params=task_params(self.cfg, seed, index, source))
        k = len(self.env.history) - 1
        self.frame_id = self.codec.task_frame_id(index)
        self.publish_sample(t0_s, k)
        outcome_override = None
        while not self.env.done:
            u = self.wait_command(t0_s, k)
            if u is None:
                outcome_override = "aborted"
                break
            for _ in range(self.steps):
                self.env.step(u)
                k = len(self.env.history) - 1
                self.publish_sample(t0_s, k)
                if self.env.done:
                    break
        traj = self.env.history
        if outcome_override is not None:
            traj = traj.slice(0, len(traj))
            traj.outcome = outcome_override
        traj.meta.update({
            "source": self.p["node.source"], "seed": self.p["node.seed"], "task_index": index,
            "task_seed": task_seed(self.p["node.seed"], index),
            "t0_ros_s": t0_s, "model_version": version_at_start,
            "model_versions": sorted(set(self.versions_seen)),
        })
        return traj

    def run(self) -> int:
        """All tasks; returns the exit status."""
        p = self.p
        if p["node.wait_planner_s"] > 0 and not self.spin_until(
                lambda: self.model_version is not None, p["node.wait_planner_s"]):
            self.log.warn("no /peel/model_version from the planner yet; starting anyway")
        if p["node.min_subscribers"] > 0 and not self.spin_until(
                lambda: self.pub_wrench.get_subscription_count() >= p["node.min_subscribers"],
                p["node.wait_planner_s"]):
            self.log.warn(f"fewer than {p['node.min_subscribers']} subscribers on "
                          f"{self.topics.WRENCH}; starting anyway")
        for pub, want in ((self.pub_traj, p["node.min_traj_subscribers"]),):
            if want > 0 and not self.spin_until(
                    lambda pub=pub, want=want: pub.get_subscription_count() >= want,
                    p["node.wait_planner_s"]):
                self.log.warn(f"fewer than {want} subscribers on {self.topics.TRAJECTORY}; "
                              "starting anyway")
        start_version = self.model_version or 0
        index = 0
        while p["node.tasks"] == 0 or index < p["node.tasks"]:
            if index > 0 and p["node.wait_model_s"] > 0:
                want = start_version + index
                if not self.spin_until(
                        lambda want=want: (self.model_version or 0) >= want,
                        p["node.wait_model_s"]):
                    self.log.warn(f"model version {want} did not arrive within "
                                  f"{p['node.wait_model_s']:g} s; next task runs with version "
                                  f"{self.model_version}")
            traj = self.run_task(index)
            self.pub_traj.publish(self.codec.trajectory_to_msg(traj))
            self.log.info(f"task {index + 1}: {traj.outcome}, T_cpl={traj.t_cpl:.1f} s, "
                          f"model v{traj.meta['model_version']}")
            index += 1
        self.log.info(f"all {index} tasks done")
        if p["node.exit_when_done"]:
            if p["node.wait_model_s"] > 0:
                self.spin_until(lambda: (self.model_version or 0) >= start_version + index,
                                p["node.wait_model_s"])
            return 0
        # stay up (the launcher stops the graph) so late subscribers and the bag get everything
        from peel_msgs_py.runtime import rclpy

        while rclpy.ok():
            rclpy.spin_once(self.node, timeout_sec=0.2)
        return 0

    def close(self) -> None:
        self.env.close()
        self.node.destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``peel_sim_node`` (``--ros-args --params-file ... -p ...``)."""
    from peel_msgs_py.runtime.entry import run_node

    return run_node(NODE_NAME, SimNode, lambda node: node.run(), args)


if __name__ == "__main__":
    sys.exit(main())
