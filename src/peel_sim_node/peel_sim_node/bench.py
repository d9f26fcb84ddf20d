"""``peel bench sim --json``: simulator throughput against bare engine stepping (docs/simulator.md).

Measures, on this machine and one process:

* ``trajectories_per_s`` / ``samples_per_s`` / ``steps_per_s``: full tasks under exploratory
  profiles (``generate_set``'s loop: effects, compliance, stick-slip, contact read-out,
  compensation, sensor model, history), engine steps counted;
* ``raw_steps_per_s``: bare ``stepSimulation`` on the same scene (a second env of the same
  source, blade and substrate in contact) with no Python per-step work, logging or
  compensation (the limit);
* ``overhead_ratio`` = raw_steps_per_s / steps_per_s;
* ``paper_scale_projected_s``: 50,000 trajectories (1000 sets x 50) with ``--workers``
  processes, assuming linear scaling over workers;
* ``rollout_50x25_s``: the median of ``--rollouts`` oracle rollouts of N=50 sequences of 25
  samples (each run in ``rollout_50x25_runs_s``).

Other jobs on a shared machine change the engine's speed from second to second, so the raw
stepping is *interleaved* with the trajectories: after each trajectory the same number of
bare engine steps is timed. Both rates then see the same load; ``overhead_ratio_pairs`` gives
the spread of the per-trajectory ratios (min / median / max).
"""

from __future__ import annotations

import json
import os
import time

import numpy as np

from peel_msgs_py.cliargs import ArgumentParser, nonnegative_int, positive_int

from ._pybullet import pb
from .config import load_sim_config
from .env import PeelEnv, sample_params
from .episode import run_episode
from .profiles import ExploratoryProfile

PAPER_TRAJECTORIES = 50_000


def run_bench(n_traj: int = 20, seed: int = 0, workers: int = 2, source: str = "sim",
              rollouts: int = 3) -> dict[str, float]:
    """Run the measurements; returns the JSON-able result."""
    cfg = load_sim_config()
    rng = np.random.default_rng(seed)
    env = PeelEnv(cfg, source=source, seed=seed)
    raw_env = PeelEnv(cfg, source=source, seed=seed)  # the same scene, for bare stepping
    for _ in range(20):
        raw_env.step(2.5)
    raw_client = raw_env.scene.client
    step_sim = pb.stepSimulation
    n_ctrl = int(np.ceil(cfg.task.t_max_s / cfg.task.control_period_s)) + 1
    samples = 0
    outcomes: dict[str, int] = {}
    wall = raw_wall = 0.0
    pair_ratios = []
    for i in range(n_traj):
        params = sample_params(cfg, rng, source)
        prof = ExploratoryProfile(rng, cfg.dataset.u_min_mmps, cfg.dataset.u_max_mmps, n_ctrl,
                                  cfg.samples_per_control)
        t0 = time.perf_counter()
        tr = run_episode(env, prof, seed=seed + i, params=params)
        t_sim = time.perf_counter() - t0
        n = len(tr) - 1
        n_steps = n * cfg.scene.substeps
        t1 = time.perf_counter()
        for _ in range(n_steps):
            step_sim(raw_client)  # positional, as in the simulator's loop
        t_raw = time.perf_counter() - t1
        wall += t_sim
        raw_wall += t_raw
        samples += n
        outcomes[tr.outcome] = outcomes.get(tr.outcome, 0) + 1
        if n_steps > 0:
            pair_ratios.append(t_sim / t_raw)
    raw_env.close()
    steps = samples * cfg.scene.substeps
    roll = []
    v = np.random.default_rng(seed).uniform(cfg.dataset.u_min_mmps, cfg.dataset.u_max_mmps,
                                            (50, 25))
    for _ in range(max(rollouts, 1)):
        env.reset(seed=seed)
        for _ in range(20):
            env.step(2.5)
        t2 = time.perf_counter()
        env.rollout(v)
        roll.append(time.perf_counter() - t2)
    env.close()
    tps = n_traj / wall
    steps_ps = steps / wall
    raw_ps = steps / raw_wall
    pr = np.array(pair_ratios) if pair_ratios else np.array([np.nan])
    return {
        "trajectories": n_traj,
        "source": source,
        "trajectories_per_s": tps,
        "samples_per_s": samples / wall,
        "mean_samples_per_trajectory": samples / n_traj,
        "steps_per_s": steps_ps,
        "raw_steps_per_s": raw_ps,
        "overhead_ratio": raw_ps / steps_ps,
        "overhead_ratio_pairs": {"min": float(pr.min()), "median": float(np.median(pr)),
                                 "max": float(pr.max())},
        "workers": workers,
        "paper_scale_projected_s": PAPER_TRAJECTORIES / (tps * workers),
        "rollout_50x25_s": float(np.median(roll)),
        "rollout_50x25_runs_s": roll,
        "outcomes": outcomes,
        "cpu_count": os.cpu_count() or 0,
    }


def main(argv: list[str] | None = None) -> int:
    """``peel bench sim [--json] [--trajectories N] [--workers W]``."""
    ap = ArgumentParser(prog="peel bench sim", description=__doc__)
    ap.add_argument("--json", action="store_true", help="print one JSON object (default)")
    ap.add_argument("--trajectories", type=positive_int, default=20, help="trajectories to time")
    ap.add_argument("--workers", type=positive_int, default=2, help="workers for the projection")
    ap.add_argument("--seed", type=nonnegative_int, default=0)
    ap.add_argument("--rollouts", type=positive_int, default=3, help="timed 50x25 oracle rollouts")
    ap.add_argument("--source", choices=("sim", "plant"), default="sim")
    ap.add_argument("--calibrate", metavar="PNG", default=None,
                    help="instead: sweep constant speeds (sim and plant), write PNG + JSON")
    ap.add_argument("--sets", type=positive_int, default=8,
                    help="parameter sets per speed (--calibrate)")
    a = ap.parse_args(argv)
    if a.calibrate:
        from peel_msgs_py.outputs import check_location

        from .calibration import sweep, write_figure

        check_location(a.calibrate, "--calibrate")
        cfg = load_sim_config()
        results = [sweep(cfg, "sim", a.sets, a.seed), sweep(cfg, "plant", a.sets, a.seed)]
        write_figure(results, a.calibrate, cfg.task.f_prewarn_n)
        print(json.dumps(results))
        return 0
    res = run_bench(a.trajectories, a.seed, a.workers, a.source, a.rollouts)
    print(json.dumps(res, sort_keys=True))
    return 0
