"""Parameters of the Nachi bridge (config/peel_nachi_bridge.yaml), validated with named errors.

Three groups, units in the names: ``link.*`` (where the controller is, how long to wait for it,
the reconnect backoff), ``safety.*`` (the link's safety rules, docs/nachi_protocol.md) and
``node.*`` (the task sequence, the same names and meanings as peel_sim_node's). A wrong type, an
out-of-range value or an inconsistent pair raises :class:`~peel_msgs_py.errors.ParameterError`
naming the parameter; the node prints it as one line and exits 2.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from peel_msgs_py.errors import ParameterError
from peel_msgs_py.params import ParamSpec, load_node_params, validate

NODE_NAME = "peel_nachi_bridge"

LINK_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("link.host", str, "127.0.0.1", "controller address (IPv4 or host name)"),
    ParamSpec("link.port", int, 48100, "controller TCP port", min=1, max=65535),
    ParamSpec("link.connect_timeout_s", float, 2.0, "wall s for the TCP connect", min=0.01),
    ParamSpec("link.hello_timeout_s", float, 2.0, "wall s for HELLO after the connect", min=0.01),
    ParamSpec("link.reply_timeout_s", float, 1.0, "wall s for OK START and PONG", min=0.01),
    ParamSpec("link.ping_interval_s", float, 1.0, "wall s between PINGs while idle", min=0.05),
    ParamSpec("link.backoff_initial_s", float, 0.2, "first reconnect delay, wall s", min=0.01),
    ParamSpec("link.backoff_max_s", float, 5.0, "longest reconnect delay, wall s", min=0.01),
    ParamSpec("link.backoff_factor", float, 2.0, "delay growth per failed attempt", min=1.0),
    ParamSpec("link.give_up_s", float, 0.0,
              "wall s without a controller (while a task waits) before the node exits 1; "
              "0 = never", min=0.0),
)

SAFETY_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("safety.f_prewarn_n", float, 20.0,
              "prewarning on |F_RX| or |F_RZ|, N (section 4.2): STOP within the same sample",
              min=0.1),
    ParamSpec("safety.stall_timeout_s", float, 0.3,
              "wall s without a sample during a task before STOP", min=0.01),
    ParamSpec("safety.bad_line_limit", int, 3,
              "consecutive malformed / oversize / non-finite lines that stop a task", min=1),
    ParamSpec("safety.stop_timeout_s", float, 2.0,
              "wall s for DONE after STOP before the link is closed", min=0.01),
)

NODE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("node.tasks", int, 3, "consecutive tasks to run; 0 = until stopped", min=0),
    ParamSpec("node.task_slot_s", float, 100.0,
              "ROS time reserved per task, s (> the controller's t_max)", min=1.0),
    ParamSpec("node.wait_model_s", float, 120.0,
              "wall s to wait for the learner's new model between tasks; 0 = do not", min=0.0),
    ParamSpec("node.wait_planner_s", float, 120.0,
              "wall s to wait for the planner's /peel/model_version and the readers before "
              "task 1", min=0.0),
    ParamSpec("node.min_subscribers", int, 1,
              "wait for this many subscribers of /peel/wrench before task 1", min=0),
    ParamSpec("node.min_traj_subscribers", int, 1,
              "wait for this many subscribers of /peel/trajectory before task 1", min=0),
    ParamSpec("node.exit_when_done", bool, False,
              "exit after the last task (and its model update); for ros2 launch"),
)

SPECS: tuple[ParamSpec, ...] = LINK_SPECS + SAFETY_SPECS + NODE_SPECS
GROUPS = ("link", "safety", "node")


@dataclass(frozen=True)
class LinkParams:
    host: str
    port: int
    connect_timeout_s: float
    hello_timeout_s: float
    reply_timeout_s: float
    ping_interval_s: float
    backoff_initial_s: float
    backoff_max_s: float
    backoff_factor: float
    give_up_s: float


@dataclass(frozen=True)
class SafetyParams:
    f_prewarn_n: float
    stall_timeout_s: float
    bad_line_limit: int
    stop_timeout_s: float


@dataclass(frozen=True)
class NodeParams:
    tasks: int
    task_slot_s: float
    wait_model_s: float
    wait_planner_s: float
    min_subscribers: int
    min_traj_subscribers: int
    exit_when_done: bool


@dataclass(frozen=True)
class BridgeConfig:
    link: LinkParams
    safety: SafetyParams
    node: NodeParams

    @classmethod
    def from_params(cls, flat: Mapping[str, Any]) -> BridgeConfig:
        """Validate the ``link.*``, ``safety.*`` and ``node.*`` entries of a flat dict of dotted
        names (an unknown name in these groups is refused). Other names are the other nodes'
        (``task.*`` from a shared ``/**`` section, as ``peel graph --params`` passes one file to
        every node) or rclpy's own (``use_sim_time``) and are ignored."""
        values = validate(SPECS, {k: v for k, v in flat.items() if k.split(".")[0] in GROUPS})
        host = values["link.host"]
        if not host or any(c.isspace() for c in host):
            raise ParameterError(f"parameter 'link.host' = {host!r} must be a non-empty address")
        if values["link.backoff_max_s"] < values["link.backoff_initial_s"]:
            raise ParameterError(
                f"parameter 'link.backoff_max_s' = {values['link.backoff_max_s']!r} is below "
                f"'link.backoff_initial_s' = {values['link.backoff_initial_s']!r}")

        def group(name: str, kind: type) -> Any:
            prefix = name + "."
            return kind(**{k[len(prefix):]: v for k, v in values.items() if k.startswith(prefix)})

        return cls(group("link", LinkParams), group("safety", SafetyParams),
                   group("node", NodeParams))


def load_config(overrides: Mapping[str, Any] | None = None) -> BridgeConfig:
    """The shipped config/peel_nachi_bridge.yaml with ``overrides`` (dotted names) on top."""
    values = load_node_params(NODE_NAME)
    values.update(overrides or {})
    return BridgeConfig.from_params(values)
