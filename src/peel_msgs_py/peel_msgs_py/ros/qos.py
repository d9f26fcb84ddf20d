"""QoS: the topic table's plain :class:`~peel_msgs_py.qos.QosSpec` as an rclpy
``QoSProfile``, and an rclpy profile (a publisher's, from its endpoint info) as the
``offered_qos_profiles`` entry rosbag2 writes into a bag.
"""

from __future__ import annotations

from typing import Any

from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

from ..qos import KEEP_LAST, RELIABLE, TRANSIENT_LOCAL, QosSpec

#: rmw's "infinite" duration as rosbag2 (Jazzy) writes it.
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


def to_profile(spec: QosSpec) -> QoSProfile:
    """The rclpy profile of a spec (deadline, lifespan, liveliness at their defaults)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST if spec.history == KEEP_LAST else HistoryPolicy.KEEP_ALL,
        depth=spec.depth,
        reliability=(ReliabilityPolicy.RELIABLE if spec.reliability == RELIABLE
                     else ReliabilityPolicy.BEST_EFFORT),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if spec.durability == TRANSIENT_LOCAL
                    else DurabilityPolicy.VOLATILE),
    )


def _duration(d: Duration) -> dict[str, int]:
    ns = d.nanoseconds
    if ns <= 0 or ns >= 9223372036854775807:
        return dict(_INFINITE)
    sec, nsec = divmod(ns, 1_000_000_000)
    return {"sec": int(sec), "nsec": int(nsec)}


def _policy(value: Any) -> str:
    name = getattr(value, "name", str(value)).lower()
    return "unknown" if name == "unknown" else name.replace("system_default", "system_default")


def profile_to_bag(profile: QoSProfile) -> dict[str, Any]:
    """``offered_qos_profiles`` entry (rosbag2 metadata version 9) of an offered profile.

    A profile from endpoint info reports the history as unknown (DDS does not announce it);
    it is written as rosbag2 writes it then: ``history: unknown``, ``depth: 0``.
    """
    return {
        "history": _policy(profile.history),
        "depth": int(profile.depth),
        "reliability": _policy(profile.reliability),
        "durability": _policy(profile.durability),
        "deadline": _duration(profile.deadline),
        "lifespan": _duration(profile.lifespan),
        "liveliness": _policy(profile.liveliness if profile.liveliness is not None
                              else LivelinessPolicy.AUTOMATIC),
        "liveliness_lease_duration": _duration(profile.liveliness_lease_duration),
        "avoid_ros_namespace_conventions": bool(profile.avoid_ros_namespace_conventions),
    }
