"""Exploratory command profiles for dataset generation (section 3.2 / 3.3.1).

A profile is piecewise in control periods (0.5 s): segments of 1-4 periods that either hold a
level or ramp linearly (per period) from one level to the next. Each trajectory has its own base
speed drawn log-uniformly over the planner's range [u_min, u_max]; segment levels scatter
log-normally around it and are clipped to the range, so the dataset covers slow careful peeling,
fast peeling that hits the 20 N prewarning, and speed changes in between.
"""

from __future__ import annotations

import numpy as np

from peel_msgs_py.trajectory import Trajectory


class ExploratoryProfile:
    """Callable policy ``u = profile(history)`` (mm/s); the command sequence is drawn at
    construction from ``rng`` for ``n_controls`` control periods (enough for t_max)."""

    def __init__(self, rng: np.random.Generator, u_min: float, u_max: float, n_controls: int,
                 samples_per_control: int = 5) -> None:
        if not (0.0 <= u_min <= u_max):
            raise ValueError(f"profile range must satisfy 0 <= u_min <= u_max, got {u_min}, {u_max}")
        self.per = samples_per_control
        lo = max(u_min, 0.05 * u_max, 1e-6)
        base = float(np.exp(rng.uniform(np.log(lo), np.log(max(u_max, lo)))))
        levels: list[float] = []
        cur = float(np.clip(base * np.exp(rng.normal(0.0, 0.4)), u_min, u_max))
        while len(levels) < n_controls:
            length = int(rng.integers(1, 5))
            nxt = float(np.clip(base * np.exp(rng.normal(0.0, 0.4)), u_min, u_max))
            if rng.random() < 0.4:  # ramp
                levels.extend(np.linspace(cur, nxt, length + 1)[1:].tolist())
            else:  # hold
                levels.extend([nxt] * length)
            cur = nxt
        self.levels = np.asarray(levels[:n_controls], dtype=np.float64)

    def __call__(self, history: Trajectory) -> float:
        k = (len(history) - 1) // self.per
        return float(self.levels[min(k, len(self.levels) - 1)])
