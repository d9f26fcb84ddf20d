"""The three state topics a control sample is built from (``/peel/wrench``, ``/peel/twist``,
``/peel/pose``; docs/interfaces.md), read the same way by every node that plans or learns from
the running peel (the planner, the learner's in-peel step).

:class:`StateTopics` subscribes to them with the table's QoS, checks each message (every value
finite, a task in ``header.frame_id``) and hands on its parts in the algorithms' units
(:mod:`peel_msgs_py.units`, the one place of the conversion): ``fx_n``, ``fz_n`` (N),
``v_mmps`` (mm/s), ``q_mm`` (mm). A refused message is dropped and logged once per topic and
field (:class:`~peel_msgs_py.wire.DropLog`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.subscription import Subscription

from .. import codec, topics
from ..errors import PeelError
from ..units import m_to_mm, mps_to_mmps
from ..wire import DropLog
from .messages import stamp_ns

#: A sample part -> the wire field it comes from (named in a drop's log line).
WIRE_FIELD = {"fx_n": "wrench.force.x", "fz_n": "wrench.force.z", "v_mmps": "twist.linear.x",
              "q_mm": "pose.position.x"}

#: ``(stamp ns, task, parts)`` of one checked message.
PartHandler = Callable[[int, int, dict[str, float]], None]


class StateTopics:
    """The state subscriptions of ``node``: each checked message's parts go to ``on_part``
    while ``wanted()`` (module docstring)."""

    def __init__(self, node: Any, on_part: PartHandler,
                 wanted: Callable[[], bool] = lambda: True) -> None:
        self.node, self.on_part, self.wanted = node, on_part, wanted
        self.drops = DropLog()

    def subscribe(self) -> list[Subscription]:
        """The three subscriptions (the caller owns them)."""
        qos = topics.qos_profile
        return [self.node.create_subscription(kind, name, callback, qos(name, subscriber=True))
                for kind, name, callback in ((WrenchStamped, topics.WRENCH, self.on_wrench),
                                             (TwistStamped, topics.TWIST, self.on_twist),
                                             (PoseStamped, topics.POSE, self.on_pose))]

    def on_wrench(self, msg: WrenchStamped) -> None:
        self.take(msg, topics.WRENCH, fx_n=msg.wrench.force.x, fz_n=msg.wrench.force.z)

    def on_twist(self, msg: TwistStamped) -> None:
        self.take(msg, topics.TWIST, v_mmps=mps_to_mmps(msg.twist.linear.x))

    def on_pose(self, msg: PoseStamped) -> None:
        self.take(msg, topics.POSE, q_mm=m_to_mm(msg.pose.position.x))

    def take(self, msg: Any, topic: str, **parts: float) -> None:
        """Check one message and hand its parts on, or drop it with one logged line."""
        if not self.wanted():
            return
        bad = next((k for k, v in parts.items() if not math.isfinite(v)), None)
        if bad is not None:
            self.drop(topic, WIRE_FIELD[bad], f"is not finite ({parts[bad]!r})")
            return
        try:
            task = codec.task_from_frame_id(msg.header.frame_id)
        except PeelError as exc:
            self.drop(topic, "header.frame_id", f"is bad: {exc}")
            return
        self.on_part(stamp_ns(msg.header.stamp), task, parts)

    def drop(self, topic: str, field: str, why: str) -> None:
        line = self.drops.drop(topic, field, why)
        if line is not None:
            self.node.get_logger().warn(line)
