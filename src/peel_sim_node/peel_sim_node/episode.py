"""run_episode: one task under a policy, commands every control period (section 4.2); and a
set of tasks under exploratory command profiles."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .config import SimConfig
from .effects import Effect
from .env import PeelEnv

Policy = Callable[[Trajectory], float]


def run_episode(env: PeelEnv, policy: Policy, *, seed: int | None = None,
                params: dict[str, float] | None = None) -> Trajectory:
    """Reset ``env``, then every control period (0.5 s = 5 samples) ask ``u = policy(history)``
    (mm/s) and step with it until the task ends (done / timeout / safety_stop).

    Each sample's speed is the command after the bridge's slowdown zone (Eq. M6,
    ``safety.slowdown.*``; the command itself when it is off), as the simulator node runs it;
    the trajectory's ``meta["slowdown"]`` says what the zone did."""
    env.reset(seed=seed, params=params)
    zone = env.cfg.slowdown_zone()
    per = env.cfg.samples_per_control
    while not env.done:
        u = float(policy(env.history))
        if u != u:
            raise PeelError("policy returned NaN")
        for _ in range(per):
            zone.measured(*env.last_forces)
            env.step(zone.speed(u))
            if env.done:
                break
    traj = env.history
    traj.meta = {**traj.meta, "slowdown": zone.as_dict()}
    return traj


def exploratory_tasks(cfg: SimConfig, *, source: str = "plant", effects: Sequence[Effect] = (),
                      n: int = 24, seed: int = 0, u_min: float = 0.5, u_max: float = 6.0,
                      level: int | None = None) -> list[Trajectory]:
    """``n`` tasks under exploratory command profiles (:mod:`.profiles`, speeds in
    [u_min, u_max] mm/s), task i with profile seed [seed, i] and noise seed 1000 seed + i; the
    varied speeds are what the residual analysis needs to tell effects apart
    (docs/residual.md). ``level``: the plant severity level (None: ``plant.level``)."""
    from .profiles import ExploratoryProfile

    env = PeelEnv(cfg, source=source, seed=seed, effects=list(effects), level=level)
    out = []
    try:
        for i in range(n):
            policy = ExploratoryProfile(np.random.default_rng([seed, i]), u_min, u_max, 200,
                                        cfg.samples_per_control)
            traj = run_episode(env, policy, seed=seed * 1000 + i)
            traj.meta = {**traj.meta, "task_index": i}
            out.append(traj)
    finally:
        env.close()
    return out
