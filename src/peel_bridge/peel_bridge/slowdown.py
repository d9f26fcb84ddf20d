"""The bridges' slowdown zone on the measured force, at the sensor rate (docs/planner.md, Eq. M6;
not in the paper). Plain Python, no ROS.

The planner commands a speed every control period (0.5 s); the force sensor is read every
sample (0.1 s). A stick-slip tooth that climbs at 20-25 N/s passes from 12 N to the 20 N
prewarning (section 4.2) inside one control period, before any planner-side rule sees it. So
each plant bridge scales the speed in force at every sample, from that sample's force, as
nav2's collision_monitor scales cmd_vel in its slowdown zone between the controller and the
base (force in place of distance). With F_a,k = |F_a| of the latest sample on axis a in
{RX, RZ}, L = ``lead_samples`` and u_cmd the planner's command in force::

    F_k = max_a (F_a,k + L max(0, F_a,k - F_a,k-1))      (F_a,k-1 = F_a,k at a task's first sample)
    s_k = clip((f_prewarn - F_k) / (f_prewarn - f_s), 0, 1)
    u_k = u_cmd                               F_k <  f_s
    u_k = min(u_cmd, max(u_floor, s_k u_cmd))  F_k >= f_s          (Eq. M6)

u_k is the speed of the next sample. With L = 0, F_k is the latest sample's force; with L > 0
it is that force carried L samples ahead at its last rise (collision_monitor's ``approach``
zone, which slows by the time to collision rather than the distance), so a tooth that climbs
fast is slowed before it reaches f_s. It never raises the command, never slows below u_floor
(the blade keeps moving, as Eq. M4's fallback), reads no model and holds only the previous
sample: as F_k falls below f_s the command is back in force.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from peel_msgs_py.errors import ParameterError
from peel_msgs_py.params import ParamSpec


def slowdown_specs(group: str) -> tuple[ParamSpec, ...]:
    """``<group>.slowdown.*``: Eq. M6's parameters, declared alike by both plant bridges."""
    g = f"{group}.slowdown"
    return (
        ParamSpec(f"{g}.enabled", bool, False,
                  "Eq. M6: scale the speed in force at every sample from that sample's force"),
        ParamSpec(f"{g}.start_n", float, 17.0,
                  "f_s of Eq. M6: max(|F_RX|, |F_RZ|) at which the slowdown starts, N "
                  "(below the prewarning)", min=0.0),
        ParamSpec(f"{g}.floor_mmps", float, 0.5,
                  "u_floor of Eq. M6: the zone never slows the blade below this, mm/s "
                  "(the planner's u_min)", min=0.0, max=20.0),
        ParamSpec(f"{g}.lead_samples", int, 0,
                  "L of Eq. M6: samples ahead each axis's force is carried at its last rise "
                  "(0: the latest sample's force)", min=0, max=5),
    )


@dataclass(frozen=True)
class SlowdownParams:
    """``<group>.slowdown.*`` of a bridge (:func:`slowdown_specs`)."""

    enabled: bool = False
    start_n: float = 17.0
    floor_mmps: float = 0.5
    lead_samples: int = 0

    @classmethod
    def from_params(cls, values: Mapping[str, Any], group: str, prewarn: str) -> SlowdownParams:
        """From a flat parameter dict holding ``<group>.slowdown.*`` and the prewarning under
        the name ``prewarn``; with the zone enabled, a start_n at or above the prewarning is
        refused by name (a disabled zone leaves the prewarning free to go below f_s)."""
        g = f"{group}.slowdown."
        enabled = bool(values[g + "enabled"])
        start, f_prewarn = float(values[g + "start_n"]), float(values[prewarn])
        if enabled and start >= f_prewarn:
            raise ParameterError(f"parameter '{g}start_n' = {start!r} must be below "
                                 f"'{prewarn}' = {f_prewarn!r} (Eq. M6)")
        return cls(enabled, start, float(values[g + "floor_mmps"]), int(values[g + "lead_samples"]))

    def zone(self, f_prewarn_n: float) -> SlowdownZone:
        """A fresh zone under the prewarning ``f_prewarn_n``, N."""
        return SlowdownZone(self.enabled, self.start_n, float(f_prewarn_n), self.floor_mmps,
                            self.lead_samples)


@dataclass
class SlowdownZone:
    """Eq. M6 (module docstring) for one task, with what it did (:meth:`as_dict`)."""

    enabled: bool
    start_n: float
    f_prewarn_n: float
    floor_mmps: float
    lead_samples: int = 0
    samples: int = 0
    samples_slowed: int = 0
    min_scale: float = 1.0
    _force: float = field(default=0.0, repr=False)
    _last: tuple[float, float] | None = field(default=None, repr=False)

    def reset(self) -> None:
        """A new task: no sample measured yet, nothing counted."""
        self.samples = self.samples_slowed = 0
        self.min_scale, self._force, self._last = 1.0, 0.0, None

    def measured(self, fx: float, fz: float) -> None:
        """The latest sample's forces, N: F_k of Eq. M6 (carried ``lead_samples`` ahead)."""
        now = (abs(float(fx)), abs(float(fz)))
        last = self._last if self._last is not None else now
        self._force = max(f + self.lead_samples * max(0.0, f - p) for f, p in zip(now, last, strict=True))
        self._last = now

    def scale(self) -> float:
        """s_k of Eq. M6 for the latest sample (1 below f_s or when disabled)."""
        if not self.enabled or self._force < self.start_n:
            return 1.0
        s = (self.f_prewarn_n - self._force) / (self.f_prewarn_n - self.start_n)
        return min(1.0, max(0.0, s))

    def limit(self, u_cmd: float) -> float:
        """u_k of Eq. M6 for the command ``u_cmd`` after the latest sample, mm/s (nothing counted)."""
        s = self.scale()
        return u_cmd if s >= 1.0 else min(u_cmd, max(self.floor_mmps, s * u_cmd))

    def speed(self, u_cmd: float) -> float:
        """:meth:`limit`, counted as the speed of one sample."""
        self.samples += 1
        u = self.limit(u_cmd)
        if u < u_cmd:
            self.samples_slowed += 1
            self.min_scale = min(self.min_scale, u / u_cmd if u_cmd > 0 else 1.0)
        return u

    def as_dict(self) -> dict[str, Any]:
        """What the trajectory's meta and the bridges' logs report."""
        return {"enabled": self.enabled, "start_n": self.start_n,
                "lead_samples": self.lead_samples, "samples": self.samples,
                "samples_slowed": self.samples_slowed, "min_scale": round(self.min_scale, 4)}


def slowdown_line(task: int, stats: dict[str, Any]) -> str | None:
    """The task's log line about Eq. M6 (None when the zone slowed nothing)."""
    if not stats.get("samples_slowed"):
        return None
    ahead = f", {stats['lead_samples']} ahead" if stats.get("lead_samples") else ""
    return (f"task {task}: slowdown zone (Eq. M6, from {stats['start_n']:g} N{ahead}) slowed "
            f"{stats['samples_slowed']} of {stats['samples']} samples, down to "
            f"{stats['min_scale']:.2f} of the command")


def log_slowdown(logger: Any, task: int, stats: dict[str, Any]) -> None:
    """Log :func:`slowdown_line` on ``logger`` (an rclpy logger or anything with ``info``)."""
    line = slowdown_line(task, stats)
    if line is not None:
        logger.info(line)
