"""Effects injected on the measurement side, drawn at random: the power study's ground truth.

The power study of ``peel residual`` (docs/residual.md, "Power and false-alarm rate") records
clean tasks once and rewrites their forces as a sensor would see an extra load nobody declared:
F'_ch,k = F_ch,k + g(x_k), with g a member of one family of the candidate library
(:data:`~peel_model.effect_terms.FAMILIES`) whose amplitude, shape parameter, sign and
channel are drawn, or a between-task offset (constant within a task, changing from one task to
the next). The shape parameters are drawn from continuous ranges (:data:`SHAPE_RANGES`), not
from the library's grids, so a draw is in general *not* one of the candidates.

Amplitude A (N): g = +-A s(x), the shape s scaled to |s| <= 1 over the data's range:

* ``sensor_offset`` 1; ``viscous_drag`` v / V_REF; ``quadratic_drag`` v |v| / V_REF^2;
  ``coulomb_friction`` tanh(v / v0); ``stribeck_friction`` exp(-(v / vs)^2);
* ``periodic_adhesion`` sin(2 pi q / lambda + phase); ``near_start_hold`` exp(-q / l);
  ``position_trend`` q / Q_REF;
* ``decay_in_time`` exp(-t / tau); ``drift_in_time`` t / T_REF;
* ``hysteresis`` tanh(dv / dv0), dv = v_k - v_{k-1};
* ``cross_talk`` F_other / mean|F_other| (a share A / mean|F_other| of the other channel);
* ``task_offset`` (between tasks): A_task (i - (n - 1) / 2) for the i-th task, A_task in N per
  task (:data:`TASK_OFFSET_RANGE_N`): a drift of the force zero from one task to the next (pad
  wear, sensor zero drift between tasks), centred on the data's mean level.

The speed families ``speed_scale`` and ``speed_offset`` are drawn on the *plant* side, not the
measurement side: the robot moves at u (1 + s) or u + c (:data:`SPEED_RANGES`, sign drawn), so
the forces respond to the speed it really has and the tasks are recorded with the effect in the
plant (:meth:`Injection.speed_error`; the study script passes it to the plant as
``peel_sim_node.example_effects.SpeedError``). A rewrite of the measured speed would instead be
a speed sensor error, which the forces would contradict. ``actuator_lag`` is not drawn: the
level-3 plant's own lag is named on every clean run, so it has no clean baseline.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from peel_model.effect_terms import FAMILIES, FORCE_CHANNELS, VELOCITY_CHANNEL
from peel_msgs_py.trajectory import Trajectory

#: The exploratory profiles' top speed (mm/s): drag terms reach A there.
V_REF_MMPS = 6.0
#: The peel path's length (mm, C to the end): a position trend reaches A there.
Q_REF_MM = 25.0
#: Time (s) at which a drift within a task reaches A (about the median exploratory task).
T_REF_S = 15.0

#: Drawn shape parameters per family: name -> (low, high), uniform. Physically plausible ranges:
#: friction breakaway and Coulomb smoothing speeds around the peel speeds (0.5-6 mm/s), pad
#: texture periods of a few mm over a 25 mm path, a residual-vacuum reach of 1-8 mm, vacuum or
#: warm-up time constants of 1-20 s within tasks of 6-40 s.
SHAPE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "sensor_offset": {}, "viscous_drag": {}, "quadratic_drag": {},
    "coulomb_friction": {"v0_mmps": (0.1, 0.5)},
    "stribeck_friction": {"vs_mmps": (0.5, 2.5)},
    "periodic_adhesion": {"lambda_mm": (2.0, 12.5), "phase_rad": (0.0, 2 * math.pi)},
    "near_start_hold": {"length_mm": (1.0, 8.0)},
    "position_trend": {}, "decay_in_time": {"tau_s": (1.0, 20.0)}, "drift_in_time": {},
    "hysteresis": {"dv0_mmps": (0.1, 0.6)}, "cross_talk": {},
}

#: Plant-side speed effects: |s| of ``speed_scale`` (a relative error: 5-30 %, an axis
#: calibration error up to a slipping gripper) and |c| of ``speed_offset`` (mm/s, 2-80 % of the
#: 0.5-6 mm/s peel speeds), uniform, sign drawn.
SPEED_RANGES: dict[str, tuple[float, float]] = {"speed_scale": (0.05, 0.30),
                                                "speed_offset": (0.1, 0.4)}

#: The between-task offset's step, N per task (uniform).
TASK_OFFSET_RANGE_N: tuple[float, float] = (0.3, 0.5)
#: The name of the between-task family (not a candidate term: a verdict, docs/residual.md).
TASK_OFFSET = "task_offset"
#: Every family the study draws.
STUDY_FAMILIES: tuple[str, ...] = (*SHAPE_RANGES, TASK_OFFSET, *SPEED_RANGES)
#: The families drawn with their size, not at the study's amplitudes.
DRAWN_SIZE: tuple[str, ...] = (TASK_OFFSET, *SPEED_RANGES)


@dataclass(frozen=True)
class Injection:
    """One drawn effect: family, channel, signed amplitude (N, or N per task; for a speed
    family s or c, :data:`SPEED_RANGES`) and shape."""

    family: str
    channel: str
    amplitude_n: float
    shape: dict[str, float] = field(default_factory=dict)

    @property
    def plant_side(self) -> bool:
        """A speed effect: recorded in the plant, not added to the measurements."""
        return self.family in SPEED_RANGES

    def speed_error(self) -> tuple[float, float]:
        """(scale, offset mm/s) of the robot's speed u * scale + offset (module docstring)."""
        if not self.plant_side:
            raise ValueError(f"{self.family} is a force effect, added to the measurements")
        if self.family == "speed_scale":
            return 1.0 + self.amplitude_n, 0.0
        return 1.0, self.amplitude_n

    def to_json(self) -> dict[str, Any]:
        return {"family": self.family, "channel": self.channel,
                "amplitude_n": self.amplitude_n, "shape": dict(self.shape)}

    def apply(self, tasks: Sequence[Trajectory]) -> list[Trajectory]:
        """The tasks with this effect added to the measured force of :attr:`channel`."""
        if self.plant_side:
            raise ValueError(f"{self.family} acts in the plant: record the tasks with "
                             "speed_error(), do not rewrite them")
        ch = FORCE_CHANNELS.index(self.channel)
        other = "fz" if ch == 0 else "fx"
        f_ref = float(np.mean(np.abs(np.concatenate([getattr(t, other) for t in tasks]))))
        out = []
        for i, tr in enumerate(tasks):
            g = self.amplitude_n * self._shape(tr, i, len(tasks), f_ref)
            out.append(replace(tr, **{self.channel: getattr(tr, self.channel) + g},
                               meta={**tr.meta, "injected": self.to_json()}))
        return out

    def _shape(self, tr: Trajectory, i: int, n: int, f_ref: float) -> np.ndarray:
        """s(x) on every sample of task ``i`` of ``n`` (module docstring)."""
        dv = np.concatenate([[0.0], np.diff(tr.v)])
        other = tr.fz if self.channel == "fx" else tr.fx
        return shape_of(self.family, self.shape, v=tr.v, q=tr.q, t=tr.t, dv=dv,
                        other=other / max(f_ref, 1e-9), task=i - (n - 1) / 2)


