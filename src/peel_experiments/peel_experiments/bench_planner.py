"""``peel bench planner``: plan() latency and episode cost, peel's OL-MPPI vs pytorch_mppi.

For each (N, H) in (50, 5), (100, 5), (1000, 10) and each implementation:

* ``median_ms`` / ``p99_ms``: wall time of one planning call (``Planner.plan`` for peel,
  ``MPPI.command`` for pytorch_mppi) from a fixed simulator history, on CPU with the real forward
  model (the shipped checkpoint when it exists, else a freshly initialised ``ours`` model: the
  JSON says which);
* ``episode_cost``: mean J (Eq. 3) over the same simulator tasks (seeds 0..tasks-1) driven by that
  planner, each task with ``--seeds`` planner noise seeds (3: 30 episodes per case; peel's
  ``mppi.seed`` and pytorch_mppi's torch seed), with ``t_cpl_s`` and outcomes beside it; the
  ``goals`` hold the paired difference peel - pytorch_mppi and its standard error (with one seed
  per task the difference of 10 episodes was mostly planner noise: +-0.4 per task).

The pytorch_mppi arm: :mod:`.torch_mppi`; ``--cost-study``, ``--cost-terms`` and
``--exactness``: :mod:`.planner_studies`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from peel_msgs_py.cliargs import ArgumentParser, nonnegative_int, positive_int, run_main
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import load_planner_config
from peel_planner_node.cost import Cost, episode_cost_terms
from peel_planner_node.dynamics import learned_dynamics
from peel_planner_node.mppi import Planner

from .bench_common import load_model, parse_sets, timing
from .planner_studies import cost_study, cost_terms, exactness
from .torch_mppi import TorchMppiPolicy

CASES: tuple[tuple[int, int], ...] = ((50, 5), (100, 5), (1000, 10))


def _case(policy_of: Any, env: Any, hist: Trajectory, cost: Cost, tasks: list[int],
          pseeds: list[int], reps: int) -> dict[str, Any]:
    """Timing from the fixed history, then every task with every planner noise seed."""
    from peel_sim_node.episode import run_episode

    med, p99, cpu = timing(policy_of(0), hist, reps)
    costs, tcpl, outcomes = [], [], []
    for ps in pseeds:  # every task with every planner noise seed (paired)
        policy = policy_of(ps)
        for seed in tasks:
            policy.reset()
            traj = run_episode(env, policy, seed=seed)
            costs.append(float(episode_cost_terms(traj, cost)["total"]))
            tcpl.append(traj.t_cpl)
            outcomes.append(traj.outcome)
    return {"median_ms": round(med, 3), "p99_ms": round(p99, 3), "cpu_ms": round(cpu, 3),
            "timing_calls": reps,
            "episode_cost": round(float(np.mean(costs)), 4),
            "episode_costs": [round(c, 4) for c in costs],
            "t_cpl_s": round(float(np.mean(tcpl)), 3), "outcomes": outcomes}


def _goals(by: dict, cases: tuple[tuple[int, int], ...]) -> dict[str, Any]:
    """Per case: latency ratio to pytorch_mppi (goal <= 0.25) and the paired cost difference."""
    goals: dict[str, Any] = {}
    for n, h in cases:
        ours, theirs = by[("peel", n, h)], by[("pytorch_mppi", n, h)]
        diff = np.asarray(ours["episode_costs"]) - np.asarray(theirs["episode_costs"])
        ratio = ours["median_ms"] / theirs["median_ms"]
        goals[f"{n}x{h}"] = {
            "latency_ratio": round(ratio, 4), "latency_ratio_le_0.25": ratio <= 0.25,
            # CPU time of all threads: peel's workers add up, so this is no latency
            "cpu_time_ratio": round(ours["cpu_ms"] / theirs["cpu_ms"], 4),
            "cost_not_higher": ours["episode_cost"] <= theirs["episode_cost"],
            # paired over the same (task, planner seed) episodes
            "cost_diff": round(float(diff.mean()), 4),
            "cost_diff_sem": (round(float(diff.std(ddof=1) / np.sqrt(len(diff))), 4)
                              if len(diff) > 1 else None),
            # J of a safety-stopped task (phi_fail = 2, short) can undercut a finished one:
            # read cost_not_higher together with how many tasks each finished
            "peel_done": ours["outcomes"].count("done"),
            "pytorch_mppi_done": theirs["outcomes"].count("done"),
        }
    return goals


def matmul_peak_gflops(threads: int, repeats: int = 5) -> float:
    """The best float32 matmul throughput torch reaches here on ``threads`` threads: square
    products of 256..2048, best of ``repeats`` each (GFLOP/s, 2 FLOP per multiply-add)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    best = 0.0
    try:
        for size in (256, 512, 1024, 2048):
            a, b = torch.randn(size, size), torch.randn(size, size)
            c = torch.mm(a, b)
            for _ in range(repeats):
                t0 = time.perf_counter()
                torch.mm(a, b, out=c)
                best = max(best, 2.0 * size ** 3 / (time.perf_counter() - t0) / 1e9)
    finally:
        torch.set_num_threads(before)
    return best


