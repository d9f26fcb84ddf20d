"""QoS profiles with rclpy's names and values, and their mapping onto Cyclone DDS policies.

Mirrors ``rclpy.qos`` (Jazzy): :class:`QoSProfile` with ``history``, ``depth``, ``reliability``,
``durability``, ``deadline``, ``lifespan``, ``liveliness`` and the preset profiles. The DDS
mapping follows ``rmw_cyclonedds_cpp``'s ``create_readwrite_qos``: reliable -> RELIABLE with an
infinite max blocking time, keep-last depth, transient-local durability, and XCDR1 data
representation (the encoding ROS 2 uses on the wire).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from cyclonedds.core import Policy, Qos
from cyclonedds.util import duration

from ...errors import PeelError


class HistoryPolicy(IntEnum):
    """rmw history policy values."""

    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class ReliabilityPolicy(IntEnum):
    """rmw reliability policy values."""

    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class DurabilityPolicy(IntEnum):
    """rmw durability policy values."""

    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class LivelinessPolicy(IntEnum):
    """rmw liveliness policy values."""

    SYSTEM_DEFAULT = 0
    AUTOMATIC = 1
    MANUAL_BY_TOPIC = 3
    UNKNOWN = 4
    BEST_AVAILABLE = 5


@dataclass(frozen=True)
class QoSDuration:
    """A QoS duration (seconds); infinite or unset is ``0`` as in rmw."""

    sec: float = 0.0

    @property
    def nanoseconds(self) -> int:
        return round(self.sec * 1e9)


def _as_seconds(value: Any) -> float:
    if value is None:
        return 0.0
    if hasattr(value, "nanoseconds"):
        return value.nanoseconds / 1e9
    return float(value)


@dataclass
class QoSProfile:
    """rclpy-compatible QoS profile; ``QoSProfile(depth=10)`` is reliable, volatile, keep-last."""

    history: HistoryPolicy = HistoryPolicy.KEEP_LAST
    depth: int = 10
    reliability: ReliabilityPolicy = ReliabilityPolicy.RELIABLE
    durability: DurabilityPolicy = DurabilityPolicy.VOLATILE
    deadline: Any = field(default=None)
    lifespan: Any = field(default=None)
    liveliness: LivelinessPolicy = LivelinessPolicy.SYSTEM_DEFAULT
    liveliness_lease_duration: Any = field(default=None)
    avoid_ros_namespace_conventions: bool = False

    def __post_init__(self) -> None:
        self.history = HistoryPolicy(self.history)
        self.reliability = ReliabilityPolicy(self.reliability)
        self.durability = DurabilityPolicy(self.durability)
        self.liveliness = LivelinessPolicy(self.liveliness)
        if isinstance(self.depth, bool) or not isinstance(self.depth, int) or self.depth < 0:
            raise PeelError(f"QoS depth must be a non-negative integer, got {self.depth!r}")
        if self.history == HistoryPolicy.KEEP_LAST and self.depth == 0:
            raise PeelError("QoS depth must be > 0 with history KEEP_LAST")


def as_profile(qos: QoSProfile | int) -> QoSProfile:
    """rclpy accepts an int (the keep-last depth) wherever a profile is expected."""
    if isinstance(qos, QoSProfile):
        return qos
    if isinstance(qos, int) and not isinstance(qos, bool):
        return QoSProfile(depth=qos)
    raise PeelError(f"qos_profile must be a QoSProfile or an int depth, got {qos!r}")


def to_dds(profile: QoSProfile, user_data: bytes | None = None, *, writer: bool) -> Qos:
    """The Cyclone DDS QoS for a reader or writer with this profile (rmw_cyclonedds mapping)."""
    policies: list[Any] = []
    if profile.history == HistoryPolicy.KEEP_ALL:
        policies.append(Policy.History.KeepAll)
    else:
        policies.append(Policy.History.KeepLast(max(1, profile.depth)))
    if profile.reliability == ReliabilityPolicy.BEST_EFFORT:
        policies.append(Policy.Reliability.BestEffort)
    else:
        policies.append(Policy.Reliability.Reliable(duration(infinite=True)))
    if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL:
        policies.append(Policy.Durability.TransientLocal)
    else:
        policies.append(Policy.Durability.Volatile)
    for name, pol in (("deadline", Policy.Deadline), ("lifespan", Policy.Lifespan)):
        sec = _as_seconds(getattr(profile, name))
        if sec > 0 and math.isfinite(sec):
            policies.append(pol(duration(seconds=sec)))
    lease = _as_seconds(profile.liveliness_lease_duration)
    if profile.liveliness == LivelinessPolicy.MANUAL_BY_TOPIC:
        policies.append(
            Policy.Liveliness.ManualByTopic(duration(seconds=lease) if lease > 0 else duration(infinite=True))
        )
    elif lease > 0:
        policies.append(Policy.Liveliness.Automatic(duration(seconds=lease)))
    # XCDR1 is what ROS 2 writes; readers also accept XCDR2 from other DDS stacks.
    if writer:
        policies.append(Policy.DataRepresentation(use_cdrv0_representation=True))
    else:
        policies.append(Policy.DataRepresentation(use_cdrv0_representation=True, use_xcdrv2_representation=True))
    if user_data:
        policies.append(Policy.Userdata(user_data))
    return Qos(*policies)


# Preset profiles, as in rclpy.qos / rmw/qos_profiles.h
qos_profile_system_default = QoSProfile(depth=10)
qos_profile_sensor_data = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
qos_profile_services_default = QoSProfile(depth=10)
qos_profile_parameters = QoSProfile(depth=1000)
qos_profile_parameter_events = QoSProfile(depth=1000)
qos_profile_clock = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)


class QoSPresetProfiles:
    """Named presets (``QoSPresetProfiles.SENSOR_DATA.value``) as in rclpy."""

    class _P:
        def __init__(self, profile: QoSProfile) -> None:
            self.value = profile

    SYSTEM_DEFAULT = _P(qos_profile_system_default)
    SENSOR_DATA = _P(qos_profile_sensor_data)
    SERVICES_DEFAULT = _P(qos_profile_services_default)
    PARAMETERS = _P(qos_profile_parameters)
    PARAMETER_EVENTS = _P(qos_profile_parameter_events)


__all__ = [
    "DurabilityPolicy",
    "HistoryPolicy",
    "LivelinessPolicy",
    "QoSDuration",
    "QoSPresetProfiles",
    "QoSProfile",
    "ReliabilityPolicy",
    "as_profile",
    "qos_profile_clock",
    "qos_profile_parameter_events",
    "qos_profile_parameters",
    "qos_profile_sensor_data",
    "qos_profile_services_default",
    "qos_profile_system_default",
    "to_dds",
]
