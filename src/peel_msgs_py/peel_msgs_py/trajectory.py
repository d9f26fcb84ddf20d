"""The trajectory record shared by simulator, plant, model, planner, learner and bags.

A trajectory tau = (x_0, u_0, x_1, u_1, ..., x_T) (paper section 2) is stored as equal-length
per-sample arrays in the paper's units (see :mod:`peel_msgs_py.units`):

========  =====  =========================================================================
field     unit   meaning at sample k (time t_k = k * dt, dt = 100 ms)
========  =====  =========================================================================
``t``     s      sample time, ``t[0] == 0`` at point C
``q``     mm     blade position along the peel axis from C: the tool centre point the robot
                 controller reports (its encoders), ahead of the blade edge by the tool
                 compliance deflection (docs/simulator.md)
``v``     mm/s   measured blade (TCP) velocity over (t_{k-1}, t_k]: (q_k - q_{k-1}) / dt (4.3)
``u``     mm/s   command in force over (t_k, t_{k+1}]; so v_{k+1} ~ N(u_k, Sigma) (Eq. 2)
``fx``    N      horizontal contact force F_RX (peel direction)
``fz``    N      vertical contact force F_RZ
``psi``   mm     indentation of the blade into the pad (L_PENE, Eq. 24); NaN where unknown
========  =====  =========================================================================

``outcome`` is one of :data:`OUTCOMES`; ``params`` holds the per-trajectory physical parameters
(the P_k of 3.2.1) as floats; ``meta`` holds provenance (source, seed, set/trajectory ids,
model version, ...), JSON-serialisable.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Ways a task can end (4.2). ``running`` marks a trajectory still being recorded.
OUTCOMES: tuple[str, ...] = ("done", "timeout", "safety_stop", "aborted", "running")

#: Per-sample array fields, in storage order.
FIELDS: tuple[str, ...] = ("t", "q", "v", "u", "fx", "fz", "psi")


@dataclass
class Trajectory:
    """One peeling task, sampled every ``dt`` seconds. Arrays are float64 of equal length."""

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    u: np.ndarray
    fx: np.ndarray
    fz: np.ndarray
    psi: np.ndarray
    outcome: str = "running"
    params: dict[str, float] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = None
        for name in FIELDS:
            arr = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            setattr(self, name, arr)
            if n is None:
                n = arr.shape[0]
            elif arr.shape[0] != n:
                raise ValueError(
                    f"trajectory field {name!r} has {arr.shape[0]} samples, expected {n}"
                )
        if self.outcome not in OUTCOMES:
            raise ValueError(f"trajectory outcome {self.outcome!r} is not one of {OUTCOMES}")

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def dt(self) -> float:
        """Sample period in s (0.1 s in the paper), from the time stamps."""
        if len(self) < 2:
            return float("nan")
        return float(np.median(np.diff(self.t)))

    def states(self) -> np.ndarray:
        """The model's per-sample state rows [q, v, fx, fz], shape (T, 4) (Eq. 2)."""
        return np.stack([self.q, self.v, self.fx, self.fz], axis=1)

    def as_array(self) -> np.ndarray:
        """All per-sample fields as a (T, len(FIELDS)) float64 array, columns in FIELDS order."""
        return np.stack([getattr(self, name) for name in FIELDS], axis=1)

    @classmethod
    def from_array(
        cls,
        arr: np.ndarray,
        outcome: str = "running",
        params: dict[str, float] | None = None,
        meta: dict[str, Any] | None = None,
    ) -> Trajectory:
        """Inverse of :meth:`as_array`."""
        arr = np.asarray(arr, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != len(FIELDS):
            raise ValueError(f"trajectory array must have shape (T, {len(FIELDS)}), got {arr.shape}")
        cols = {name: arr[:, i] for i, name in enumerate(FIELDS)}
        return cls(**cols, outcome=outcome, params=dict(params or {}), meta=dict(meta or {}))

    def slice(self, start: int, stop: int) -> Trajectory:
        """Samples [start, stop) as a new trajectory with the same outcome, params and meta."""
        cols = {name: getattr(self, name)[start:stop].copy() for name in FIELDS}
        return Trajectory(**cols, outcome=self.outcome, params=dict(self.params),
                          meta=dict(self.meta))

    @property
    def t_cpl(self) -> float:
        """Completion time T_cpl (s): time of the last sample (4.2)."""
        return float(self.t[-1]) if len(self) else 0.0

    @property
    def sum_fx(self) -> float:
        """Sum of |F_RX| over all samples (Table 1)."""
        return float(np.abs(self.fx).sum())

    @property
    def sum_fz(self) -> float:
        """Sum of |F_RZ| over all samples (Table 1)."""
        return float(np.abs(self.fz).sum())
