"""Checks of what arrives from the wire, shared by every node and the launcher (no ROS).

Every message a node takes from a topic is checked where it enters: a command, a wrench, a
state sample, a trajectory or a model report holding a non-finite or out-of-limit value is
dropped (or, for a speed command, clamped into the bridge's limits) and counted per topic,
field and action (dropped, clamped) by a :class:`DropLog`, which says when a log line is due:
the first of a kind at once, further ones at most every :data:`LOG_EVERY_S` seconds, each line
with the count so far. Nothing a peer publishes can end a node.

A bridge executes a speed only inside ``[u_min, u_max]`` (:class:`SpeedLimits`); the default is
the Nachi controller's accepted ``V`` range, 0 to 20 mm/s (docs/nachi_protocol.md).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import PeelError
from .params import ParamSpec

#: Seconds between two log lines about drops of the same topic and field.
LOG_EVERY_S = 5.0
#: The Nachi controller's accepted command range, mm/s (``V``, docs/nachi_protocol.md).
CMD_MIN_MMPS, CMD_MAX_MMPS = 0.0, 20.0


def speed_limit_specs(group: str, action: str) -> tuple[ParamSpec, ParamSpec]:
    """The ``<group>.u_min_mmps`` / ``u_max_mmps`` parameters of a bridge: the speeds it
    ``action`` (e.g. "executed", "forwarded as V"), inside the controller's 0-20 mm/s."""
    bounds = {"min": CMD_MIN_MMPS, "max": CMD_MAX_MMPS}
    return (ParamSpec(f"{group}.u_min_mmps", float, CMD_MIN_MMPS,
                      f"lowest speed {action}, mm/s (lower commands are clamped)", **bounds),
            ParamSpec(f"{group}.u_max_mmps", float, CMD_MAX_MMPS,
                      f"highest speed {action}, mm/s (the Nachi controller's limit; higher "
                      "commands are clamped)", **bounds))


def first_nonfinite(values: Mapping[str, float]) -> str | None:
    """The name of the first entry of ``values`` that is not a finite number, else None."""
    for name, value in values.items():
        if not math.isfinite(float(value)):
            return name
    return None


def trajectory_nonfinite(traj: Any, fields: Iterable[str] = ("t", "q", "v", "u", "fx", "fz")
                         ) -> str | None:
    """The first trajectory array among ``fields`` holding a non-finite value, else None."""
    for name in fields:
        if not np.all(np.isfinite(np.asarray(getattr(traj, name), dtype=np.float64))):
            return name
    return None


@dataclass
class DropLog:
    """Counted, rate-limited drops per (topic, field) (module docstring)."""

    every_s: float = LOG_EVERY_S
    clock: Callable[[], float] = time.monotonic
    counts: dict[tuple[str, str, str], int] = field(default_factory=dict)
    _last: dict[tuple[str, str, str], float] = field(default_factory=dict)

    def drop(self, topic: str, name: str, why: str, action: str = "dropped") -> str | None:
        """Count one message of ``topic`` refused (or clamped: ``action``) for its field
        ``name``; the log line when one is due (first time, then at most every ``every_s`` per
        topic, field and action), else None."""
        key = (topic, name, action)
        self.counts[key] = self.counts.get(key, 0) + 1
        now = self.clock()
        if now - self._last.get(key, -math.inf) < self.every_s:
            return None
        self._last[key] = now
        return (f"{action} a {topic} message: {name} {why} "
                f"({self.counts[key]} {action} so far on {topic} for {name})")

    @property
    def total(self) -> int:
        return sum(self.counts.values())


@dataclass(frozen=True)
class SpeedLimits:
    """The speeds a bridge executes, mm/s: ``u_min <= u <= u_max``."""

    u_min_mmps: float = CMD_MIN_MMPS
    u_max_mmps: float = CMD_MAX_MMPS

    def __post_init__(self) -> None:
        lo, hi = self.u_min_mmps, self.u_max_mmps
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise PeelError(f"command limits must be finite with u_min <= u_max, got "
                            f"{lo!r}..{hi!r} mm/s")

    def clamp(self, u_mmps: float) -> float:
        """``u_mmps`` (finite) held inside the limits."""
        return min(max(float(u_mmps), self.u_min_mmps), self.u_max_mmps)

    def describe(self) -> str:
        return f"{self.u_min_mmps:g}-{self.u_max_mmps:g} mm/s"
