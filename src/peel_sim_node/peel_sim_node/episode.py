"""run_episode: one task under a policy, commands every control period (section 4.2)."""

from __future__ import annotations

from collections.abc import Callable

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .env import PeelEnv

Policy = Callable[[Trajectory], float]


def run_episode(env: PeelEnv, policy: Policy, *, seed: int | None = None,
                params: dict[str, float] | None = None) -> Trajectory:
    """Reset ``env``, then every control period (0.5 s = 5 samples) ask ``u = policy(history)``
    (mm/s) and step with it until the task ends (done / timeout / safety_stop)."""
    env.reset(seed=seed, params=params)
    per = env.cfg.samples_per_control
    while not env.done:
        u = float(policy(env.history))
        if u != u:
            raise PeelError("policy returned NaN")
        for _ in range(per):
            env.step(u)
            if env.done:
                break
    return env.history
