"""ROS time: ``Time``, ``Duration``, ``Clock`` and ``ClockType`` with rclpy's interface.

A node's clock is a ROS clock: system time, or -- with parameter ``use_sim_time`` true -- the
last time received on ``/clock`` (``rosgraph_msgs/msg/Clock``), starting at zero until the first
message arrives, as rcl does.
"""

from __future__ import annotations

import threading
import time as _time
from collections.abc import Callable
from enum import IntEnum
from typing import Any

from ...errors import PeelError

_NS = 1_000_000_000


class ClockType(IntEnum):
    """rcl clock types."""

    UNINITIALIZED = 0
    ROS_TIME = 1
    SYSTEM_TIME = 2
    STEADY_TIME = 3


class Duration:
    """A span of time in integer nanoseconds (``rclpy.duration.Duration``)."""

    __slots__ = ("nanoseconds",)

    def __init__(self, *, seconds: float = 0, nanoseconds: int = 0) -> None:
        self.nanoseconds = round(seconds * _NS) + int(nanoseconds)

    def to_msg(self) -> Any:
        from .messages import Duration as DurationMsg

        sec, nsec = divmod(self.nanoseconds, _NS)
        return DurationMsg(sec=sec, nanosec=nsec)

    @classmethod
    def from_msg(cls, msg: Any) -> Duration:
        return cls(nanoseconds=msg.sec * _NS + msg.nanosec)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Duration) and other.nanoseconds == self.nanoseconds

    def __lt__(self, other: Duration) -> bool:
        return self.nanoseconds < other.nanoseconds

    def __le__(self, other: Duration) -> bool:
        return self.nanoseconds <= other.nanoseconds

    def __hash__(self) -> int:
        return hash(self.nanoseconds)

    def __repr__(self) -> str:
        return f"Duration(nanoseconds={self.nanoseconds})"


class Time:
    """A point in time of a clock, integer nanoseconds (``rclpy.time.Time``)."""

    __slots__ = ("clock_type", "nanoseconds")

    def __init__(
        self,
        *,
        seconds: float = 0,
        nanoseconds: int = 0,
        clock_type: ClockType = ClockType.SYSTEM_TIME,
    ) -> None:
        ns = round(seconds * _NS) + int(nanoseconds)
        if ns < 0:
            raise PeelError(f"time must not be negative, got {ns} ns")
        self.nanoseconds = ns
        self.clock_type = ClockType(clock_type)

    def seconds_nanoseconds(self) -> tuple[int, int]:
        return divmod(self.nanoseconds, _NS)

    def to_msg(self) -> Any:
        from .messages import Time as TimeMsg

        sec, nsec = divmod(self.nanoseconds, _NS)
        return TimeMsg(sec=sec, nanosec=nsec)

    @classmethod
    def from_msg(cls, msg: Any, clock_type: ClockType = ClockType.ROS_TIME) -> Time:
        return cls(nanoseconds=msg.sec * _NS + msg.nanosec, clock_type=clock_type)

    def __add__(self, other: Duration) -> Time:
        return Time(nanoseconds=self.nanoseconds + other.nanoseconds, clock_type=self.clock_type)

    def __sub__(self, other: Time | Duration) -> Any:
        if isinstance(other, Time):
            return Duration(nanoseconds=self.nanoseconds - other.nanoseconds)
        return Time(nanoseconds=self.nanoseconds - other.nanoseconds, clock_type=self.clock_type)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Time) and other.nanoseconds == self.nanoseconds

    def __lt__(self, other: Time) -> bool:
        return self.nanoseconds < other.nanoseconds

    def __le__(self, other: Time) -> bool:
        return self.nanoseconds <= other.nanoseconds

    def __hash__(self) -> int:
        return hash(self.nanoseconds)

    def __repr__(self) -> str:
        return f"Time(nanoseconds={self.nanoseconds}, clock_type={self.clock_type.name})"


class Clock:
    """A clock: ``now()`` -> :class:`Time`. ROS clocks follow ``/clock`` when sim time is on."""

    def __init__(self, *, clock_type: ClockType = ClockType.SYSTEM_TIME) -> None:
        self.clock_type = ClockType(clock_type)
        self._lock = threading.Lock()
        self._sim_active = False
        self._sim_ns = 0
        self._on_change: list[Callable[[int, int], None]] = []

    @property
    def ros_time_is_active(self) -> bool:
        return self._sim_active

    def now(self) -> Time:
        if self.clock_type == ClockType.STEADY_TIME:
            return Time(nanoseconds=_time.monotonic_ns(), clock_type=self.clock_type)
        with self._lock:
            if self.clock_type == ClockType.ROS_TIME and self._sim_active:
                return Time(nanoseconds=self._sim_ns, clock_type=self.clock_type)
        return Time(nanoseconds=_time.time_ns(), clock_type=self.clock_type)

    def now_ns(self) -> int:
        return self.now().nanoseconds

    # --- simulated time (called by the node's /clock subscription) ---
    def _set_ros_time_override_active(self, active: bool) -> None:
        with self._lock:
            self._sim_active = active
            self._sim_ns = 0

    def _set_sim_time(self, ns: int) -> None:
        with self._lock:
            old = self._sim_ns
            self._sim_ns = int(ns)
        for cb in list(self._on_change):
            cb(old, int(ns))

    def _add_change_callback(self, cb: Callable[[int, int], None]) -> None:
        self._on_change.append(cb)

    def __repr__(self) -> str:
        return f"Clock(clock_type={self.clock_type.name})"


class ROSClock(Clock):
    """A ROS_TIME clock (``rclpy.clock.ROSClock``)."""

    def __init__(self) -> None:
        super().__init__(clock_type=ClockType.ROS_TIME)
