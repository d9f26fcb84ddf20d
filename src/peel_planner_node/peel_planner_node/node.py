"""``peel_planner_node``: OL-MPPI as a ROS 2 node (docs/graph.md).

A managed node (:class:`~peel_msgs_py.ros.lifecycle.ManagedNode`, docs/graph.md "Lifecycle"):
configure checks the parameters and loads, probes and warms up the model; activate lets it plan
and publish; deactivate stops both; cleanup drops the model and the topics. While active it
subscribes the measured state (``/peel/wrench``, ``/peel/twist``, ``/peel/pose``, SI), plans
once per control period of ROS time (:class:`~peel_planner_node.control_loop.ControlLoop`,
Algorithm 2) and publishes ``/peel/cmd_vel`` stamped with the sample it answers (lockstep).
Holds the forward model; the model swap is its standard parameter service: setting
``model.path`` runs :func:`~peel_planner_node.model_check.validate_model` in the on-set callback
and either swaps the model in between two planning cycles (callbacks of one executor thread) or
refuses with the reason, keeping the old model. Versions come from a
:class:`~peel_model.versions.ModelLedger` (0 = the starting model, +1 per accepted swap,
whoever asked for it and whatever the file is called); the active version goes out on
``/peel/model_version`` (Int64, transient local) and, with the model's identity (SHA-256,
producer and task of a learner update), on ``/peel/model_info`` (JSON, transient local). The
task's guard of the force limit goes out on ``/peel/planner_safety`` (JSON) before each command.
A state message with a non-finite value is dropped where it enters, counted and logged
(:class:`~peel_msgs_py.wire.DropLog`); the sample it belonged to is not planned on.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import torch
from geometry_msgs.msg import TwistStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter
from std_msgs.msg import Int64, String

from peel_model.versions import ModelLedger
from peel_msgs_py import codec, topics
from peel_msgs_py.diagnostics import Status
from peel_msgs_py.errors import PeelError
from peel_msgs_py.lifecycle import AUTOSTART, ConfigureError
from peel_msgs_py.ros.diagnostics import publish_diagnostics
from peel_msgs_py.ros.lifecycle import ManagedNode
from peel_msgs_py.ros.main import run_node
from peel_msgs_py.ros.messages import stamp
from peel_msgs_py.ros.parameters import NamedRefusals, declare
from peel_msgs_py.ros.state_topics import StateTopics
from peel_msgs_py.units import mmps_to_mps

from .config import PlannerConfig
from .control_loop import Answer, ControlLoop, StateAssembler
from .dynamics import learned_dynamics
from .health import peak_force, plan_costs, planner_status
from .model_check import resolve_model_path, validate_model
from .parameters import MODEL_PATH, NODE_NAME, SPECS


class PlannerNode(NamedRefusals, ManagedNode):
    """Subscriptions, the command publisher and the model swap around a :class:`ControlLoop`,
    as a managed node: configure loads and warms up the model, activate starts the commands
    (docs/graph.md "Lifecycle")."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        self.values = declare(self, SPECS)
        self.loop: ControlLoop | None = None  # None while unconfigured
        self.refusal: str | None = None  # the last model swap's refusal, until one is accepted
        self.refusals = 0
        self.add_on_set_parameters_callback(self.on_set_parameters)
        publish_diagnostics(self, self.diagnostics)
        self.autostart(self.values[AUTOSTART.name])

    def setup(self) -> None:
        """configure: the parameters checked, the model loaded, probed and warmed up, the
        topics made."""
        self.values = {n: p.value for n, p in self.get_parameters_by_prefix("").items()}
        torch.set_num_threads(self.values["node.threads"])
        self.cfg = PlannerConfig.from_params(self.values)
        self.dt_s = float(self.cfg.cost.dt_s)
        path = resolve_model_path(self.values[MODEL_PATH])
        try:
            pred = validate_model(path, None, self.values["node.probe_batch"], None)
            self.ledger = ModelLedger.start(path)  # version 0
        except PeelError as exc:
            raise ConfigureError(f"parameter '{MODEL_PATH}': {exc}") from None
        self.h = int(pred.h)
        loop = ControlLoop(self.cfg, learned_dynamics(pred, self.cfg.dynamics),
                           self.values["node.seed"])
        warm_s = loop.warm_up(self.h)
        self.parts = StateAssembler()
        self.state_topics = StateTopics(self, self.on_part,
                                        lambda: self.active and self.loop is not None)
        qos = topics.qos_profile
        self.pub_cmd = self.own(self.create_lifecycle_publisher(TwistStamped, topics.CMD_VEL,
                                                                qos(topics.CMD_VEL)))
        self.pub_version = self.own(self.create_publisher(Int64, topics.MODEL_VERSION,
                                                          qos(topics.MODEL_VERSION)))
        self.pub_info = self.own(self.create_publisher(String, topics.MODEL_INFO,
                                                       qos(topics.MODEL_INFO)))
        self.pub_safety = self.own(self.create_publisher(String, topics.PLANNER_SAFETY,
                                                         qos(topics.PLANNER_SAFETY)))
        for sub in self.state_topics.subscribe():
            self.own(sub)
        self.loop = loop
        self.get_logger().info(f"planner ready: model v{self.version} ({path.name}), "
                               f"N={self.cfg.mppi.n_samples}, H={self.cfg.mppi.horizon}, "
                               f"{loop.planner.dynamics.describe()}; warm-up plan {warm_s * 1e3:.0f} ms")

    def start(self) -> None:
        """activate: announce the model once the command's readers are matched; plan."""
        self.waiting_since = time.monotonic()
        self.announcer = self.own(self.create_timer(
            0.05, self.announce, clock=Clock(clock_type=ClockType.STEADY_TIME)))

    def stop(self) -> None:
        """deactivate: no more commands (the lifecycle publisher is disabled, no plan runs)."""
        self.announcer.cancel()

    def release(self) -> None:
        """cleanup / shutdown: the model and the control loop go (the topics with :meth:`own`)."""
        self.loop = None

    def announce(self) -> None:
        """Publish the model version once the command's readers are matched: the simulator
        starts on it, so no command is published before its readers (the recorder) are there."""
        want = self.values["node.min_cmd_subscribers"]
        waited = time.monotonic() - self.waiting_since
        if self.pub_cmd.get_subscription_count() < want and \
                waited < self.values["node.wait_subscribers_s"]:
            return
        if self.pub_cmd.get_subscription_count() < want:
            self.get_logger().warn(f"fewer than {want} readers of {topics.CMD_VEL}; going on")
        self.announcer.cancel()  # destroyed at the release (own)
        self.publish_version()
        self.get_logger().info(f"model v{self.version} announced after {waited:.2f} s "
                               f"({self.pub_cmd.get_subscription_count()} readers of "
                               f"{topics.CMD_VEL})")

    @property
    def version(self) -> int:
        """The version of the model planning now."""
        return self.ledger.latest.version

    def publish_version(self) -> None:
        """The active model on ``/peel/model_version`` and, with its identity, ``/peel/model_info``."""
        self.pub_version.publish(Int64(data=self.version))
        self.pub_info.publish(String(data=self.ledger.latest.to_json()))

    def diagnostics(self) -> list[Status]:
        """The planner's health (:func:`~peel_planner_node.health.planner_status`), 1 Hz;
        the lifecycle state while not active."""
        if self.loop is None:
            return self.lifecycle_status()
        loop = self.loop
        return [*self.lifecycle_status(),
                planner_status(loop.latency, self.cfg, self.ledger.latest, self.refusal,
                               self.refusals, peak_force(loop.rows), loop.margin_n,
                               plan_costs(loop.planner.last))]

    # -- state -------------------------------------------------------------------------------
    def on_part(self, stamp_ns: int, task: int, parts: dict[str, float]) -> None:
        """One checked part of a state sample (:class:`StateTopics`: an inactive planner gets
        none); a whole sample is planned for."""
        assert self.loop is not None
        sample = self.parts.add(stamp_ns, task, **parts)
        if sample is not None:
            answer = self.loop.on_sample(sample)
            if answer is not None:
                self.publish_cmd(answer)

    def publish_cmd(self, a: Answer) -> None:
        report = self.loop.safety_report()
        if report is not None:  # before the command it belongs to: a bridge has it at task end
            self.pub_safety.publish(String(data=report))
        msg = TwistStamped()
        msg.header.stamp, msg.header.frame_id = stamp(a.stamp_ns), codec.task_frame_id(a.task)
        msg.twist.linear.x = mmps_to_mps(a.u_mmps)
        self.pub_cmd.publish(msg)
        if a.note:
            self.get_logger().info(a.note)

    # -- parameters: the model swap and the run-time settings -----------------------------------
    def on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate before anything changes; refuse with the reason (the old values stay).
        Unconfigured, a value is only kept (checked by its descriptor): configure reads it."""
        if self.loop is None:
            return SetParametersResult(successful=True)
        model = [p for p in params if p.name == MODEL_PATH]
        others = {p.name: p.value for p in params if p.name != MODEL_PATH}
        try:
            cfg = PlannerConfig.from_params({**self.values, **others}) if others else None
            checked = self.check_model(str(model[-1].value)) if model else None
        except PeelError as exc:
            self.get_logger().warn(str(exc))
            if model:
                self.refusal, self.refusals = str(exc), self.refusals + 1
            return SetParametersResult(successful=False, reason=str(exc))
        if cfg is not None:  # from the next task on
            self.values.update(others)
            self.cfg = self.loop.cfg = cfg
        if checked is not None:
            self.swap(*checked, Path(str(model[-1].value)))
        return SetParametersResult(successful=True)

    def check_model(self, value: str) -> tuple[Any, tuple[str, str | None, int | None]]:
        """The predictor and its identity (SHA-256, producer, task), or PeelError."""
        from peel_model.versions import identify

        if not value:
            raise PeelError("model swap refused: model.path must be a non-empty string")
        try:
            pred = validate_model(Path(value), self.loop.probe_rows(),
                                  self.values["node.probe_batch"], self.h)
            return pred, identify(value)
        except PeelError as exc:
            raise PeelError(f"model swap refused: {exc}") from None
        except Exception as exc:  # anything else a broken file can raise
            raise PeelError(f"model swap refused: {type(exc).__name__}: {exc}") from None

    def swap(self, pred: Any, identity: tuple[str, str | None, int | None], path: Path) -> None:
        """Plan with ``pred`` from the next cycle on; publish its version and identity."""
        self.loop.set_dynamics(learned_dynamics(pred, self.cfg.dynamics))
        rec = self.ledger.accept(path, identity)
        self.refusal = None
        self.publish_version()
        origin = f"{rec.producer}'s update after task {rec.task}" if rec.producer else "outside"
        self.get_logger().info(f"model swap: now v{rec.version} ({path.name}, {origin})")


def main(args: list[str] | None = None) -> int:
    """Console entry point ``peel_planner_node`` (``--ros-args --params-file ... -p ...``)."""
    return run_node(NODE_NAME, PlannerNode, args)


if __name__ == "__main__":
    sys.exit(main())
