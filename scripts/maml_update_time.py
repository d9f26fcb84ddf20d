#!/usr/bin/env python3
"""Time Algorithm 1 (``MetaLearner.update``, paper 3.4) per peel at plant severity levels.

Usage: ``.venv/bin/python scripts/maml_update_time.py 0,1,2,3``

Per level: 12 constant-command peels (speeds drawn in 1-6 mm/s) of that level, then 11
sequential updates of the shipped checkpoint as ``peel experiment`` makes them (the replay pool
holds the earlier peels), one torch thread, default ``maml:`` config. Prints one JSON object:
per level the wall time and the process CPU time of an update (mean and max). The CPU time is
what an update costs on a core of its own; the wall time includes whatever else the machine runs.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import torch

from model_learner_node.maml import MetaLearner, load_maml_config
from model_learner_node.replay import ReplayPool
from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_sim_node.config import load_sim_config
from peel_sim_node.env import PeelEnv, sample_params
from peel_sim_node.episode import run_episode


def time_level(cfg, level: int) -> dict[str, float]:
    rng = np.random.default_rng([7, level])
    trajs = []
    with PeelEnv(cfg, source="plant", level=level, seed=0) as env:
        for i in range(12):
            u = float(rng.uniform(1.0, 6.0))
            tr = run_episode(env, lambda _h, u=u: u, seed=100 + i,
                             params=sample_params(cfg, rng, "plant", level))
            tr.meta = {**tr.meta, "cost": 10.0}
            trajs.append(tr)
    learner = MetaLearner(load_checkpoint(shipped_checkpoint()), load_maml_config())
    pool = ReplayPool()
    wall, cpu = [], []
    for tr in trajs[:-1]:
        t0, c0 = time.perf_counter(), time.process_time()
        learner.update(tr, pool)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        pool.add(tr)
    return {"n": len(wall), "update_s_mean": float(np.mean(wall)),
            "update_s_max": float(np.max(wall)), "cpu_s_mean": float(np.mean(cpu)),
            "cpu_s_max": float(np.max(cpu))}


def main() -> None:
    torch.set_num_threads(1)
    cfg = load_sim_config()
    levels = [int(x) for x in (sys.argv[1] if len(sys.argv) > 1 else "0,1,2,3").split(",")]
    print(json.dumps({lv: time_level(cfg, lv) for lv in levels}))


if __name__ == "__main__":
    main()
