"""Physical effect terms: the candidate library of ``peel residual`` and the compensation terms.

A *family* is a physical effect with a meaning and a physical variable (viscous drag: the speed
v; position-periodic adhesion: the position q; vacuum loss: the time t in the task, ...). A
*candidate* is a family with its shape parameter fixed (the period lambda = 6 mm, the time
constant tau = 5 s), i.e. a fixed set of basis functions phi_k. A *term* is a candidate on one
channel with fitted coefficients c_k. Force terms add to a force channel, velocity terms to the
robot's speed response:

* force channels ``fx``/``fz`` (N): F = f_theta(x with the terms removed, v) + sum_k c_k phi_k
  (:class:`~peel_model.compensated.CompensatedPredictor`); phi_k is a function of a
  sample's row (q mm, v mm/s, t s, the previous row's v, the other channel's force);
* velocity channel ``v`` (mm/s): v_{k+1} = u_k + sum_k c_k phi_k(u_k, v_k), the correction of
  Eq. 2's mean v = u that the planner assumes (actuator lag, scale, offset).

Terms are data: a checkpoint stores ``family``, ``param`` and the coefficients; the basis
functions are looked up here by family name, never loaded from the file (docs/residual.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from peel_msgs_py.errors import PeelError

FORCE_CHANNELS: tuple[str, ...] = ("fx", "fz")
VELOCITY_CHANNEL = "v"
CHANNELS: tuple[str, ...] = (*FORCE_CHANNELS, VELOCITY_CHANNEL)


@dataclass
class Rows:
    """Per-row variables of a sequence of samples, tensors of shape ``[..., L]``.

    ``t`` is None when the sample times are unknown (then time terms contribute nothing);
    ``f`` holds the two force channels ``[..., L, 2]`` (only the cross-talk family reads it);
    ``u`` is the command over the next sample (only the velocity families read it).
    """

    q: Tensor
    v: Tensor
    t: Tensor | None = None
    f: Tensor | None = None
    u: Tensor | None = None

    @property
    def dv(self) -> Tensor:
        """v_j - v_{j-1} along the rows (0 for the first row)."""
        return torch.cat([torch.zeros_like(self.v[..., :1]), self.v[..., 1:] - self.v[..., :-1]],
                         dim=-1)


Basis = Callable[[Rows, float, int], list[Tensor]]


@dataclass(frozen=True)
class Family:
    """A physical effect: what it means, its variable and its basis functions phi_k."""

    name: str
    label: str
    meaning: str
    variable: str  # the physical variable the figure plots the residual against
    channels: tuple[str, ...]
    param: str | None  # name (with unit) of its shape parameter, or None
    expressions: Callable[[float], tuple[str, ...]]
    basis: Basis  # (rows, param, channel index) -> [phi_k of shape [..., L]]
    uses_time: bool = False
    uses_force: bool = False


def _pos(x: Tensor) -> Tensor:
    return torch.clamp(x, min=0.0)


def _time(r: Rows) -> Tensor:
    if r.t is None:
        raise PeelError("a time term needs the sample times")
    return _pos(r.t)


def _other_force(r: Rows, ch: int) -> Tensor:
    if r.f is None:
        raise PeelError("the cross-talk term needs the force channels")
    return r.f[..., 1 - ch]


def _command(r: Rows) -> Tensor:
    if r.u is None:
        raise PeelError("a velocity term needs the commands")
    return r.u


def _fmt(x: float) -> str:
    return f"{x:g}"


_FORCE_FAMILIES: tuple[Family, ...] = (
    Family("sensor_offset", "sensor offset / constant extra load",
           "a constant force: zero error of the force sensor, or a constant extra load",
           "t_s", FORCE_CHANNELS, None, lambda p: ("1",),
           lambda r, p, c: [torch.ones_like(r.q)]),
    Family("viscous_drag", "viscous drag",
           "force proportional to the speed (a viscous film, damping)",
           "v_mmps", FORCE_CHANNELS, None, lambda p: ("v",), lambda r, p, c: [r.v]),
    Family("quadratic_drag", "quadratic drag",
           "force growing with the square of the speed (rate hardening)",
           "v_mmps", FORCE_CHANNELS, None, lambda p: ("v*|v|",),
           lambda r, p, c: [r.v * r.v.abs()]),
    Family("coulomb_friction", "Coulomb friction",
           "a constant friction force once the blade moves, none at rest",
           "v_mmps", FORCE_CHANNELS, "v0_mmps", lambda p: (f"tanh(v/{_fmt(p)})",),
           lambda r, p, c: [torch.tanh(r.v / p)]),
    Family("stribeck_friction", "Stribeck friction",
           "breakaway friction that falls off with the speed",
           "v_mmps", FORCE_CHANNELS, "vs_mmps", lambda p: (f"exp(-(v/{_fmt(p)})^2)",),
           lambda r, p, c: [torch.exp(-(r.v / p) ** 2)]),
    Family("periodic_adhesion", "position-periodic adhesion",
           "adhesion varying periodically along the path (pad texture, grooves)",
           "q_mm", FORCE_CHANNELS, "lambda_mm",
           lambda p: (f"sin(2*pi*q/{_fmt(p)})", f"cos(2*pi*q/{_fmt(p)})"),
           lambda r, p, c: [torch.sin(2 * math.pi * r.q / p), torch.cos(2 * math.pi * r.q / p)]),
    Family("near_start_hold", "hold-down near C",
           "extra hold-down decaying with the distance from C (residual vacuum)",
           "q_mm", FORCE_CHANNELS, "length_mm", lambda p: (f"exp(-q/{_fmt(p)})",),
           lambda r, p, c: [torch.exp(-_pos(r.q) / p)]),
    Family("position_trend", "load changing along the path",
           "force changing linearly with the position (peeled length, pad wear)",
           "q_mm", FORCE_CHANNELS, None, lambda p: ("q",), lambda r, p, c: [r.q]),
    Family("decay_in_time", "decay within a task",
           "a load decaying with the time in the task (vacuum loss, warm-up)",
           "t_s", FORCE_CHANNELS, "tau_s", lambda p: (f"exp(-t/{_fmt(p)})",),
           lambda r, p, c: [torch.exp(-_time(r) / p)], uses_time=True),
    Family("drift_in_time", "drift within a task",
           "a force growing linearly with the time in the task (sensor drift, leak)",
           "t_s", FORCE_CHANNELS, None, lambda p: ("t",), lambda r, p, c: [_time(r)],
           uses_time=True),
    Family("hysteresis", "hysteresis",
           "force depending on the direction of the last speed change (loading vs unloading)",
           "dv_mmps", FORCE_CHANNELS, "dv0_mmps", lambda p: (f"tanh(dv/{_fmt(p)})",),
           lambda r, p, c: [torch.tanh(r.dv / p)]),
    Family("cross_talk", "cross-talk between the force channels",
           "the channel reads a share of the other channel's force (sensor cross-talk)",
           "f_other_n", FORCE_CHANNELS, None, lambda p: ("F_other",),
           lambda r, p, c: [_other_force(r, c)], uses_force=True),
)

_VELOCITY_FAMILIES: tuple[Family, ...] = (
    Family("actuator_lag", "actuator lag",
           "the robot's speed follows the command with a first-order lag",
           "v_minus_u_mmps", (VELOCITY_CHANNEL,), None, lambda p: ("v_k - u_k",),
           lambda r, p, c: [r.v - _command(r)]),
    Family("speed_scale", "speed scale error",
           "the robot moves at a fixed multiple of the command (axis calibration, slip)",
           "u_mmps", (VELOCITY_CHANNEL,), None, lambda p: ("u_k",),
           lambda r, p, c: [_command(r)]),
    Family("speed_offset", "speed offset",
           "a constant speed added to the command", "u_mmps", (VELOCITY_CHANNEL,), None,
           lambda p: ("1",), lambda r, p, c: [torch.ones_like(_command(r))]),
)

#: Every family by name.
FAMILIES: dict[str, Family] = {f.name: f for f in (*_FORCE_FAMILIES, *_VELOCITY_FAMILIES)}


@dataclass(frozen=True)
class Candidate:
    """A family with its shape parameter fixed: a fixed set of basis functions."""

    family: str
    param: float | None = None

    def __post_init__(self) -> None:
        fam = FAMILIES.get(self.family)
        if fam is None:
            raise PeelError(f"unknown effect family {self.family!r} (known: "
                            f"{', '.join(FAMILIES)})")
        if (fam.param is None) != (self.param is None):
            raise PeelError(f"effect family {self.family!r} takes "
                            f"{'no parameter' if fam.param is None else 'the parameter ' + fam.param}")
        if self.param is not None and not (math.isfinite(self.param) and self.param > 0):
            raise PeelError(f"effect {self.family!r}: {fam.param} must be finite and > 0, "
                            f"got {self.param!r}")

    @property
    def spec(self) -> Family:
        return FAMILIES[self.family]

    @property
    def key(self) -> str:
        """Unique name, e.g. ``periodic_adhesion(lambda_mm=6)``."""
        fam = self.spec
        return fam.name if fam.param is None else f"{fam.name}({fam.param}={_fmt(self.param)})"

    @property
    def n_basis(self) -> int:
        return len(self.expressions)

    @property
    def expressions(self) -> tuple[str, ...]:
        return self.spec.expressions(self.param if self.param is not None else 0.0)

    def basis(self, rows: Rows, channel: int = 0) -> Tensor:
        """phi_k on every row, ``[..., L, n_basis]``."""
        parts = self.spec.basis(rows, self.param if self.param is not None else 0.0, channel)
        return torch.stack(parts, dim=-1)


@dataclass(frozen=True)
class Term:
    """A candidate on one channel with coefficients c_k (the unit of its channel per unit phi_k).

    ``coef_std`` is the coefficients' standard error as estimated by ``peel residual`` (kept in
    the checkpoint for the record; not used by the model)."""

    candidate: Candidate
    channel: str
    coef: tuple[float, ...]
    coef_std: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        fam = self.candidate.spec
        if self.channel not in fam.channels:
            raise PeelError(f"effect {self.candidate.key!r} acts on {list(fam.channels)}, not on "
                            f"channel {self.channel!r}")
        if len(self.coef) != self.candidate.n_basis:
            raise PeelError(f"effect {self.candidate.key!r} has {self.candidate.n_basis} "
                            f"coefficient(s), got {len(self.coef)}")
        if not all(isinstance(c, (int, float)) and math.isfinite(c) for c in self.coef):
            raise PeelError(f"effect {self.candidate.key!r}: coefficients must be finite numbers")

    @property
    def expression(self) -> str:
        """The term as a formula, e.g. ``+0.41*sin(2*pi*q/6) -0.12*cos(2*pi*q/6)``."""
        return " ".join(f"{c:+.4g}*{f'({e})' if ' ' in e else e}"
                        for c, e in zip(self.coef, self.candidate.expressions, strict=True))

    def to_json(self) -> dict[str, Any]:
        return {"family": self.candidate.family, "param": self.candidate.param,
                "param_name": self.candidate.spec.param, "channel": self.channel,
                "coefficients": list(self.coef), "coefficient_std": list(self.coef_std),
                "expression": self.expression, "key": self.candidate.key}

    @classmethod
    def from_json(cls, obj: Mapping[str, Any]) -> Term:
        """Rebuild from :meth:`to_json` (the basis comes from :data:`FAMILIES`, never the file)."""
        if not isinstance(obj, Mapping):
            raise PeelError("a compensation term must be a JSON object")
        try:
            param = obj.get("param")
            cand = Candidate(str(obj["family"]), None if param is None else float(param))
            coef = tuple(float(c) for c in obj["coefficients"])
            std = tuple(float(c) for c in obj.get("coefficient_std") or ())
            return cls(cand, str(obj["channel"]), coef, std)
        except (KeyError, TypeError, ValueError) as exc:
            raise PeelError(f"malformed compensation term {dict(obj)!r}: {exc}") from None


def candidates_from_grid(grid: Mapping[str, Sequence[float] | None]) -> list[Candidate]:
    """Candidates for ``{family: [param values] or None}``."""
    out = []
    for name, values in grid.items():
        if name not in FAMILIES:
            raise PeelError(f"unknown effect family {name!r}")
        if FAMILIES[name].param is None:
            out.append(Candidate(name))
        else:
            if not values:
                raise PeelError(f"effect family {name!r} needs parameter values")
            out.extend(Candidate(name, float(v)) for v in values)
    return out
