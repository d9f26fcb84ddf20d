"""Force-sensor model of the WEF-6A (section 4.1) and the actuator scatter (Eq. 2).

The sensor reads the true force plus a per-task bias, white noise and (plant only) a slow
random-walk drift, quantised to the 0.01 N resolution. Noise never enters :meth:`rollout`.
"""

from __future__ import annotations

import numpy as np


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
        """One reading (N) of the true forces after ``dt`` seconds."""
        if self.drift_rate > 0.0:
            self.drift = self.drift + rng.normal(0.0, self.drift_rate * np.sqrt(dt), 2)
        noise = rng.normal(0.0, self.sigma, 2) if self.sigma > 0 else np.zeros(2)
        out = np.array([fx, fz]) + self.bias + self.drift + noise
        if self.resolution > 0.0:
            out = np.round(out / self.resolution) * self.resolution
        return float(out[0]), float(out[1])
