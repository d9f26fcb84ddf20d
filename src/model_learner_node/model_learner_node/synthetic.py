"""Synthetic trajectories for unit tests and the model benchmark (not physics, not training data).

A damped, spring-like force response to the blade velocity with a stick-slip-like ripple: enough
structure that a forward model can learn it in seconds, so tests and ``peel bench model`` do not
need the simulator. Real training data comes from ``peel dataset`` (peel_sim_node).
"""

from __future__ import annotations

import numpy as np

from peel_msgs_py.trajectory import Trajectory


def synthetic_trajectory(seed: int, n: int = 60, dt: float = 0.1) -> Trajectory:
    """One trajectory of ``n`` samples; fully determined by ``seed``."""
    rng = np.random.default_rng(seed)
    k_x = rng.uniform(1.0, 3.0)  # N per mm/s
    tau = rng.uniform(0.2, 0.6)  # s
    u = np.repeat(rng.uniform(0.5, 5.0, size=n // 5 + 1), 5)[:n]
    q = np.zeros(n)
    v = np.zeros(n)
    fx = np.zeros(n)
    for k in range(1, n):
        v[k] = max(0.0, u[k - 1] + 0.05 * rng.standard_normal())
        q[k] = q[k - 1] + v[k] * dt
        target = k_x * v[k] + 0.8 * np.sin(2.0 * q[k])
        fx[k] = fx[k - 1] + dt / tau * (target - fx[k - 1])
    fz = 0.5 * fx + 0.3 * np.sqrt(np.maximum(q, 0.0))
    psi = 0.02 * fz
    t = np.arange(n) * dt
    return Trajectory(t=t, q=q, v=v, u=u, fx=fx, fz=fz, psi=psi, outcome="done",
                      params={"k_x": k_x, "tau": tau}, meta={"source": "synthetic", "seed": seed})


def synthetic_split(seed: int, count: int, n: int = 60) -> list[Trajectory]:
    """``count`` trajectories with seeds derived from ``seed``."""
    return [synthetic_trajectory(seed * 100_003 + i, n) for i in range(count)]
