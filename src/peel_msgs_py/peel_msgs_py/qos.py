"""QoS profiles of peel as plain, hashable data: :class:`QosSpec` and the profiles of the topic
table (:mod:`peel_msgs_py.topics`). No ROS here: :mod:`peel_msgs_py.ros.qos` turns a spec into
rclpy's ``QoSProfile``, :meth:`QosSpec.to_bag` into the ``offered_qos_profiles`` entry rosbag2
writes. Why each topic has its profile: :mod:`peel_msgs_py.topics`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .errors import PeelError

KEEP_LAST = "keep_last"
KEEP_ALL = "keep_all"
RELIABLE = "reliable"
BEST_EFFORT = "best_effort"
VOLATILE = "volatile"
TRANSIENT_LOCAL = "transient_local"

#: rmw's "infinite" duration as rosbag2 (Jazzy) writes it in ``offered_qos_profiles``.
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


@dataclass(frozen=True)
class QosSpec:
    """A QoS profile as plain data: history, depth, reliability, durability.

    Deadline, lifespan and liveliness stay at the ROS defaults (infinite / automatic).
    """

    history: str = KEEP_LAST
    depth: int = 10
    reliability: str = RELIABLE
    durability: str = VOLATILE

    def __post_init__(self) -> None:
        if self.history not in (KEEP_LAST, KEEP_ALL):
            raise PeelError(f"QoS history must be keep_last or keep_all, got {self.history!r}")
        if self.reliability not in (RELIABLE, BEST_EFFORT):
            raise PeelError(
                f"QoS reliability must be reliable or best_effort, got {self.reliability!r}"
            )
        if self.durability not in (VOLATILE, TRANSIENT_LOCAL):
            raise PeelError(
                f"QoS durability must be volatile or transient_local, got {self.durability!r}"
            )
        if not isinstance(self.depth, int) or isinstance(self.depth, bool) or self.depth < 0:
            raise PeelError(f"QoS depth must be a non-negative int, got {self.depth!r}")

    def to_bag(self) -> dict[str, Any]:
        """The ``offered_qos_profiles`` entry as rosbag2 metadata version 9 writes it."""
        return {
            "history": self.history,
            "depth": self.depth,
            "reliability": self.reliability,
            "durability": self.durability,
            "deadline": dict(_INFINITE),
            "lifespan": dict(_INFINITE),
            "liveliness": "automatic",
            "liveliness_lease_duration": dict(_INFINITE),
            "avoid_ros_namespace_conventions": False,
        }

    def describe(self) -> str:
        """Short human form for tables: ``reliable, keep_last 10, volatile``."""
        hist = f"keep_last {self.depth}" if self.history == KEEP_LAST else "keep_all"
        return f"{self.reliability}, {hist}, {self.durability}"


#: Streams sampled by the simulator / plant and the planner's command.
STREAM_QOS = QosSpec(KEEP_LAST, 10, RELIABLE, VOLATILE)
#: One finished trajectory per task; each must arrive, and a learner that (re)starts late gets
#: the recent ones (docs/fleet.md, "The learner dies and comes back").
TRAJECTORY_QOS = QosSpec(KEEP_LAST, 10, RELIABLE, TRANSIENT_LOCAL)
#: Latched state: the current value reaches subscribers that join later.
LATCHED_QOS = QosSpec(KEEP_LAST, 1, RELIABLE, TRANSIENT_LOCAL)
#: The planner's record of each model it swapped in: each must arrive, and a reader that
#: discovery matched late still gets the last 16, newest last (a keep-last-1 writer hands such a
#: reader only the current record, and the swaps before it are lost to it).
RECORD_QOS = QosSpec(KEEP_LAST, 16, RELIABLE, TRANSIENT_LOCAL)
#: The learner's per-task reports: each must arrive, a late reader gets the recent ones.
REPORT_QOS = QosSpec(KEEP_LAST, 10, RELIABLE, TRANSIENT_LOCAL)
#: ``/clock`` as published (reliable: matches reliable and best-effort subscribers).
CLOCK_QOS = QosSpec(KEEP_LAST, 1, RELIABLE, VOLATILE)
#: ``/clock`` as subscribed (best effort: matches any publisher, as rclpy's time source).
CLOCK_SUB_QOS = QosSpec(KEEP_LAST, 1, BEST_EFFORT, VOLATILE)