def shape_of(family: str, p: dict[str, float], *, v: np.ndarray, q: np.ndarray, t: np.ndarray,
             dv: np.ndarray | None = None, other: np.ndarray | None = None,
             task: float = 0.0) -> np.ndarray:
    """The shape s(x) of ``family`` with shape parameters ``p`` (module docstring) at speeds
    ``v`` (mm/s), positions ``q`` (mm) and times ``t`` (s); ``dv`` is the change of speed from
    the previous sample, ``other`` the other channel's force over its mean magnitude and
    ``task`` the task's place from the middle of the sequence (the families that need them)."""
    v, q, t = (np.asarray(x, dtype=float) for x in (v, q, t))
    shapes = {
        "sensor_offset": lambda: np.ones_like(v),
        "viscous_drag": lambda: v / V_REF_MMPS,
        "quadratic_drag": lambda: v * np.abs(v) / V_REF_MMPS ** 2,
        "coulomb_friction": lambda: np.tanh(v / p.get("v0_mmps", 1.0)),
        "stribeck_friction": lambda: np.exp(-(v / p.get("vs_mmps", 1.0)) ** 2),
        "periodic_adhesion": lambda: np.sin(2 * math.pi * q / p.get("lambda_mm", 1.0)
                                            + p.get("phase_rad", 0.0)),
        "near_start_hold": lambda: np.exp(-np.clip(q, 0, None) / p.get("length_mm", 1.0)),
        "position_trend": lambda: q / Q_REF_MM,
        "decay_in_time": lambda: np.exp(-t / p.get("tau_s", 1.0)),
        "drift_in_time": lambda: t / T_REF_S,
        "hysteresis": lambda: np.tanh(np.asarray(dv, dtype=float) / p.get("dv0_mmps", 1.0)),
        "cross_talk": lambda: np.asarray(other, dtype=float),
        TASK_OFFSET: lambda: np.full_like(v, task),
    }
    if family not in shapes:
        raise ValueError(f"unknown study family {family!r} (known: {', '.join(shapes)})")
    return shapes[family]()


def draw(family: str, amplitude_n: float, rng: np.random.Generator) -> Injection:
    """An effect of ``family`` at ``amplitude_n`` (N; ignored for :data:`DRAWN_SIZE`, whose
    size is drawn from :data:`TASK_OFFSET_RANGE_N` or :data:`SPEED_RANGES`): sign, channel and
    shape drawn (a speed family acts on the speed channel ``v``)."""
    if family not in STUDY_FAMILIES:
        raise ValueError(f"unknown study family {family!r} (known: {', '.join(STUDY_FAMILIES)})")
    assert family == TASK_OFFSET or family in FAMILIES
    channel = FORCE_CHANNELS[int(rng.integers(2))]
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if family in SPEED_RANGES:
        return Injection(family, VELOCITY_CHANNEL, sign * float(rng.uniform(*SPEED_RANGES[family])))
    if family == TASK_OFFSET:
        return Injection(family, channel, sign * float(rng.uniform(*TASK_OFFSET_RANGE_N)))
    shape = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in SHAPE_RANGES[family].items()}
    return Injection(family, channel, sign * float(amplitude_n), shape)
