"""``peel bench sim --json``: simulator throughput against bare engine stepping (issue 3 §7).

Measures, on this machine and one process:

* ``trajectories_per_s`` / ``samples_per_s`` / ``steps_per_s``: full tasks under exploratory
  profiles (``generate_set``'s loop: effects, compliance, stick-slip, contact read-out,
  compensation, sensor model, history), engine steps counted;
* ``raw_steps_per_s``: bare ``stepSimulation`` on the same scene with the same contacts and no
  Python per-step work, logging or compensation (the limit);
* ``overhead_ratio`` = raw_steps_per_s / steps_per_s;
* ``paper_scale_projected_s``: 50,000 trajectories (1000 sets x 50) with ``--workers``
  processes, assuming linear scaling over workers;
* ``rollout_50x25_s``: one oracle rollout of N=50 sequences of 25 samples.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from ._pybullet import pb
from .config import load_sim_config
from .env import PeelEnv, sample_params
from .episode import run_episode
from .profiles import ExploratoryProfile

PAPER_TRAJECTORIES = 50_000


def run_bench(n_traj: int = 20, seed: int = 0, workers: int = 2, source: str = "sim"
              ) -> dict[str, float]:
    """Run the measurements; returns the JSON-able result."""
    cfg = load_sim_config()
    rng = np.random.default_rng(seed)
    env = PeelEnv(cfg, source=source, seed=seed)
    n_ctrl = int(np.ceil(cfg.task.t_max_s / cfg.task.control_period_s)) + 1
    samples = 0
    outcomes: dict[str, int] = {}
    t0 = time.perf_counter()
    for i in range(n_traj):
        params = sample_params(cfg, rng, source)
        prof = ExploratoryProfile(rng, cfg.dataset.u_min_mmps, cfg.dataset.u_max_mmps, n_ctrl,
                                  cfg.samples_per_control)
        tr = run_episode(env, prof, seed=seed + i, params=params)
        samples += len(tr) - 1
        outcomes[tr.outcome] = outcomes.get(tr.outcome, 0) + 1
    wall = time.perf_counter() - t0
    steps = samples * cfg.scene.substeps
    # raw: the same scene, blade sliding in contact, bare stepSimulation
    env.reset(seed=seed)
    for _ in range(20):
        env.step(2.5)
    c = env.scene.client
    n_raw = max(steps, 20000)
    t1 = time.perf_counter()
    for _ in range(n_raw):
        pb.stepSimulation(physicsClientId=c)
    raw_wall = time.perf_counter() - t1
    env.reset(seed=seed)
    for _ in range(20):
        env.step(2.5)
    v = np.random.default_rng(seed).uniform(cfg.dataset.u_min_mmps, cfg.dataset.u_max_mmps,
                                            (50, 25))
    t2 = time.perf_counter()
    env.rollout(v)
    roll = time.perf_counter() - t2
    env.close()
    tps = n_traj / wall
    steps_ps = steps / wall
    raw_ps = n_raw / raw_wall
    return {
        "trajectories": n_traj,
        "source": source,
        "trajectories_per_s": tps,
        "samples_per_s": samples / wall,
        "mean_samples_per_trajectory": samples / n_traj,
        "steps_per_s": steps_ps,
        "raw_steps_per_s": raw_ps,
        "overhead_ratio": raw_ps / steps_ps,
        "workers": workers,
        "paper_scale_projected_s": PAPER_TRAJECTORIES / (tps * workers),
        "rollout_50x25_s": roll,
        "outcomes": outcomes,
        "cpu_count": os.cpu_count() or 0,
    }


def main(argv: list[str] | None = None) -> int:
    """``peel bench sim [--json] [--trajectories N] [--workers W]``."""
    ap = argparse.ArgumentParser(prog="peel bench sim", description=__doc__)
    ap.add_argument("--json", action="store_true", help="print one JSON object (default)")
    ap.add_argument("--trajectories", type=int, default=20, help="trajectories to time")
    ap.add_argument("--workers", type=int, default=2, help="workers for the projection")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--source", choices=("sim", "plant"), default="sim")
    ap.add_argument("--calibrate", metavar="PNG", default=None,
                    help="instead: sweep constant speeds (sim and plant), write PNG + JSON")
    ap.add_argument("--sets", type=int, default=8, help="parameter sets per speed (--calibrate)")
    a = ap.parse_args(argv)
    if a.calibrate:
        from .calibration import sweep, write_figure

        cfg = load_sim_config()
        results = [sweep(cfg, "sim", a.sets, a.seed), sweep(cfg, "plant", a.sets, a.seed)]
        write_figure(results, a.calibrate, cfg.task.f_prewarn_n)
        print(json.dumps(results))
        return 0
    if a.trajectories < 1:
        from peel_msgs_py.errors import PeelError

        raise PeelError(f"--trajectories must be >= 1, got {a.trajectories}")
    res = run_bench(a.trajectories, a.seed, a.workers, a.source)
    print(json.dumps(res, sort_keys=True))
    return 0
