#!/usr/bin/env python3
"""The residual analysis on known scenarios, several seeds: what it names and the error ratio.

    .venv/bin/python scripts/residual_scenarios.py [--seeds 401,402,403] [--tasks 24]
                                [--scenarios sim,plant,leak,...] [--level L] [--out FILE]
    .venv/bin/python scripts/residual_scenarios.py --history-gradient [--seeds 401] [--tasks 10]

Each scenario is plant (or simulator) data with undeclared effects from
``peel_sim_node.example_effects``, generated in-process under exploratory command profiles
(``peel_sim_node.episode.exploratory_tasks``), analysed with the shipped model exactly as
``peel residual`` does (``peel_residual.analysis.analyse``), on the plant at
``--level`` (default: ``plant.level`` of config/peel_sim_node.yaml). One JSON line per
(scenario, seed): the named terms and the held-out open-loop RMSE after / before per channel;
docs/residual.md reports the table. ``--history-gradient``: instead, how much of a force offset in
its history the shipped model carries into its next prediction (sum over the history rows of
dF_{k+1}/dF_j, per channel, percentiles over the samples of plant data).
"""

from __future__ import annotations

import json
import sys
import time

import torch
from tqdm import tqdm

from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_msgs_py.cliargs import ArgumentParser, int_arg, int_list, positive_int, run_main
from peel_residual import predict as P
from peel_residual.analysis import analyse
from peel_residual.config import load_residual_config
from peel_residual.data import one_step_samples
from peel_sim_node import example_effects as X
from peel_sim_node.config import load_sim_config
from peel_sim_node.episode import exploratory_tasks
from peel_sim_node.plant import LEVELS

SCENARIOS = {
    "sim": ("sim", []),
    "plant": ("plant", []),
    "leak": ("plant", [X.vacuum_leak]),
    "axis": ("plant", [X.slipping_axis]),
    "drag": ("plant", [X.hose_drag]),
    "grooves": ("plant", [X.grooved_pad]),
    "axis+leak": ("plant", [X.slipping_axis, X.vacuum_leak]),
    "axis+drag": ("plant", [X.slipping_axis, X.hose_drag]),
}


def history_gradient(model, sim, seed: int, n: int, level: int | None) -> dict:
    """Percentiles of sum_j dF_{k+1}/dF_j on exploratory plant tasks (past the padded start)."""
    import numpy as np

    tasks = exploratory_tasks(sim, source="plant", n=n, seed=seed, level=level)
    s = one_step_samples(tasks, model.h)
    s = s.subset(s.k >= model.h - 1)
    g = P.history_gradient(model, s).sum(axis=2)  # [n, out, in]
    pct = {}
    for o, out in enumerate(("fx", "fz")):
        for i, inp in enumerate(("fx", "fz")):
            pct[f"d{out}/d{inp}"] = [round(float(x), 3) for x in
                                     np.percentile(g[:, o, i], [10, 50, 90])]
    return {"seed": seed, "tasks": n, "level": level, "samples": len(s),
            "percentiles_10_50_90": pct}


def main(argv: list[str]) -> int:
    p = ArgumentParser(prog="residual_scenarios.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int_list(0), default=(401, 402, 403))
    p.add_argument("--tasks", type=positive_int, default=24)
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--level", type=int_arg(min(LEVELS), max(LEVELS)), default=None,
                   help="plant severity level (default: plant.level of the config)")
    p.add_argument("--out", default=None, help="also write the JSON lines to this file")
    p.add_argument("--history-gradient", action="store_true",
                   help="print the model's history gradient on plant data instead")
    args = p.parse_args(argv)
    names = [n for n in args.scenarios.split(",") if n]
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        p.error(f"unknown scenario(s) {unknown}; known: {', '.join(SCENARIOS)}")
    torch.set_num_threads(1)
    model = load_checkpoint(shipped_checkpoint())
    cfg, sim = load_residual_config(), load_sim_config()
    level = args.level if args.level is not None else sim.plant.level
    if args.history_gradient:
        for seed in args.seeds:
            print(json.dumps(history_gradient(model, sim, seed, args.tasks, level)))
        return 0
    lines = []
    jobs = [(name, seed) for name in names for seed in args.seeds]
    for name, seed in tqdm(jobs, desc="scenarios", unit="run"):
        source, effects = SCENARIOS[name]
        t0 = time.perf_counter()
        tasks = exploratory_tasks(sim, source=source, effects=effects, n=args.tasks, seed=seed,
                                  level=level if source == "plant" else None)
        r = analyse(tasks, model, cfg)
        rec = {"scenario": name, "seed": seed,
               "level": level if source == "plant" else 0,
               "effects": [e.__name__ for e in effects],
               "named": [f"{f.candidate.key}@{f.channel}" for tr in r.traces.values()
                         for f in tr.findings],
               "coefficients": {f"{f.candidate.key}@{f.channel}": [round(float(c), 4)
                                                                  for c in f.coef]
                                for tr in r.traces.values() for f in tr.findings},
               "open_loop_after_over_before": {
                   ch: round(r.rmse_after[ch]["open_loop"] / r.rmse_before[ch]["open_loop"], 3)
                   for ch in ("fx", "fz", "v")},
               "structure_remains": [s.channel for s in r.structure if s.remains],
               "open_loop_end_mean_se_n": {ch: [round(d["mean_n"], 2), round(d["se_n"], 2)]
                                           for ch, d in r.drift.items()},
               "wall_s": round(time.perf_counter() - t0, 1)}
        lines.append(json.dumps(rec))
        tqdm.write(lines[-1])
    if args.out:
        with open(args.out, "w") as fh:
            fh.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(run_main("residual_scenarios.py", main))
