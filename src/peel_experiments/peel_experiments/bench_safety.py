"""``peel bench safety``: prewarnings and peak forces per plant level and planner arm.

Every arm plans with the same model (the shipped checkpoint, not updated: the guard is a
planner property) and the same cost, N and H on the same peels:

* ``peel``: the shipped planner (config/peel_planner_node.yaml), with the guard of the force
  limit (Eq. M1-M4, docs/planner.md);
* ``peel_unguarded``: the same with the guard off (no margin, no slowest sequence, no check, no
  fallback): the planner before the guard;
* ``pytorch_mppi``: pytorch_mppi 0.9.1 over the same model and critics (``bench_planner``).

Levels: ``sim`` (the simulator, task k with env seed ``seed * 1000 + k``) and plant levels 0-3
(``PeelEnv(source="plant")``, the substrates of experiment seed ``seed`` as ``peel experiment``
draws them, changed over the peels as each ``--sequences`` entry says). Each peel runs with every
planner seed in ``--planner-seeds`` (peel's ``mppi.seed``, pytorch_mppi's torch seed).

Prints one JSON object: per level (and sequence) and arm, ``peels``, ``prewarnings`` (outcome
``safety_stop``), ``over_18n`` (peels whose largest |F_RX| or |F_RZ| reached 18 N, stops
included) and its share, mean J (Eq. 3), T_cpl and peak force, each with a 95 % interval
(mean +- 1.96 standard errors over the peels) and the per-planner-seed means, the prewarning
rate with its 95 % Wilson interval, and the guard's counts (commands reduced, fallbacks) summed
over the peels. ``latency``: ``plan()`` at (N, H) = (50, 5) of every arm on one simulator
history, interleaved calls in the same run (median / p99 wall ms, median CPU ms, each arm's
median over pytorch_mppi's); ``--latency-repeats 0`` leaves it out. ``--per-peel`` adds each
peel's outcome, peak, J and T_cpl (to compare arms run separately on the first peels).

``--oracle-on-stops`` asks of every stop whether it could have been avoided
(:mod:`.stops`): each substrate on which some arm tripped the prewarning is peeled again by
the oracle (the shipped planner with the plant's true dynamics as its model) and at a few
constant speeds; the cell then holds ``oracle_on_stops`` (task index, the oracle's outcome and
peak, each constant speed's outcome, ``peelable``) and every arm ``prewarnings_avoidable``: its
prewarnings on peelable substrates. ``--experiments DIR ...`` runs no bench peel: it reads the
peels of ``peel experiment`` output folders (with learning, every method) and reports the same
counts per folder and method, every stop replayed in the same way, and the totals.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from peel_msgs_py.cliargs import ArgumentParser, nonnegative_int, positive_int, run_main
from peel_msgs_py.errors import PeelError
from peel_planner_node.config import UNGUARDED, PlannerConfig, load_planner_config
from peel_planner_node.cost import Cost, episode_cost_terms
from peel_planner_node.dynamics import learned_dynamics
from peel_planner_node.mppi import Planner

from .bench_common import interval, load_model, parse_sets, timing, wilson
from .planner_studies import peak_force
from .stops import experiment_cells, oracle_on_stops
from .torch_mppi import TorchMppiPolicy

ARMS: tuple[str, ...] = ("peel", "peel_unguarded", "pytorch_mppi")


def make_policy(arm: str, pred: Any, base: PlannerConfig, pseed: int) -> Any:
    """The planner of one arm with planner seed ``pseed``."""
    if arm == "pytorch_mppi":
        return TorchMppiPolicy(pred, Cost(base.cost), base, seed=pseed)
    extra = UNGUARDED if arm == "peel_unguarded" else {}
    cfg = base.replace(**{**extra, "mppi.seed": pseed})
    return Planner(learned_dynamics(pred, cfg.dynamics), Cost(cfg.cost), cfg)


def peels_of(level: str, sequence: str, seed: int, tasks: int,
             sim_cfg: Any) -> tuple[Any, list[tuple[int, dict[str, float] | None]]]:
    """The env of a level and its peels: (env seed, plant parameters or None) per task."""
    from peel_sim_node.env import PeelEnv

    from .experiment import substrates, task_seed

    if level == "sim":
        return PeelEnv(sim_cfg, seed=0), [(seed * 1000 + k, None) for k in range(tasks)]
    lv = int(level)
    subs = substrates(sim_cfg, seed, tasks, 0, lv, sequence)
    env = PeelEnv(sim_cfg, source="plant", seed=task_seed(seed, 0), params=subs[0], level=lv)
    return env, [(task_seed(seed, k), subs[k]) for k in range(tasks)]


def run_peel(env: Any, policy: Any, env_seed: int, params: dict | None,
             cost: Cost) -> dict[str, Any]:
    """One peel: J, T_cpl, outcome, peak force and (peel's arms) the guard's counts."""
    from peel_sim_node.episode import run_episode

    policy.reset()
    traj = run_episode(env, policy, seed=env_seed, params=params)
    guard = policy.guard.as_dict() if isinstance(policy, Planner) else {}
    return {"J": float(episode_cost_terms(traj, cost)["total"]), "t": float(traj.t_cpl),
            "out": traj.outcome, "peak": peak_force(traj),
            "reduced": guard.get("commands_reduced", 0), "fallbacks": guard.get("fallbacks", 0),
            "margin_mean": float(np.mean(guard["margin_mean_n"])) if guard else 0.0}


def summary(runs: list[dict[str, Any]], pseeds: list[int], over_n: float) -> dict[str, Any]:
    """The counts and intervals of one (level, sequence, arm) cell; runs are seed-major."""
    k = len(runs) // len(pseeds)
    by_seed = [runs[i * k:(i + 1) * k] for i in range(len(pseeds))]
    over = [r["peak"] >= over_n for r in runs]
    stops = sum(r["out"] == "safety_stop" for r in runs)
    return {
        "peels": len(runs),
        "prewarnings": stops,
        "prewarning_rate": {"rate": round(stops / len(runs), 5),
                            "ci95_wilson": wilson(stops, len(runs))},
        "over_18n": int(sum(over)), "share_over_18n": round(float(np.mean(over)), 4),
        "done": sum(r["out"] == "done" for r in runs),
        "J": interval([r["J"] for r in runs]), "t_cpl_s": interval([r["t"] for r in runs]),
        "peak_n": {**interval([r["peak"] for r in runs]),
                   "max": round(max(r["peak"] for r in runs), 3)},
        "by_planner_seed": {str(s): {
            "prewarnings": sum(r["out"] == "safety_stop" for r in rs),
            "over_18n": sum(r["peak"] >= over_n for r in rs),
            "J": round(float(np.mean([r["J"] for r in rs])), 4),
            "t_cpl_s": round(float(np.mean([r["t"] for r in rs])), 4)}
            for s, rs in zip(pseeds, by_seed, strict=True)},
        "commands_reduced": int(sum(r["reduced"] for r in runs)),
        "fallbacks": int(sum(r["fallbacks"] for r in runs)),
        "margin_mean_n": round(float(np.mean([r["margin_mean"] for r in runs])), 4),
    }


def latency(arms: list[str], pred: Any, base: PlannerConfig, repeats: int,
            sim_cfg: Any) -> dict[str, Any]:
    """``plan()`` at (50, 5) of every arm on one simulator history (task seed 1000 after 3 s at
    2 mm/s: longer than the horizon, so that Eq. M7's replay runs when it is on), in rounds of
    interleaved calls so that machine load hits every arm alike."""
    from peel_sim_node.env import PeelEnv

    cfg = base.replace(**{"mppi.n_samples": 50, "mppi.horizon": 5})
    env = PeelEnv(sim_cfg, seed=0)
    try:
        env.reset(seed=1000)
        for _ in range(30):
            env.step(2.0)
        hist = env.history
    finally:
        env.close()
    pols = {arm: make_policy(arm, pred, cfg, 0) for arm in arms}
    wall: dict[str, list[float]] = {a: [] for a in arms}
    cpu: dict[str, list[float]] = {a: [] for a in arms}
    for _ in range(repeats):
        for arm, pol in pols.items():
            med, _, c = timing(pol, hist, 1, warmup=1 if not wall[arm] else 0)
            wall[arm].append(med)
            cpu[arm].append(c)
    out = {a: {"median_ms": round(float(np.median(wall[a])), 3),
               "p99_ms": round(float(np.percentile(wall[a], 99)), 3),
               "cpu_median_ms": round(float(np.median(cpu[a])), 3)} for a in arms}
    if "pytorch_mppi" in out:
        ref = out["pytorch_mppi"]
        for a in arms:
            out[a]["ratio_to_pytorch_mppi"] = round(out[a]["median_ms"] / ref["median_ms"], 4)
            out[a]["cpu_ratio_to_pytorch_mppi"] = round(
                out[a]["cpu_median_ms"] / ref["cpu_median_ms"], 4)
    return {"n": 50, "h": 5, "repeats": repeats, "arms": out}


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Every (level, sequence) cell with every arm on the same peels (module docstring)."""
    from peel_sim_node.config import load_sim_config

    torch.set_num_threads(1)
    pred, model_info = load_model()
    base = load_planner_config().replace(**args.set)
    cost = Cost(base.cost)
    sim_cfg = load_sim_config()
    cells = [(lv, "stationary" if lv == "sim" else sq) for lv in args.levels
             for sq in (["-"] if lv == "sim" else args.sequences)]
    out: list[dict[str, Any]] = []
    bar = tqdm(total=len(cells) * len(args.arms) * len(args.planner_seeds) * args.tasks,
               desc="bench safety", disable=not args.progress, file=sys.stderr)
    for level, sequence in cells:
        env, peels = peels_of(level, sequence, args.seed, args.tasks, sim_cfg)
        arms: dict[str, Any] = {}
        outcomes: dict[str, list[str]] = {}
        try:
            for arm in args.arms:
                runs = []
                for ps in args.planner_seeds:
                    policy = make_policy(arm, pred, base, ps)
                    for env_seed, params in peels:
                        runs.append(run_peel(env, policy, env_seed, params, cost))
                        bar.update(1)
                arms[arm] = summary(runs, args.planner_seeds, args.over_n)
                outcomes[arm] = [r["out"] for r in runs]
                if args.per_peel:  # seed-major, task order within each planner seed
                    arms[arm]["per_peel"] = [{"out": r["out"], "peak": round(r["peak"], 3),
                                              "J": round(r["J"], 4), "t": r["t"]}
                                             for r in runs]
            if args.oracle_on_stops:
                checked, avoidable = oracle_on_stops(env, peels, outcomes, base,
                                                     args.planner_seeds[0])
                for arm, n in avoidable.items():
                    arms[arm]["prewarnings_avoidable"] = n
        finally:
            env.close()
        cell = {"level": level, "sequence": sequence if level != "sim" else None, "arms": arms}
        out.append({**cell, "oracle_on_stops": checked} if args.oracle_on_stops else cell)
    bar.close()
    lat = (latency(args.arms, pred, base, args.latency_repeats, sim_cfg)
           if args.latency_repeats else None)
    return {"benchmark": "safety", "model": model_info, "seed": args.seed,
            "tasks": args.tasks, "planner_seeds": args.planner_seeds, "over_n": args.over_n,
            "n": base.mppi.n_samples, "h": base.mppi.horizon, "base_overrides": args.set,
            "cells": out, "latency": lat}


def _levels(text: str) -> list[str]:
    out = [x.strip() for x in text.split(",") if x.strip()]
    for x in out:
        if x != "sim" and x not in ("0", "1", "2", "3"):
            raise PeelError(f"--levels: {x!r} is not sim or a plant level 0-3")
    return out


def main(argv: list[str] | None = None) -> int:
    """``peel bench safety [--levels sim,0,1,2,3] [--sequences ...] [--tasks N] ...``."""
    from peel_sim_node.plant import SEQUENCES, check_sequence

    ap = ArgumentParser(prog="peel bench safety", description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object (default)")
    ap.add_argument("--levels", default="sim,0,1,2,3",
                    help="comma-separated: sim and/or plant levels 0-3 (default all)")
    ap.add_argument("--sequences", default=",".join(SEQUENCES),
                    help="plant sequences (comma-separated; default all)")
    ap.add_argument("--arms", default=",".join(ARMS), help=f"comma-separated, of {ARMS}")
    ap.add_argument("--tasks", type=positive_int, default=20, help="peels per cell and seed")
    ap.add_argument("--seed", type=nonnegative_int, default=0,
                    help="substrate seed: sim env seeds seed*1000+k, plant experiment seed")
    ap.add_argument("--planner-seeds", default="0", help="comma-separated planner seeds")
    ap.add_argument("--over-n", type=float, default=18.0, help="peak force counted, N (18)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="planner parameter for every arm (repeatable)")
    ap.add_argument("--latency-repeats", type=nonnegative_int, default=50,
                    help="timed plan() calls per arm at (50, 5); 0: no latency (default 50)")
    ap.add_argument("--per-peel", action="store_true",
                    help="also list every peel's outcome, peak, J and T_cpl per arm")
    ap.add_argument("--oracle-on-stops", action="store_true",
                    help="peel every substrate an arm stopped on again with the oracle (true "
                         "dynamics): which prewarnings were avoidable")
    ap.add_argument("--experiments", nargs="+", metavar="DIR", default=[],
                    help="instead of bench peels: the peels of these peel experiment --out "
                         "folders (with learning), every stop replayed as --oracle-on-stops")
    ap.add_argument("--progress", action="store_true", help="tqdm progress bar on stderr")
    args = ap.parse_args(argv)
    args.set = parse_sets(args.set)
    args.levels = _levels(args.levels)
    args.sequences = [x.strip() for x in args.sequences.split(",") if x.strip()]
    for sq in args.sequences:
        check_sequence(sq)
    args.arms = [x.strip() for x in args.arms.split(",") if x.strip()]
    for arm in args.arms:
        if arm not in ARMS:
            raise PeelError(f"--arms: unknown arm {arm!r} (one of {', '.join(ARMS)})")
    try:
        args.planner_seeds = [int(x) for x in args.planner_seeds.split(",") if x.strip()]
    except ValueError:
        raise PeelError("--planner-seeds must be comma-separated integers") from None
    if not args.planner_seeds or not args.levels or not args.arms:
        raise PeelError("--levels, --arms and --planner-seeds must not be empty")
    if args.experiments:
        out = {"benchmark": "safety", "mode": "experiments", "over_n": args.over_n,
               **experiment_cells([Path(d) for d in args.experiments], args.over_n)}
    else:
        out = run(args)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("peel bench safety", main))