def flop_floor(pred: Any, by: dict, cases: tuple[tuple[int, int], ...],
               steps_per_horizon_step: int) -> dict[str, Any]:
    """The FLOP-limited floor of each case: multiply-adds per plan (N x H x k model steps)
    over the measured matmul peak, on one core and on all cores, beside the measured median."""
    from peel_planner_node.flops import fused_macs_per_step, model_macs_per_step

    cores = os.cpu_count() or 1
    peak = {1: matmul_peak_gflops(1), cores: matmul_peak_gflops(cores)}
    per_step = {"model": model_macs_per_step(pred)}
    try:
        per_step["fused"] = fused_macs_per_step(pred)
    except AttributeError:  # a model the fused rollout does not support
        per_step["fused"] = None
    out: dict[str, Any] = {"peak_gflops": {f"{k}_threads": round(v, 1) for k, v in peak.items()},
                           "macs_per_model_step": per_step, "cases": {}}
    for n, h in cases:
        macs = n * h * steps_per_horizon_step * (per_step["fused"] or per_step["model"])
        floor = {f"floor_ms_{k}_threads": round(2.0 * macs / (v * 1e9) * 1e3, 3)
                 for k, v in peak.items()}
        median = by[("peel", n, h)]["median_ms"]
        out["cases"][f"{n}x{h}"] = {"macs_per_plan": int(macs), **floor, "median_ms": median,
                                    "median_over_floor_all_cores":
                                    round(median / floor[f"floor_ms_{cores}_threads"], 2)}
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv

    torch.set_num_threads(args.threads)
    pred, model_info = load_model()
    base = load_planner_config()
    cases = CASES[:2] if args.quick else CASES
    tasks, pseeds = list(range(args.tasks)), list(range(args.seeds))
    env = PeelEnv(load_sim_config(), seed=0)
    by: dict[tuple[str, int, int], dict[str, Any]] = {}
    bar = tqdm(total=len(cases) * 2, desc="bench planner", disable=not args.progress,
               file=sys.stderr)
    try:
        env.reset(seed=1000)
        for _ in range(20):
            env.step(2.0)
        hist = env.history
        for n, h in cases:
            cfg = base.replace(**{"mppi.n_samples": n, "mppi.horizon": h})
            cost = Cost(cfg.cost)
            impls = {
                "peel": lambda ps, cfg=cfg, cost=cost: Planner(
                    learned_dynamics(pred, cfg.dynamics), cost,
                    cfg.replace(**{"mppi.seed": ps})),
                "pytorch_mppi": lambda ps, cfg=cfg, cost=cost: TorchMppiPolicy(pred, cost, cfg,
                                                                               seed=ps),
            }
            for name, make in impls.items():
                reps = max(5, args.repeats // (10 if n >= 1000 else 1))
                by[(name, n, h)] = {"impl": name, "n": n, "h": h,
                                    **_case(make, env, hist, cost, tasks, pseeds, reps)}
                bar.update(1)
    finally:
        bar.close()
        env.close()
    from peel_planner_node.native_loop import status as native_status

    floor = (flop_floor(pred, by, cases, base.mppi.steps_per_horizon_step)
             if args.floor else None)
    return {"benchmark": "planner", "model": model_info, "threads": args.threads,
            "native_loop": native_status(), "load_avg_1min": round(os.getloadavg()[0], 2),
            "device": "cpu", "torch": torch.__version__, "tasks": tasks,
            "planner_seeds": pseeds, "episodes_per_case": len(tasks) * len(pseeds),
            "planner_config": base.as_dict(), "cases": list(by.values()),
            "goals": _goals(by, cases), "flop_floor": floor}


def main(argv: list[str] | None = None) -> int:
    """``peel bench planner [--json] [--quick] [--tasks N] [--repeats N] [--threads N]``."""
    ap = ArgumentParser(prog="peel bench planner", description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object (default)")
    ap.add_argument("--quick", action="store_true",
                    help="small version: cases (50,5) and (100,5), 2 tasks, 20 timing calls")
    ap.add_argument("--tasks", type=positive_int, default=None, help="simulator tasks per case (10)")
    ap.add_argument("--repeats", type=positive_int, default=None, help="timed calls per case (100)")
    ap.add_argument("--threads", type=positive_int, default=1,
                    help="torch CPU threads (1: on a shared 2-core machine 2 threads contend)")
    ap.add_argument("--progress", action="store_true", help="tqdm progress bar on stderr")
    ap.add_argument("--cost-study", action="store_true",
                    help="instead of the benchmark: J of peel variants vs pytorch_mppi over "
                         "--tasks x --seeds at (--study-n, --study-h)")
    ap.add_argument("--seeds", type=positive_int, default=3,
                    help="planner noise seeds per task (both implementations, paired; 3)")
    ap.add_argument("--first-task", type=nonnegative_int, default=0,
                    help="--cost-study: simulator task seeds first-task .. first-task+tasks-1")
    ap.add_argument("--study-n", type=positive_int, default=50, help="N for --cost-study")
    ap.add_argument("--study-h", type=positive_int, default=5, help="H for --cost-study")
    ap.add_argument("--variants", default="",
                    help="comma-separated --cost-study variants (default: all)")
    ap.add_argument("--cost-terms", action="store_true",
                    help="instead of the benchmark: which cost critic drives the plans over "
                         "--tasks at (--study-n, --study-h)")
    ap.add_argument("--exactness", action="store_true",
                    help="instead of the benchmark: fused vs reference dynamics against the "
                         "float64 reference")
    ap.add_argument("--near-miss-n", type=float, default=18.0,
                    help="--cost-study: a task without a safety stop whose peak |F| reaches "
                         "this (N) is a near miss (18 = 90 %% of the 20 N prewarning)")
    ap.add_argument("--no-floor", action="store_true",
                    help="skip the FLOP-limited floor (matmul peak measurement)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="--cost-study: planner parameter for every variant and pytorch_mppi "
                         "(e.g. cost.barrier.weight=4); repeatable")
    args = ap.parse_args(argv)
    args.set = parse_sets(args.set)
    if args.tasks is None:
        args.tasks = 2 if args.quick else 10
    if args.quick:
        args.seeds = 1
    if args.repeats is None:
        args.repeats = 20 if args.quick else 100
    for name in ("tasks", "repeats", "threads", "seeds", "study_n", "study_h"):
        if getattr(args, name) < 1:
            raise PeelError(f"--{name.replace('_', '-')} must be at least 1")
    args.floor = not args.no_floor
    if args.near_miss_n <= 0 or not np.isfinite(args.near_miss_n):
        raise PeelError("--near-miss-n must be a positive number of newtons")
    job = (cost_study if args.cost_study else cost_terms if args.cost_terms
           else exactness if args.exactness else run)
    print(json.dumps(job(args), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("peel bench planner", main))
