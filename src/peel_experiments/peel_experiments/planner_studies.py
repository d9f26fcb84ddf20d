"""The studies of ``peel bench planner`` besides the benchmark (docs/planner.md):
``--cost-study`` (J of peel's variants against pytorch_mppi, paired by task and seed),
``--cost-terms`` (which cost critic drives the plans) and ``--exactness`` (fused against
reference dynamics, against the float64 reference)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import GUARDED, UNGUARDED, load_planner_config
from peel_planner_node.cost import Cost, episode_cost_terms
from peel_planner_node.dynamics import learned_dynamics
from peel_planner_node.mppi import Planner, term_influence

from .bench_common import load_model, parse_sets
from .torch_mppi import TorchMppiPolicy

#: --cost-study variants: peel with one default undone (an ablation of today's defaults, see
#: docs/planner.md), peel configured as pytorch_mppi's algorithm, and two more iterations
STUDY_VARIANTS: dict[str, dict[str, Any]] = {
    "peel": {},
    # white noise over the horizon instead of AR(1) with rho = 0.8
    "peel_white_noise": {"mppi.noise_correlation": 0.0},
    # Eq. 38's control term with the re-estimated Sigma (the paper's literal form)
    "peel_control_estimate": {"mppi.control_cost_sigma": "estimate"},
    # the Sigma floor of the first version
    "peel_sigma_floor_0.25": {"mppi.sigma_min": 0.25},
    # the first version's planner: all three above and the weaker barrier
    "peel_first_version": {"mppi.noise_correlation": 0.0, "mppi.control_cost_sigma": "estimate",
                           "mppi.sigma_min": 0.25, "cost.barrier.weight": 2.0},
    # pytorch_mppi's algorithm: fixed Sigma = sigma0, white noise, shift fill u_init
    "peel_as_pytorch_mppi": {"mppi.sigma_min": 1.0, "mppi.sigma_max": 1.0,
                             "mppi.noise_correlation": 0.0, "mppi.shift_fill": "init"},
    # two MPPI updates per plan() (twice the rollouts)
    "peel_iterations_2": {"mppi.iterations": 2},
    # Eq. 38 with correlated noise (docs/planner.md): the paper's white noise, AR(1) noise with
    # the per-step control term, AR(1) noise with the joint-covariance (precision) term
    "noise_white": {"mppi.noise_correlation": 0.0, "mppi.control_term": "per_step"},
    "noise_ar1_per_step": {"mppi.noise_correlation": 0.8, "mppi.control_term": "per_step"},
    "noise_ar1_joint": {"mppi.noise_correlation": 0.8, "mppi.control_term": "joint"},
    # the planner without the guard of the force limit (docs/planner.md, Eq. M1-M3)
    "peel_unguarded": UNGUARDED,
    "peel_guarded": GUARDED,
}


def _study_settings(args: argparse.Namespace) -> tuple[list[str], dict[str, dict]]:
    """The variant names of --variants (or all) + pytorch_mppi, and each one's overrides."""
    names = [*(args.variants.split(",") if args.variants else STUDY_VARIANTS), "pytorch_mppi"]
    settings = dict(STUDY_VARIANTS)
    for name in names[:-1]:
        if name not in settings:
            if "=" not in name:
                raise PeelError(f"--variants: unknown variant {name!r} (one of "
                                f"{', '.join(STUDY_VARIANTS)}, or NAME=VALUE[+NAME=VALUE...])")
            settings[name] = parse_sets(name.split("+"))
    return names, settings


def _study_episode(env: Any, policy: Any, task: int, cost: Cost) -> dict[str, Any]:
    """One task: J (the paper's), t_cpl, outcome, the mean Sigma in use, the peak force."""
    from peel_sim_node.episode import run_episode

    policy.reset()
    sigmas: list[float] = []

    def pol(hist: Trajectory) -> float:
        u = policy(hist)
        if isinstance(policy, Planner) and policy.stop is None:
            sigmas.append(policy.sigma)
        return u

    traj = run_episode(env, pol, seed=task)
    return {"J": float(episode_cost_terms(traj, cost)["total"]), "t": float(traj.t_cpl),
            "out": traj.outcome, "sigma": float(np.mean(sigmas)) if sigmas else float("nan"),
            "peak": peak_force(traj)}


