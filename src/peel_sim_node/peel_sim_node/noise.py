"""Force-sensor model of the WEF-6A (section 4.1) and the actuator scatter (Eq. 2).

The sensor reads the true force plus a per-task bias, white noise and (plant only) a slow
random-walk drift, quantised to the 0.01 N resolution. Noise never enters :meth:`rollout`.
"""

from __future__ import annotations

import math

import numpy as np


def quantise(x: float, resolution: float) -> float:
    """``x`` rounded to a multiple of ``resolution``, exactly as
    ``np.round(x / resolution) * resolution`` (round half to even, the sign of zero kept)
    but on Python floats, which is several times faster for one reading."""
    y = x / resolution
    if not math.isfinite(y):
        return y * resolution
    r = round(y)
    return (float(r) if r != 0 else math.copysign(0.0, y)) * resolution


class ForceSensor:
    """Two-axis force sensor: bias + white noise (+ drift), quantised to ``resolution``."""

    def __init__(self, resolution_n: float, sigma_n: float, bias_sigma_n: float,
                 drift_n_per_sqrt_s: float = 0.0) -> None:
        self.resolution = resolution_n
        self.sigma = sigma_n
        self.bias_sigma = bias_sigma_n
        self.drift_rate = drift_n_per_sqrt_s
        self.bias = np.zeros(2)
        self.drift = np.zeros(2)

    def reset(self, rng: np.random.Generator) -> None:
        """New per-task bias (the sensor is re-zeroed before each task, imperfectly)."""
        self.bias = rng.normal(0.0, self.bias_sigma, 2) if self.bias_sigma > 0 else np.zeros(2)
        self.drift = np.zeros(2)

    def read(self, fx: float, fz: float, dt: float, rng: np.random.Generator) -> tuple[float, float]:
        """One reading (N) of the true forces after ``dt`` seconds.

        Per channel ``((f + bias) + drift) + noise``, then quantised; the random draws (and
        their order) are those of the array form this replaced, so the data are unchanged."""
        if self.drift_rate > 0.0:
            self.drift = self.drift + rng.normal(0.0, self.drift_rate * np.sqrt(dt), 2)
        b0, b1 = self.bias.tolist()
        d0, d1 = self.drift.tolist()
        if self.sigma > 0:
            n0, n1 = rng.normal(0.0, self.sigma, 2).tolist()
        else:
            n0 = n1 = 0.0
        ox = fx + b0 + d0 + n0
        oz = fz + b1 + d1 + n1
        if self.resolution > 0.0:
            return quantise(ox, self.resolution), quantise(oz, self.resolution)
        return float(ox), float(oz)
