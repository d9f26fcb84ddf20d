"""Node health as plain data: what each node publishes on ``/diagnostics`` (docs/interfaces.md).

A node's report is a list of :class:`Status` (one ``diagnostic_msgs/msg/DiagnosticStatus`` each:
name, level, message, hardware id, key values); :mod:`peel_msgs_py.ros.diagnostics` converts it
and publishes it as a ``DiagnosticArray`` once a second of wall time. The level of a status is
the worst of its checks, and its message names the checks at that level, so what a health
monitor (``rqt_runtime_monitor``, Foxglove's diagnostics panel) shows first is the reason.
This module imports no ROS; the per-node functions live beside each node (``<pkg>.health``).
"""

from __future__ import annotations

import statistics
import threading
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass

#: Levels of ``diagnostic_msgs/msg/DiagnosticStatus`` (STALE = 3 is the monitor's, not ours).
OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}
#: Publication rate of every node's report, Hz of wall time (steady clock).
RATE_HZ = 1.0
#: Wall s a fault counter that rose keeps its status at WARN (:class:`RecentRises`).
HOLD_S = 30.0

Check = tuple[int, str]  # (level, what is wrong), one per condition found


@dataclass(frozen=True)
class Status:
    """One ``DiagnosticStatus``: ``values`` are its key values, already text."""

    name: str
    level: int
    message: str
    hardware_id: str = ""
    values: tuple[tuple[str, str], ...] = ()

    def value(self, key: str) -> str:
        """The value of ``key``; ``KeyError`` naming it when absent."""
        for k, v in self.values:
            if k == key:
                return v
        raise KeyError(key)


def text(value: object) -> str:
    """A key value as text: ``-`` for None, 6 significant digits for a float."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def make_status(name: str, hardware_id: str, checks: list[Check], values: Mapping[str, object],
                ok_message: str = "ok") -> Status:
    """The status of ``checks`` (the worst level wins; its texts are the message)."""
    level = max((lvl for lvl, _ in checks), default=OK)
    message = "; ".join(msg for lvl, msg in checks if lvl == level) if level > OK else ok_message
    return Status(name, level, message, hardware_id,
                  tuple((k, text(v)) for k, v in values.items()))


class DurationWindow:
    """The last ``size`` durations (s) of a repeated step, and how many exceeded ``budget_s``.

    Thread-safe: one thread adds, another reads.
    """

    def __init__(self, budget_s: float | None = None, size: int = 20) -> None:
        self.budget_s = budget_s
        self.recent: deque[float] = deque(maxlen=size)
        self.count = 0
        self.over = 0  # over the budget, all time
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self.recent.append(float(seconds))
            self.count += 1
            if self.budget_s is not None and seconds > self.budget_s:
                self.over += 1

    def summary(self) -> tuple[float | None, float | None, int]:
        """(median, max, number over the budget) of the window; None before the first."""
        with self._lock:
            window = list(self.recent)
        if not window:
            return None, None, 0
        budget = self.budget_s
        over = sum(s > budget for s in window) if budget is not None else 0
        return statistics.median(window), max(window), over

    @property
    def last(self) -> float | None:
        with self._lock:
            return self.recent[-1] if self.recent else None


class RecentRises:
    """Which fault counters rose within the last ``hold_s`` (wall s, the caller's clock)."""

    def __init__(self, hold_s: float = HOLD_S) -> None:
        self.hold_s = hold_s
        self.seen: dict[str, int] = {}
        self.rose_at: dict[str, float] = {}

    def update(self, counts: Mapping[str, int], now: float) -> set[str]:
        for name, count in counts.items():
            if count > self.seen.get(name, 0):
                self.rose_at[name] = now
            self.seen[name] = count
        return {n for n, t in self.rose_at.items() if now - t <= self.hold_s}


def ms(seconds: float | None) -> float | None:
    """Milliseconds of ``seconds`` (None stays None), for key values."""
    return None if seconds is None else 1e3 * seconds
