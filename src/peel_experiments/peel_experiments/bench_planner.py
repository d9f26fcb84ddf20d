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

pytorch_mppi (PyPI ``pytorch-mppi``) drives the same model and the same cost: its state is the
model's history window (h x 4) plus the time, flattened; one of its dynamics steps is one horizon
step = ``steps_per_horizon_step`` model steps with the velocity held, and it returns that step's
Eq. 4 + barrier cost in an extra state column that its running cost reads; its terminal cost is
the cost-to-go + phi of :class:`peel_planner_node.cost.Cost`. Its noise covariance is sigma0
(it has no Sigma re-estimation) and its control term is scaled by the same
``control_cost_scale``, so both optimise the same objective.
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
from peel_planner_node.config import GUARDED, UNGUARDED, PlannerConfig, load_planner_config
from peel_planner_node.cost import Cost, Rollouts, episode_cost_terms
from peel_planner_node.dynamics import history_window, learned_dynamics
from peel_planner_node.mppi import Planner, term_influence

CASES: tuple[tuple[int, int], ...] = ((50, 5), (100, 5), (1000, 10))


def load_model() -> tuple[Any, dict[str, Any]]:
    """The shipped checkpoint, else a fresh ``ours`` ForcePredictor (seed 0)."""
    from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
    from peel_model.config import ModelConfig
    from peel_model.predictor import ForcePredictor

    try:
        path = shipped_checkpoint()
        pred = load_checkpoint(path)
        info = {"source": "shipped_checkpoint", "path": str(path)}
    except PeelError:
        torch.manual_seed(0)
        pred = ForcePredictor(ModelConfig())
        info = {"source": "fresh_untrained", "path": None}
    pred.eval()
    info.update({"arch": pred.arch, "h": pred.h,
                 "parameters": int(sum(p.numel() for p in pred.parameters()))})
    return pred, info


class TorchMppiPolicy:
    """pytorch_mppi.MPPI over the forward model and peel's cost (module docstring)."""

    def __init__(self, predictor: Any, cost: Cost, cfg: PlannerConfig, seed: int = 0) -> None:
        from pytorch_mppi import MPPI

        self.pred, self.cost, self.cfg = predictor, cost, cfg
        self.h = int(predictor.h)
        m = cfg.mppi
        self.k, self.dt = m.steps_per_horizon_step, cfg.cost.dt_s
        nx = self.h * 4 + 2  # window, t, cost of the last step
        self.mppi = MPPI(self._dynamics, self._running_cost, nx,
                         torch.tensor([[m.sigma0]]), num_samples=m.n_samples, horizon=m.horizon,
                         lambda_=m.lam, u_min=torch.tensor([m.u_min]),
                         u_max=torch.tensor([m.u_max]), u_init=torch.tensor([m.u_init]),
                         terminal_state_cost=self._terminal)
        inv = 1.0 / m.sigma0
        scale = m.control_cost_scale
        self.mppi._compute_action_cost = lambda noise: scale * m.lam * noise * inv
        self.seed = seed
        self.reset()

    def reset(self) -> None:
        torch.manual_seed(self.seed)
        self.mppi.U = torch.full_like(self.mppi.U, self.cfg.mppi.u_init)

    def _dynamics(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        n = state.shape[0]
        win = state[:, :self.h * 4].reshape(n, self.h, 4)
        t = state[:, -2]
        v = action[:, 0]
        step_cost = torch.zeros(n, dtype=state.dtype)
        for _ in range(self.k):
            f = self.pred.predict(win, v)
            q_before = win[:, -1, 0]
            q = q_before + self.dt * v
            row = torch.stack([q, v, f[:, 0], f[:, 1]], dim=1)
            win = torch.cat([win[:, 1:], row.unsqueeze(1)], dim=1)
            # the running critics (Eq. 4 + barrier) of this one model step, as peel's planner
            one = Rollouts.predicted(q_before, 0.0, row[:, [0, 2, 3]].unsqueeze(1),
                                     self.cost.cfg)
            step_cost = step_cost + self.cost.running_cost(one)
            t = t + self.dt
        return torch.cat([win.reshape(n, -1), t.unsqueeze(1), step_cost.unsqueeze(1)], dim=1)

    @staticmethod
    def _running_cost(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return state[:, -1]

    def _terminal(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """phi + cost-to-go (the terminal critics) of the last state of each sample."""
        last = states[..., -1, :]  # [1, K, nx]
        q = last[..., self.h * 4 - 4].reshape(-1)
        t_end = float(last[..., -2].reshape(-1)[0])
        end = torch.stack([q, torch.zeros_like(q), torch.zeros_like(q)], dim=-1).unsqueeze(1)
        one = Rollouts.predicted(q, t_end - self.dt, end, self.cost.cfg)
        return self.cost.terminal_cost(one).reshape(last.shape[:-1])

    def state(self, history: Trajectory) -> torch.Tensor:
        win = torch.as_tensor(history_window(history, self.h), dtype=torch.float32)
        return torch.cat([win.reshape(-1), torch.tensor([float(history.t[-1]), 0.0])])

    def __call__(self, history: Trajectory) -> float:
        if float(history.q[-1]) >= self.cost.cfg.q_ter_mm:
            return 0.0
        with torch.inference_mode():
            u = self.mppi.command(self.state(history))
        m = self.cfg.mppi
        return float(min(max(float(u.reshape(-1)[0]), m.u_min), m.u_max))


def timing(fn: Any, history: Trajectory, repeats: int,
           warmup: int = 3) -> tuple[float, float, float]:
    """Median and p99 wall time of one call (ms), and the median CPU time of the process
    (all its threads; on a loaded machine less disturbed than the wall time)."""
    for _ in range(warmup):
        fn(history)
    ts, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn(history)
        ts.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return float(np.median(ts)), float(np.percentile(ts, 99)), float(np.median(cpu))


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


def parse_sets(items: list[str]) -> dict[str, Any]:
    """``NAME=VALUE`` pairs -> {name: value} with YAML scalars (numbers, strings)."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise PeelError(f"--set {item!r}: expected NAME=VALUE, e.g. cost.barrier.weight=4")
        out[name.strip()] = yaml.safe_load(value)
    if out:
        load_planner_config().replace(**out)  # unknown names / bad values fail here, named
    return out


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
