"""Publishers, subscriptions and timers of the embedded runtime (rclpy's interface).

A subscription's DDS reader is drained by the executor one sample per ``spin_once``, so the
callback runs in the spinning thread, as with rclpy's single-threaded executor. Timers follow
rcl: a timer is ready when its clock reaches ``next_call``; after a call ``next_call`` moves on
by one period, skipping periods that were missed entirely; a clock jumping backwards (a new
simulation) restarts the timer from the new time.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from cyclonedds.core import DDSException, InstanceState, ReadCondition, SampleState, ViewState
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

from ...errors import PeelError
from . import cdr
from .context import DdsEntity
from .qos import QoSProfile, to_dds
from .time import Clock, ClockType

if TYPE_CHECKING:
    from .node import Node

ANY_STATE = SampleState.Any | ViewState.Any | InstanceState.Any


def check_message_class(msg_type: Any) -> None:
    if not isinstance(msg_type, type) or not hasattr(msg_type, "__rostype__"):
        raise PeelError(f"{msg_type!r} is not a message class of peel_msgs_py.runtime.msg")


class Publisher(DdsEntity):
    """``rclpy.publisher.Publisher``."""

    def __init__(self, node: Node, msg_type: type[Any], topic: str, qos: QoSProfile) -> None:
        self.msg_type = msg_type
        self.topic = topic
        self.qos_profile = qos
        self._node = node
        dds_topic = node.context.topic("rt" + topic, msg_type)
        try:
            self._writer = DataWriter(node.context.participant, dds_topic, qos=to_dds(qos, writer=True))
        except DDSException as exc:
            raise PeelError(f"cannot create publisher on {topic}: {exc}") from None

    @property
    def topic_name(self) -> str:
        return self.topic

    def publish(self, msg: Any) -> None:
        if isinstance(msg, (bytes, bytearray, memoryview)):
            msg = cdr.deserialize(msg, self.msg_type)
        if not isinstance(msg, self.msg_type):
            raise TypeError(
                f"expected {self.msg_type.__rostype__}, got {type(msg).__name__} on {self.topic}"
            )
        self._writer.write(msg)

    def get_subscription_count(self) -> int:
        return len(self._writer.get_matched_subscriptions())

    def wait_for_acks(self, timeout_sec: float = 1.0) -> bool:
        from cyclonedds.util import duration

        return bool(self._writer.wait_for_acks(duration(seconds=timeout_sec)))

    def _dds_handles(self) -> tuple[Any, ...]:
        return (self._writer,)


class Subscription(DdsEntity):
    """``rclpy.subscription.Subscription``; ``raw=True`` hands the callback CDR bytes."""

    def __init__(
        self,
        node: Node,
        msg_type: type[Any],
        topic: str,
        callback: Callable[[Any], Any],
        qos: QoSProfile,
        raw: bool = False,
    ) -> None:
        self.msg_type = msg_type
        self.topic = topic
        self.callback = callback
        self.qos_profile = qos
        self.raw = raw
        self._node = node
        dds_topic = node.context.topic("rt" + topic, msg_type)
        try:
            self._reader = DataReader(
                node.context.participant, dds_topic, qos=to_dds(qos, writer=False)
            )
            self._cond = ReadCondition(self._reader, ANY_STATE)
        except DDSException as exc:
            raise PeelError(f"cannot create subscription on {topic}: {exc}") from None

    @property
    def topic_name(self) -> str:
        return self.topic

    def get_publisher_count(self) -> int:
        return len(self._reader.get_matched_publications())

    def _take_work(self) -> Callable[[], None] | None:
        while samples := self._reader.take(N=1):
            sample = samples[0]
            info = getattr(sample, "sample_info", None)
            if info is None or not info.valid_data:
                continue
            if hasattr(sample, "sample_info"):
                del sample.sample_info
            msg = cdr.serialize(sample) if self.raw else sample
            return lambda: self.callback(msg)
        return None

    def _dds_handles(self) -> tuple[Any, ...]:
        return (self._cond, self._reader,)


class Timer:
    """``rclpy.timer.Timer`` on a node clock (ROS time by default, sim time when enabled)."""

    def __init__(
        self,
        callback: Callable[[], Any] | None,
        period_ns: int,
        clock: Clock,
        node: Node | None = None,
        autostart: bool = True,
    ) -> None:
        if period_ns < 0:
            raise PeelError(f"timer period must not be negative, got {period_ns} ns")
        self.callback = callback
        self._period = int(period_ns)
        self._clock = clock
        self._node = node
        self._canceled = not autostart
        now = clock.now().nanoseconds
        self._last = now
        self._next = now + self._period

    @property
    def timer_period_ns(self) -> int:
        return self._period

    @timer_period_ns.setter
    def timer_period_ns(self, value: int) -> None:
        self._period = int(value)
        self.reset()

    @property
    def clock(self) -> Clock:
        return self._clock

    def cancel(self) -> None:
        self._canceled = True

    def is_canceled(self) -> bool:
        return self._canceled

    def reset(self) -> None:
        now = self._clock.now().nanoseconds
        self._canceled = False
        self._last = now
        self._next = now + self._period

    def _now(self) -> int:
        now = self._clock.now().nanoseconds
        if now < self._last:  # clock jumped backwards: restart from the new time
            self._last = now
            self._next = now + self._period
        return now

    def is_ready(self) -> bool:
        return not self._canceled and self._now() >= self._next

    def time_until_next_call(self) -> int | None:
        if self._canceled:
            return None
        return self._next - self._now()

    def time_since_last_call(self) -> int:
        return self._now() - self._last

    @property
    def _uses_sim_time(self) -> bool:
        return self._clock.clock_type == ClockType.ROS_TIME and self._clock.ros_time_is_active

    def _take_work(self) -> Callable[[], None] | None:
        if not self.is_ready():
            return None
        now = self._now()
        self._last = now
        if self._period == 0:
            self._next = now
        else:
            self._next += self._period
            if self._next < now:
                self._next += ((now - self._next) // self._period + 1) * self._period
        cb = self.callback
        return (lambda: cb()) if cb is not None else (lambda: None)

    def destroy(self) -> None:
        self._canceled = True
        if self._node is not None:
            self._node._destroy_entity(self)

    def _delete(self) -> None:
        self._canceled = True
