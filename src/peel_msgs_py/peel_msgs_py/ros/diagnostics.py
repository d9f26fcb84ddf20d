"""``/diagnostics``: a node's :class:`~peel_msgs_py.diagnostics.Status` list as
``diagnostic_msgs/msg/DiagnosticArray``, published once a second of wall time.

The timer runs on the steady clock, not on ROS time: the graph runs in lockstep on simulated
time (12-28x the wall clock during a task, and no ``/clock`` at all while it waits or stalls),
and a health report must keep coming exactly when the simulated clock stands still. The header
stamp is the node's ROS time (simulated time under ``use_sim_time``), as every other stamp.
"""

from __future__ import annotations

from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.publisher import Publisher

from .. import topics
from ..diagnostics import ERROR, RATE_HZ, Status


def status_msg(s: Status) -> DiagnosticStatus:
    """One status on the wire."""
    return DiagnosticStatus(level=bytes([s.level]), name=s.name, message=s.message,
                            hardware_id=s.hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in s.values])


def publish_diagnostics(node: Node, report: Callable[[], list[Status]]) -> Publisher:
    """Publish ``report()`` on ``/diagnostics`` at :data:`RATE_HZ` (wall clock). A report that
    raises becomes one ERROR status naming the exception: the node goes on."""
    pub = node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                topics.qos_profile(topics.DIAGNOSTICS))

    def tick() -> None:
        try:
            statuses = report()
        except Exception as exc:  # a health report never takes the node down
            statuses = [Status(f"{node.get_name()}: diagnostics", ERROR,
                               f"report failed: {type(exc).__name__}: {exc}", node.get_name())]
        msg = DiagnosticArray(status=[status_msg(s) for s in statuses])
        msg.header.stamp = node.get_clock().now().to_msg()
        pub.publish(msg)

    node.create_timer(1.0 / RATE_HZ, tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
    return pub
