"""``peel_sim_node``: the simulator / plant bridge node of the graph (docs/graph.md).

A managed node (:class:`~peel_msgs_py.ros.lifecycle.ManagedNode`, docs/graph.md "Lifecycle"):
configure checks the parameters and builds the simulator and the topics; activate runs the task
loop; deactivate stops it (no task starts, no command is executed, a running task ends
``aborted``); cleanup closes the simulator. Active, it runs ``node.tasks`` consecutive tasks
(:class:`~peel_sim_node.lockstep.TaskSequence` on :class:`~peel_sim_node.env.PeelEnv`, ``sim``
or ``plant``) and owns the clock: every sample (dt = 0.1 s, section 4.2) it publishes ``/clock``
and the measured state on ``/peel/wrench``, ``/peel/twist``, ``/peel/pose`` (SI, stamped with
the sample's ROS time, frame ``peel_task_<k>``); each control sample waits for the
``/peel/cmd_vel`` that answers its stamp (lockstep); each finished task goes out on
``/peel/trajectory``. A wall-clock timer re-sends an unanswered sample every
``node.cmd_timeout_s`` and aborts the task after ``node.cmd_give_up_s``. Which task runs when
(the graph's readers before task 1; between tasks, ``node.wait_model_s`` for the learner's
update of the last task, Algorithm 2 line 20) is the ROS-free
:class:`~peel_bridge.loop.TaskLoop`, and the publishers, the command subscription and model
following (``/peel/model_info``, ``/peel/model_update``) are
:class:`~peel_bridge.plant_node.PlantTopics`, both shared with ``peel_nachi_bridge``.
``node.effects`` adds user effects (``module:function``,
:func:`~peel_sim_node.effects.load_effects`) to the plant; a name that does not import is
refused (exit 2) before any topic exists. A command is executed only inside ``[node.u_min_mmps,
node.u_max_mmps]`` (default the Nachi controller's 0-20 mm/s,
:class:`~peel_msgs_py.wire.SpeedLimits`): a faster or negative one is clamped, a non-finite one
dropped, both counted and logged (:class:`~peel_msgs_py.wire.DropLog`) and counted in the
trajectory's meta (``cmd_limits_mmps``, ``cmd_clamped``, ``cmd_dropped``).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from geometry_msgs.msg import TwistStamped
from rclpy.clock import Clock, ClockType

from peel_bridge.loop import LoopParams, TaskLoop
from peel_bridge.plant_node import PlantTopics
from peel_bridge.slowdown import log_slowdown
from peel_msgs_py import topics
from peel_msgs_py.diagnostics import Status
from peel_msgs_py.errors import PeelError
from peel_msgs_py.lifecycle import AUTOSTART
from peel_msgs_py.ros.diagnostics import publish_diagnostics
from peel_msgs_py.ros.lifecycle import ManagedNode
from peel_msgs_py.ros.main import run_node
from peel_msgs_py.ros.messages import stamp_ns
from peel_msgs_py.ros.parameters import NamedRefusals, declare
from peel_msgs_py.task import Sample
from peel_msgs_py.units import mps_to_mmps
from peel_msgs_py.wire import SpeedLimits

from .config import SimConfig
from .effects import load_effects
from .health import sim_status
from .lockstep import TaskSequence
from .pacing import Pace
from .parameters import LIBRARY_SPECS, NODE_NAME, SPECS

#: Period (s, wall clock) of the timer that drives waiting, re-sending and giving up.
TICK_S = 0.05


def library_params(values: dict[str, Any]) -> dict[str, Any]:
    """The declared values the library reads (not the node's, nor rclpy's own)."""
    names = {s.name for s in LIBRARY_SPECS}
    return {k: v for k, v in values.items() if k in names}


def speed_limits(p: dict[str, Any]) -> SpeedLimits:
    """``[node.u_min_mmps, node.u_max_mmps]``, refused with both names when they do not fit."""
    try:
        return SpeedLimits(p["node.u_min_mmps"], p["node.u_max_mmps"])
    except PeelError as exc:
        raise PeelError(f"parameters 'node.u_min_mmps', 'node.u_max_mmps': {exc}") from None


class SimNode(NamedRefusals, ManagedNode):
    """A :class:`TaskSequence` in lockstep with the planner, driven by a :class:`TaskLoop`, as
    a managed node: configure builds the simulator, activate runs the tasks (docs/graph.md
    "Lifecycle")."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        values = declare(self, SPECS)
        self.p = {k: v for k, v in values.items() if k.startswith("node.")}
        self.seq: TaskSequence | None = None  # None while unconfigured
        self.done, self.exit_status = False, 0
        self.last_outcome: str | None = None
        publish_diagnostics(self, self.diagnostics)
        self.autostart(self.p[AUTOSTART.name])

    def setup(self) -> None:
        """configure: the parameters checked, the effects imported, the simulator built."""
        values = {n: p.value for n, p in self.get_parameters_by_prefix("").items()}
        self.p = {k: v for k, v in values.items() if k.startswith("node.")}
        self.limits = speed_limits(self.p)
        cfg = SimConfig.from_params(library_params(values))
        effects = load_effects(self.p["node.effects"])
        self.seq = TaskSequence(cfg, source=self.p["node.source"], seed=self.p["node.seed"],
                                task_slot_s=self.p["node.task_slot_s"], effects=effects)
        self.plant = PlantTopics(self, self.p["node.learner_node"], self.on_cmd)
        self.loop = TaskLoop(LoopParams.from_params(self.p), self.on_log)
        self.pace = Pace(self.p["node.real_time_factor"])
        self.clamped = self.dropped = 0  # commands of the running task
        self.sent = self.asked = time.monotonic()  # last publication; first sending of the waiting one
        self.own(self.create_timer(TICK_S, self.on_tick,
                                   clock=Clock(clock_type=ClockType.STEADY_TIME)))
        self.get_logger().info(f"{self.p['node.source']} ready: {self.p['node.tasks']} tasks, "
                               f"seed {self.p['node.seed']}, commands limited to "
                               f"{self.limits.describe()}")

    def stop(self) -> None:
        """deactivate: no task starts, no command is executed; a running task ends aborted."""
        if self.loop.phase == "running":
            self.get_logger().warning("deactivated during a task: the task is aborted")
            self.pace.clear()
            self.end_task("aborted")

    def release(self) -> None:
        """cleanup / shutdown: the simulator closed, the topics destroyed."""
        if self.seq is not None:
            self.seq.close()
        self.seq = None
        if getattr(self, "plant", None) is not None:
            self.plant.destroy()
        self.plant = None

    # -- callbacks ---------------------------------------------------------------------------
    def on_cmd(self, msg: TwistStamped) -> None:
        """A command answering the waiting sample, executed inside the limits (only while
        active: an inactive bridge forwards nothing to the simulator)."""
        if not self.active:
            return
        u = float(mps_to_mmps(msg.twist.linear.x))
        if not math.isfinite(u):
            self.dropped += 1
            self.plant.log_drop(self.plant.drops.drop(topics.CMD_VEL, "twist.linear.x",
                                                      f"is not finite ({u!r})"))
            return
        held = self.limits.clamp(u)
        samples = self.seq.apply(stamp_ns(msg.header.stamp), held)
        if samples is None:
            return
        if held != u:
            self.clamped += 1
            self.plant.log_drop(self.plant.drops.drop(
                topics.CMD_VEL, "twist.linear.x", f"= {u:g} mm/s is outside "
                f"{self.limits.describe()}; executed {held:g} mm/s", action="clamped"))
        self.pace.hold(samples)
        self.release_due()

    def release_due(self) -> None:
        """Publish the held samples that are due (:class:`Pace`); once the last is out, the
        lockstep waits for its answer, or the ended task is closed."""
        if not self.pace.waiting:
            return
        now = time.monotonic()
        for s in self.pace.release(now):
            self.publish(s)
        if self.pace.waiting:
            return
        self.asked = now
        if self.seq.ended:
            self.end_task(None)

    def on_tick(self) -> None:
        """Active: start the next task when the task loop says so, or watch the lockstep."""
        if not self.active:
            return
        index = self.loop.poll(time.monotonic(), self.plant.readiness())
        if index is not None:
            self.start_task(index)
        elif self.loop.phase == "running" and self.pace.waiting:
            self.release_due()
        elif self.loop.phase == "running":
            self.check_lockstep()
        self.done = self.loop.exit_now

    def on_log(self, level: str, text: str) -> None:
        """The task loop's lines (one call site per severity: rclpy's logger wants that)."""
        if level == "warn":
            self.get_logger().warning(text)
        else:
            self.get_logger().info(text)

    def diagnostics(self) -> list[Status]:
        """The lockstep's health (:func:`~peel_sim_node.health.sim_status`), 1 Hz; the
        lifecycle state while not active."""
        if self.seq is None:
            return self.lifecycle_status()
        phase = self.loop.phase
        waiting = time.monotonic() - self.asked if phase == "running" else None
        return [*self.lifecycle_status(),
                sim_status(self.p["node.source"], phase, self.loop.ended_tasks,
                           self.p["node.tasks"], self.plant.model_version, waiting,
                           self.p["node.cmd_timeout_s"], self.last_outcome)]

    # -- tasks -------------------------------------------------------------------------------
    def start_task(self, index: int) -> None:
        self.plant.task_started(index)
        first = self.seq.start(index)
        self.publish(first)
        self.asked = time.monotonic()
        self.pace.start(first, self.asked)

    def check_lockstep(self) -> None:
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
        index = self.seq.index
        traj = self.seq.finish({**self.plant.graph_meta(index),
                                "cmd_limits_mmps": [self.limits.u_min_mmps,
                                                    self.limits.u_max_mmps],
                                "cmd_clamped": self.clamped, "cmd_dropped": self.dropped},
                               outcome)
        self.clamped = self.dropped = 0
        log_slowdown(self.get_logger(), index + 1, traj.meta["slowdown"])
        self.plant.publish_trajectory(traj, index + 1)
        self.last_outcome = traj.outcome
        self.loop.task_ended(time.monotonic(), index)

    def publish(self, s: Sample) -> None:
        self.plant.publish_sample(s)
        self.sent = time.monotonic()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``peel_sim_node`` (``--ros-args --params-file ... -p ...``)."""
    return run_node(NODE_NAME, SimNode, args)


if __name__ == "__main__":
    sys.exit(main())