def _study_summary(name: str, runs: list[dict], ref: np.ndarray, settings: dict,
                   near_miss_n: float, sigma0: float) -> dict[str, Any]:
    """Mean J, its paired difference to pytorch_mppi, outcomes, near misses, peak forces."""
    j = np.asarray([r["J"] for r in runs])
    out, peak = [r["out"] for r in runs], [r["peak"] for r in runs]
    d, k = j - ref, len(ref)
    return {
        "variant": name, "overrides": settings.get(name, {}),
        "episode_cost": round(float(j.mean()), 4),
        "sem": round(float(j.std(ddof=1) / np.sqrt(k)), 4) if k > 1 else None,
        "diff_vs_pytorch_mppi": round(float(d.mean()), 4),
        "diff_sem": round(float(d.std(ddof=1) / np.sqrt(k)), 4) if k > 1 else None,
        "t_cpl_s": round(float(np.mean([r["t"] for r in runs])), 3),
        "done": out.count("done"), "safety_stop": out.count("safety_stop"),
        # a near miss: a task without a safety stop whose peak |F| reached near_miss_n
        "near_miss": sum(1 for o, f in zip(out, peak, strict=True)
                         if o != "safety_stop" and f >= near_miss_n),
        "peak_force_n": {"mean": round(float(np.mean(peak)), 3),
                         "p90": round(float(np.percentile(peak, 90)), 3),
                         "max": round(float(np.max(peak)), 3)},
        "mean_sigma": (round(float(np.nanmean([r["sigma"] for r in runs])), 4)
                       if name != "pytorch_mppi" else sigma0),
        "episode_costs": [round(x, 4) for x in j.tolist()],
    }


def cost_study(args: argparse.Namespace) -> dict[str, Any]:
    """Episode cost J of peel variants and pytorch_mppi over tasks x planner seeds at one (N, H).

    Each variant plans with its own settings (cost critics included); J is always the paper's
    (the base config's paper critics). Every (task, seed) pair is run by every variant, so
    differences are paired. Reports per variant the mean J, its standard error over the task x
    seed runs, the paired mean difference to pytorch_mppi with its standard error, t_cpl,
    outcomes, near misses (``--near-miss-n``), peak forces and the mean Sigma in use.
    """
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv

    torch.set_num_threads(args.threads)
    pred, model_info = load_model()
    n, h = args.study_n, args.study_h
    base = load_planner_config().replace(**{**args.set, "mppi.n_samples": n, "mppi.horizon": h})
    cost = Cost(base.cost)
    tasks = list(range(args.first_task, args.first_task + args.tasks))
    pseeds = list(range(args.seeds))
    names, settings = _study_settings(args)
    res: dict[str, list[dict]] = {k: [] for k in names}
    env = PeelEnv(load_sim_config(), seed=0)
    bar = tqdm(total=len(names) * len(tasks) * len(pseeds), desc="cost study",
               disable=not args.progress, file=sys.stderr)
    try:
        for name in names:
            for ps in pseeds:
                if name == "pytorch_mppi":
                    policy: Any = TorchMppiPolicy(pred, cost, base, seed=ps)
                else:
                    cfg = base.replace(**{**settings[name], "mppi.seed": ps})
                    policy = Planner(learned_dynamics(pred, cfg.dynamics), Cost(cfg.cost), cfg)
                for task in tasks:
                    res[name].append(_study_episode(env, policy, task, cost))
                    bar.update(1)
    finally:
        bar.close()
        env.close()
    ref = np.asarray([r["J"] for r in res["pytorch_mppi"]])
    return {"benchmark": "planner_cost_study", "model": model_info, "n": n, "h": h,
            "base_overrides": args.set, "near_miss_n": args.near_miss_n,
            "tasks": tasks, "planner_seeds": pseeds, "runs_per_variant": len(ref),
            "variants": [_study_summary(name, res[name], ref, settings, args.near_miss_n,
                                        base.mppi.sigma0) for name in names]}


def peak_force(traj: Trajectory) -> float:
    """The largest measured |F_RX| or |F_RZ| of a task, N."""
    return float(max(np.max(np.abs(traj.fx)), np.max(np.abs(traj.fz))))


