"""The Nachi bridge's parameters (config/peel_nachi_bridge.yaml; the specs in
:mod:`.parameters`) as typed groups, validated with named errors.

Three groups, units in the names: ``link.*`` (where the controller is, how long to wait for it,
the reconnect backoff), ``safety.*`` (the link's safety rules, docs/nachi_protocol.md) and
``node.*`` (the task sequence, the same names and meanings as peel_sim_node's). A wrong type, an
out-of-range value or an inconsistent pair (a backoff maximum below its start, an empty host)
raises :class:`~peel_msgs_py.errors.ParameterError` naming the parameter; the node prints it as
one line and exits 2.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from peel_bridge.slowdown import SlowdownParams
from peel_msgs_py.errors import ParameterError
from peel_msgs_py.params import load_node_params, validate
from peel_msgs_py.wire import CMD_MAX_MMPS, CMD_MIN_MMPS

from .parameters import GROUPS, LINK_SPECS, NODE_NAME, NODE_SPECS, SAFETY_SPECS

#: The bridge's own parameters (not ``use_sim_time``, which rclpy declares).
BRIDGE_SPECS = (*LINK_SPECS, *SAFETY_SPECS, *NODE_SPECS)


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
    configure_timeout_s: float = 10.0


@dataclass(frozen=True)
class SafetyParams:
    f_prewarn_n: float
    stall_timeout_s: float
    bad_line_limit: int
    stop_timeout_s: float
    u_min_mmps: float = CMD_MIN_MMPS
    u_max_mmps: float = CMD_MAX_MMPS
    slowdown: SlowdownParams = field(default_factory=SlowdownParams)  # Eq. M6 (peel_bridge.slowdown)


@dataclass(frozen=True)
class NodeParams:
    tasks: int
    task_slot_s: float
    wait_model_s: float
    wait_planner_s: float
    min_subscribers: int
    min_traj_subscribers: int
    learner_node: str
    exit_when_done: bool
    autostart: bool = True


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
        own = {k: v for k, v in flat.items() if k.split(".")[0] in GROUPS}
        values = validate(BRIDGE_SPECS, own)
        host = values["link.host"]
        if not host or any(c.isspace() for c in host):
            raise ParameterError(f"parameter 'link.host' = {host!r} must be a non-empty address")
        if values["link.backoff_max_s"] < values["link.backoff_initial_s"]:
            raise ParameterError(
                f"parameter 'link.backoff_max_s' = {values['link.backoff_max_s']!r} is below "
                f"'link.backoff_initial_s' = {values['link.backoff_initial_s']!r}")

        if values["safety.u_max_mmps"] < values["safety.u_min_mmps"]:
            raise ParameterError(
                f"parameter 'safety.u_max_mmps' = {values['safety.u_max_mmps']!r} is below "
                f"'safety.u_min_mmps' = {values['safety.u_min_mmps']!r}")

        slowdown = SlowdownParams.from_params(values, "safety", "safety.f_prewarn_n")
        values = {k: v for k, v in values.items() if not k.startswith("safety.slowdown.")}

        def group(name: str, kind: type, **extra: Any) -> Any:
            prefix = name + "."
            return kind(**{k[len(prefix):]: v for k, v in values.items() if k.startswith(prefix)},
                        **extra)

        return cls(group("link", LinkParams), group("safety", SafetyParams, slowdown=slowdown),
                   group("node", NodeParams))


def load_config(overrides: Mapping[str, Any] | None = None) -> BridgeConfig:
    """The shipped config/peel_nachi_bridge.yaml with ``overrides`` (dotted names) on top."""
    values = load_node_params(NODE_NAME)
    values.update(overrides or {})
    return BridgeConfig.from_params(values)