def cost_terms(args: argparse.Namespace) -> dict[str, Any]:
    """Which cost critic drives the plans: over ``--tasks`` simulator tasks with the default
    planner at (``--study-n``, ``--study-h``), per plan the reduction of each term by the
    weighting (mean over the N samples minus its omega-weighted mean, ``term_influence``),
    including Eq. 38's control term; reports the mean reduction per term, how often each term
    is the largest, and the omega-weighted mean of each term."""
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv
    from peel_sim_node.episode import run_episode

    torch.set_num_threads(args.threads)
    pred, model_info = load_model()
    cfg = load_planner_config().replace(**{**args.set, "mppi.n_samples": args.study_n,
                                           "mppi.horizon": args.study_h})
    planner = Planner(learned_dynamics(pred, cfg.dynamics), Cost(cfg.cost), cfg)
    tasks = list(range(args.first_task, args.first_task + args.tasks))
    rows: list[dict[str, float]] = []
    weighted: list[dict[str, float]] = []

    def policy(hist: Trajectory) -> float:
        u = planner.plan(hist)
        last = planner.last
        if planner.stop is None and last:
            terms = {**last["terms"], "control": last["control"]}
            rows.append(term_influence(terms, last["omega"]))
            weighted.append({k: float(last["omega"].to(v.dtype) @ v) for k, v in terms.items()})
            planner.last = {}
        return u

    env = PeelEnv(load_sim_config(), seed=0)
    try:
        for task in tqdm(tasks, desc="cost terms", disable=not args.progress, file=sys.stderr):
            planner.reset()
            run_episode(env, policy, seed=task)
    finally:
        env.close()
    names = list(rows[0]) if rows else []
    top = [max(r, key=r.get) for r in rows]
    return {"benchmark": "planner_cost_terms", "model": model_info, "n": args.study_n,
            "h": args.study_h, "tasks": tasks, "plans": len(rows), "base_overrides": args.set,
            "terms": {name: {
                "mean_reduction": round(float(np.mean([r[name] for r in rows])), 5),
                "median_reduction": round(float(np.median([r[name] for r in rows])), 5),
                "largest_reduction_share": round(top.count(name) / len(rows), 4),
                "weighted_mean": round(float(np.mean([r[name] for r in weighted])), 4),
            } for name in names}}


def exactness(args: argparse.Namespace) -> dict[str, Any]:
    """Fused vs reference dynamics on the model from a simulator history, commands uniform in
    0.5-8 mm/s: each in float32 and float64 against the float64 reference (max and quantiles
    of each sample's largest force error, N)."""
    import copy

    from peel_planner_node.config import DynamicsConfig, FusedConfig
    from peel_planner_node.dynamics import ReferenceDynamics
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv

    torch.set_num_threads(args.threads)
    pred, model_info = load_model()
    pred64 = copy.deepcopy(pred).double()
    env = PeelEnv(load_sim_config(), seed=0)
    cases = {}
    try:
        for seed, (n, s) in ((1000, (50, 25)), (1001, (1000, 50))):
            env.reset(seed=seed)
            for _ in range(20):
                env.step(2.0)
            hist = env.history
            v = 0.5 + 7.5 * torch.rand(n, s, generator=torch.Generator().manual_seed(seed),
                                       dtype=torch.float64)
            want = ReferenceDynamics(pred64).rollout(hist, v)
            runs = {"reference_float32": ReferenceDynamics(pred).rollout(hist, v.float()),
                    **{f"fused_{dt}": learned_dynamics(pred, DynamicsConfig(
                        fused=FusedConfig(dtype=dt))).rollout(hist, v.to(torch.float64 if dt
                                                                         == "float64" else
                                                                         torch.float32))
                       for dt in ("float32", "float64")}}
            cases[f"{n}x{s}"] = {name: _errors(out.double() - want) for name, out in runs.items()}
    finally:
        env.close()
    return {"benchmark": "planner_exactness", "model": model_info,
            "against": "reference dynamics in float64", "cases": cases}


def _errors(diff: torch.Tensor) -> dict[str, float]:
    per_sample = diff[..., 1:].abs().amax(dim=(1, 2))
    return {"max_n": float(per_sample.max()), "median_n": float(per_sample.median()),
            "p99_n": float(per_sample.quantile(0.99)), "q_max_mm": float(diff[..., 0].abs().max())}
