"""The paper's experiments on the plant: 20 consecutive peels per method (4.4) and Table 2 (4.5).

``run_experiment`` peels, for every method and seed, ``tasks`` consecutive substrates on the
*plant* (``PeelEnv(source="plant")``), all starting from the same pretrained checkpoint:

* ``ol-mppi``: after every peel the model is updated with Algorithm 1
  (:class:`model_learner_node.maml.MetaLearner`); the replay pool holds the earlier peels;
* ``ol-mppi-fast``: ``ol-mppi`` plus the fast step inside every peel
  (:mod:`peel_experiments.fast_arm`, :mod:`model_learner_node.fast_step`);
* ``baseline1``: the model is never updated (the original MPPI);
* ``baseline2``: after every peel the model is retrained on all peels so far
  (:class:`model_learner_node.baselines2.HistoryRetrainer`);
* ``oracle``: the same MPPI with the plant's true dynamics (:mod:`peel_experiments.oracle`).

Same substrates for every method: task k of seed s uses plant parameters drawn by
``sample_params(cfg, default_rng([s, 0, k]), "plant")``, sensor-noise seed and planner noise seed
derived from (s, k) alone. Each (seed, method) is one independent job with its own seeds and one
torch thread, so the results do not depend on ``workers``.

Per task (``results.json``): ``cost`` (J, Eq. 3, :func:`peel_planner_node.cost.episode_cost`),
``t_cpl``, ``sum_fx``, ``sum_fz`` (Table 1), ``outcome``, ``model_version`` (the version of the
model that planned this task: 0 = pretrained), ``update_s`` (wall time of the update that produced
that model, 0 for the pretrained model and the methods that never update), ``planner_guard``
(what the guard of the force limit did in the task, also in the trajectory's meta:
:meth:`peel_planner_node.guard.GuardStats.as_dict`).

``run_sweep`` is Table 2: the OL-MPPI model of the last task, one peel per (value, seed) on fresh
plant substrates, N, H and lambda varied one at a time around the planner defaults.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.task import mppi_seed, task_seed
from peel_msgs_py.trajectory import Trajectory

from .experiment_config import (
    METHODS,
    ORACLE,
    ExperimentConfig,
    check_methods,
    load_experiment_config,
)

# ------------------------------------------------------------------------------ setup


@dataclass(frozen=True)
class Setup:
    """Everything a job needs, picklable (config override files are paths, not objects)."""

    checkpoint: str
    tasks: int
    planner_params: dict[str, Any]
    sim_overrides: str | None = None
    learner_overrides: str | None = None
    out_dir: str | None = None
    save_model: bool = True
    substrate_stream: int = 0  # 0: the experiment's substrates, 1: the sweep's
    maml_changes: dict[str, Any] = field(default_factory=dict)
    fast_changes: dict[str, Any] = field(default_factory=dict)  # online.* of ol-mppi-fast
    baseline2_changes: dict[str, Any] = field(default_factory=dict)
    plant_level: int | None = None  # None: plant.level of the simulator config
    sequence: str = "stationary"
    effects: tuple[str, ...] = ()  # user effects module:function added to the plant


def substrates(sim_cfg: Any, seed: int, n: int, stream: int = 0, level: int | None = None,
               sequence: str = "stationary") -> list[dict[str, float]]:
    """Plant parameters of the n substrates of ``seed`` (one per task): drawn from the 3.2.1
    intervals of plant severity ``level``, then changed over the peels as ``sequence`` says
    (:func:`peel_sim_node.plant.sequence_params`). The draws do not depend on the sequence, so
    the sequences of one seed peel the same substrates until the process changes."""
    from peel_sim_node.env import sample_params
    from peel_sim_node.plant import sequence_params

    return [sequence_params(sim_cfg, dict(sample_params(
        sim_cfg, np.random.default_rng([seed, stream, k]), "plant", level)), k + 1, sequence)
        for k in range(n)]


def planner_params(base: Mapping[str, Any] | None = None, *, n_samples: int | None = None,
                   horizon: int | None = None, lam: float | None = None,
                   planner_overrides: str | None = None) -> dict[str, Any]:
    """Flat planner parameters: the shipped YAML (+ override file) with N, H, lambda set."""
    from peel_planner_node.config import load_planner_config

    params = dict(base) if base is not None else load_planner_config(planner_overrides).to_params()
    if n_samples is not None:
        params["mppi.n_samples"] = int(n_samples)
    if horizon is not None:
        params["mppi.horizon"] = int(horizon)
    if lam is not None:
        params["mppi.lambda"] = float(lam)
    return params


def _trajectory_record(traj: Trajectory, cost_value: float) -> dict[str, Any]:
    return {
        "cost": float(cost_value),
        "t_cpl": traj.t_cpl,
        "sum_fx": traj.sum_fx,
        "sum_fz": traj.sum_fz,
        "max_abs_fx": float(np.abs(traj.fx).max()) if len(traj) else 0.0,
        "max_abs_fz": float(np.abs(traj.fz).max()) if len(traj) else 0.0,
        "q_end": float(traj.q[-1]) if len(traj) else 0.0,
        "n_samples": len(traj),
        "outcome": traj.outcome,
    }


def _trace(traj: Trajectory) -> dict[str, list[float]]:
    return {k: [float(x) for x in getattr(traj, k)] for k in ("t", "q", "v", "u", "fx", "fz")}


def _updater(method: str, predictor: Any, setup: Setup) -> Any:
    """The method's between-peel update as model_learner_node runs it: Algorithm 1 behind the
    held-out check (``gate.*``), baseline 2 as the paper has it; None for the others."""
    if method in ("ol-mppi", "ol-mppi-fast"):
        from model_learner_node.gate import HeldOutGate, load_gate_config
        from model_learner_node.maml import MetaLearner, load_maml_config

        meta = MetaLearner(predictor, load_maml_config(setup.learner_overrides,
                                                       **setup.maml_changes))
        return HeldOutGate(meta, predictor, load_gate_config(setup.learner_overrides))
    if method == "baseline2":
        from model_learner_node.baselines2 import HistoryRetrainer, load_baseline2_config

        return HistoryRetrainer(predictor, load_baseline2_config(setup.learner_overrides,
                                                                 **setup.baseline2_changes))
    return None


def run_job(method: str, seed: int, setup: Setup,
            progress: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """``setup.tasks`` consecutive peels of one method on the substrates of one seed."""
    import torch

    from model_learner_node.replay import ReplayPool
    from peel_model.checkpoint import load_checkpoint, save_checkpoint
    from peel_planner_node.config import PlannerConfig
    from peel_planner_node.cost import Cost, episode_cost
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.effects import load_effects
    from peel_sim_node.env import PeelEnv
    from peel_sim_node.episode import run_episode

    from .fast_arm import FastPolicy, fast_stepper, task_record
    from .oracle import learned_planner, oracle_planner

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    sim_cfg = load_sim_config(setup.sim_overrides)
    subs = substrates(sim_cfg, seed, setup.tasks, setup.substrate_stream, setup.plant_level,
                      setup.sequence)
    pcfg = PlannerConfig.from_params(setup.planner_params)
    cost = Cost(pcfg.cost)
    predictor = None if method == ORACLE else load_checkpoint(setup.checkpoint)
    updater = None if predictor is None else _updater(method, predictor, setup)
    stepper = fast_stepper(method, predictor, setup.learner_overrides, setup.fast_changes)
    pretrained = load_checkpoint(setup.checkpoint) if stepper is not None else None
    pool = ReplayPool()
    version, update_s = 0, 0.0
    records: list[dict[str, Any]] = []
    last: Trajectory | None = None
    model_path = None
    previous: Any = None  # the last task's planner (Eq. M8 carries its margin window)
    env = PeelEnv(sim_cfg, source="plant", seed=task_seed(seed, 0, setup.substrate_stream),
                  params=subs[0], level=setup.plant_level, effects=load_effects(setup.effects))
    try:
        for k, params in enumerate(subs):
            ts = task_seed(seed, k, setup.substrate_stream)
            cfg_k = pcfg.replace(**{"mppi.seed": mppi_seed(seed, k, setup.substrate_stream)})
            planner = (oracle_planner(env, cfg_k, cost) if predictor is None
                       else learned_planner(predictor, cfg_k, cost))
            planner.reset()
            planner.carry_from(previous)
            previous = planner
            plan_times: list[float] = []

            def policy(history: Trajectory, planner: Any = planner,
                       plan_times: list[float] = plan_times) -> float:
                t0 = time.perf_counter()
                u = planner.plan(history)
                plan_times.append(time.perf_counter() - t0)
                return u

            if stepper is not None:
                stepper.start(k + 1)
                policy = FastPolicy(planner, stepper, pcfg.dynamics, plan_times)
            t0 = time.perf_counter()
            traj = run_episode(env, policy, seed=ts, params=params)
            episode_s = time.perf_counter() - t0
            j = episode_cost(traj, cost)
            traj.meta = {**traj.meta, "cost": j, "task": k + 1, "method": method, "seed": seed,
                         "model_version": version, "planner_guard": planner.guard.as_dict()}
            rec = {"task": k + 1, **_trajectory_record(traj, j), "model_version": version,
                   "planner_guard": traj.meta["planner_guard"],
                   "slowdown": traj.meta.get("slowdown"),
                   "update_s": update_s, "plan_s": float(np.mean(plan_times)) if plan_times
                   else 0.0, "episode_s": episode_s, "substrate": params}
            if stepper is not None:
                rec["fast"] = task_record(traj, policy, pretrained)
            last = traj
            if k == setup.tasks - 1 and method == "ol-mppi" and setup.save_model \
                    and setup.out_dir is not None:
                model_path = str(save_checkpoint(
                    Path(setup.out_dir) / f"ol_mppi_task{k + 1}_seed{seed}.safetensors",
                    predictor, meta={"source": "peel experiment", "method": method,
                                     "seed": seed, "task": k + 1, "model_version": version,
                                     "pretrained": setup.checkpoint}))
            if updater is not None and k < setup.tasks - 1:
                report = updater.update(traj, pool)
                version = int(report.get("version", version))
                update_s = float(report["update_s"])
                rec["update"] = {key: report[key] for key in
                                 ("updated", "query_loss_before", "query_loss_after", "chosen",
                                  "loss_first", "loss_last", "n_history", "reason", "gate")
                                 if key in report}
                rec["next_update_s"] = update_s
            pool.add(traj)
            records.append(rec)
            if progress is not None:
                progress({"method": method, "seed": seed, **rec})
    finally:
        env.close()
    return {"method": method, "seed": seed, "tasks": records,
            "trace": _trace(last) if last is not None else {}, "model_path": model_path}


def _run_job_star(args: tuple[str, int, Setup]) -> dict[str, Any]:
    return run_job(*args)


def run_jobs(jobs: Sequence[tuple[str, int]], setup: Setup, workers: int = 1,
             desc: str = "peels") -> list[dict[str, Any]]:
    """Run (method, seed) jobs serially or in ``workers`` processes (same results either way)."""
    from tqdm import tqdm

    if workers <= 1 or len(jobs) <= 1:
        out = []
        with tqdm(total=len(jobs) * setup.tasks, desc=desc, unit="peel") as bar:
            for method, seed in jobs:
                def tick(rec: dict[str, Any]) -> None:
                    bar.set_postfix_str(f"{rec['method']} s{rec['seed']} J={rec['cost']:.2f}")
                    bar.update(1)
                out.append(run_job(method, seed, setup, tick))
        return out
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as ex:
        futures = ex.map(_run_job_star, [(m, s, setup) for m, s in jobs])
        return list(tqdm(futures, total=len(jobs), desc=desc, unit="job"))


# ------------------------------------------------------------------------------ experiment


def plant_description(sim_overrides: str | None, level: int | None) -> dict[str, Any]:
    """The plant level an experiment ran on: number, name and every value that differs from
    the simulator (docs/simulator.md)."""
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.plant import plant_spec

    cfg = load_sim_config(sim_overrides)
    spec = plant_spec(cfg, level)
    return {"level": spec.level, "name": spec.name, "spec": asdict(spec),
            "sequence_params": dict(cfg.sequence._values)}


def run_experiment(cfg: ExperimentConfig, *, checkpoint: str | os.PathLike[str], out: Path,
                   sim_overrides: str | None = None, planner_overrides: str | None = None,
                   learner_overrides: str | None = None, command: str = "",
                   maml_changes: Mapping[str, Any] | None = None,
                   baseline2_changes: Mapping[str, Any] | None = None,
                   effects: Sequence[str] = ()) -> dict[str, Any]:
    """Run every method (and the oracle) on every seed; write results.json, figures, report.
    ``effects``: user effects (``module:function``) added to the plant of every job."""
    from peel_sim_node.plant import check_level, check_sequence

    from . import report as rp

    check_methods(cfg.methods)
    if cfg.plant_level is not None:
        check_level(cfg.plant_level)
    check_sequence(cfg.sequence)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pparams = planner_params(n_samples=cfg.n_samples, horizon=cfg.horizon, lam=cfg.lam,
                             planner_overrides=planner_overrides)
    setup = Setup(checkpoint=str(checkpoint), tasks=cfg.tasks, planner_params=pparams,
                  sim_overrides=sim_overrides, learner_overrides=learner_overrides,
                  out_dir=str(out), save_model=cfg.save_model,
                  maml_changes=dict(maml_changes or {}),
                  baseline2_changes=dict(baseline2_changes or {}),
                  plant_level=cfg.plant_level, sequence=cfg.sequence, effects=tuple(effects))
    methods = list(cfg.methods) + ([ORACLE] if cfg.oracle else [])
    jobs = [(m, s) for s in cfg.seeds for m in methods]
    t0 = time.perf_counter()
    results_list = run_jobs(jobs, setup, cfg.workers, desc="experiment")
    wall = time.perf_counter() - t0
    runs: dict[str, dict[str, list[dict[str, Any]]]] = {}
    traces: dict[str, Any] = {}
    model_paths: dict[str, str] = {}
    for r in results_list:
        runs.setdefault(str(r["seed"]), {})[r["method"]] = r["tasks"]
        if r["seed"] == cfg.seeds[0]:
            traces[r["method"]] = r["trace"]
        if r["model_path"]:
            model_paths[str(r["seed"])] = r["model_path"]
    if len(cfg.seeds) == 1:
        agg = {m: runs[str(cfg.seeds[0])][m] for m in methods}
    else:
        agg = rp.aggregate({s: {m: runs[s][m] for m in methods} for s in runs})
    ups = [rec["next_update_s"] for s in runs for m in runs[s] for rec in runs[s][m]
           if "next_update_s" in rec and m == "ol-mppi"]
    ups2 = [rec["next_update_s"] for s in runs for m in runs[s] for rec in runs[s][m]
            if "next_update_s" in rec and m == "baseline2"]
    plans = [rec["plan_s"] for s in runs for m in runs[s] for rec in runs[s][m]]
    results: dict[str, Any] = {
        "command": command,
        "tasks": cfg.tasks,
        "seeds": list(cfg.seeds),
        "checkpoint": str(checkpoint),
        "effects": list(effects),
        "planner": {"n_samples": cfg.n_samples, "horizon": cfg.horizon, "lambda": cfg.lam},
        "plant": plant_description(sim_overrides, cfg.plant_level),
        "sequence": cfg.sequence,
        "config": {**asdict(cfg), "planner_params": pparams},
        "methods": {m: {"tasks": agg[m]} for m in methods},
        "runs": {s: {m: {"tasks": runs[s][m]} for m in methods} for s in runs},
        "traces": traces,
        "task20_model": model_paths.get(str(cfg.seeds[0])),
        "task20_models": model_paths,
        "timing": {
            "wall_s": wall,
            "ol_mppi_update_s_mean": float(np.mean(ups)) if ups else None,
            "ol_mppi_update_s_max": float(np.max(ups)) if ups else None,
            "baseline2_update_s_mean": float(np.mean(ups2)) if ups2 else None,
            "plan_s_mean": float(np.mean(plans)) if plans else None,
            "workers": cfg.workers,
            "torch_threads_per_job": 1,
        },
    }
    flat = {m: agg[m] for m in methods}
    results["table1"] = rp.table1(flat)
    results["gap_to_oracle"] = rp.gaps_to_oracle(flat)
    results["targets"] = rp.evaluate_targets(flat, runs)
    paths = rp.write_experiment_outputs(results, out)
    results["files"] = {k: str(v) for k, v in paths.items()}
    return results


# ------------------------------------------------------------------------------ sweep (Table 2)


def run_sweep(cfg: ExperimentConfig, *, checkpoint: str | os.PathLike[str], out: Path,
              sim_overrides: str | None = None, planner_overrides: str | None = None,
              command: str = "", effects: Sequence[str] = ()) -> dict[str, Any]:
    """Table 2: one peel per (factor value, seed) with the given model, no learning."""
    from . import report as rp

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = planner_params(n_samples=cfg.n_samples, horizon=cfg.horizon, lam=cfg.lam,
                          planner_overrides=planner_overrides)
    factors = {"N": ("mppi.n_samples", cfg.sweep_n), "H": ("mppi.horizon", cfg.sweep_h),
               "lambda": ("mppi.lambda", cfg.sweep_lambda)}
    setups: list[tuple[str, float, Setup]] = []
    for name, (key, values) in factors.items():
        for val in values:
            params = dict(base)
            params[key] = type(base[key])(val)
            setups.append((name, float(val), Setup(
                checkpoint=str(checkpoint), tasks=1, planner_params=params,
                sim_overrides=sim_overrides, save_model=False, substrate_stream=1,
                effects=tuple(effects))))
    from tqdm import tqdm

    jobs = [(name, val, st, s) for name, val, st in setups for s in cfg.sweep_seeds]
    t0 = time.perf_counter()
    outs: list[dict[str, Any]] = []
    if cfg.workers <= 1:
        for _name, _val, st, s in tqdm(jobs, desc="sweep", unit="peel"):
            outs.append(run_job("baseline1", s, st))
    else:
        import multiprocessing as mp

        with ProcessPoolExecutor(max_workers=cfg.workers,
                                 mp_context=mp.get_context("spawn")) as ex:
            outs = list(tqdm(ex.map(_run_job_star, [("baseline1", s, st)
                                                     for _, _, st, s in jobs]),
                             total=len(jobs), desc="sweep", unit="peel"))
    wall = time.perf_counter() - t0
    table: dict[str, list[dict[str, Any]]] = {n: [] for n in factors}
    raw: list[dict[str, Any]] = []
    for (name, val, _, s), res in zip(jobs, outs, strict=True):
        rec = res["tasks"][0]
        raw.append({"factor": name, "value": val, "seed": s, **rec})
    for name, (_, values) in factors.items():
        for val in values:
            recs = [r for r in raw if r["factor"] == name and r["value"] == float(val)]
            c = np.array([r["cost"] for r in recs])
            table[name].append({
                "value": float(val), "n": len(recs),
                "cost_mean": float(c.mean()), "cost_std": float(c.std()),
                "cost_min": float(c.min()), "cost_max": float(c.max()),
                "t_cpl_mean": float(np.mean([r["t_cpl"] for r in recs])),
                "sum_fx_mean": float(np.mean([r["sum_fx"] for r in recs])),
                "sum_fz_mean": float(np.mean([r["sum_fz"] for r in recs])),
                "plan_s_mean": float(np.mean([r["plan_s"] for r in recs])),
                "safety_stops": sum(r["outcome"] == "safety_stop" for r in recs),
                "outcomes": [r["outcome"] for r in recs],
            })
    sweep = {"command": command, "checkpoint": str(checkpoint), "effects": list(effects),
             "seeds": list(cfg.sweep_seeds),
             "defaults": {"N": cfg.n_samples, "H": cfg.horizon, "lambda": cfg.lam},
             "table2": table, "runs": raw, "timing": {"wall_s": wall, "workers": cfg.workers}}
    rp.write_json(out / "table2.json", sweep)
    rp.write_text(out / "table2.md", "# Table 2: hyperparameters (one factor at a time)\n\n"
                  f"Model: `{checkpoint}`; seeds {list(cfg.sweep_seeds)}; defaults N = "
                  f"{cfg.n_samples}, H = {cfg.horizon}, lambda = {cfg.lam}.\n\n"
                  + rp.sweep_markdown(sweep))
    rp.plot_sweep(sweep, out / "table2.png")
    sweep["files"] = {"json": str(out / "table2.json"), "md": str(out / "table2.md"),
                      "png": str(out / "table2.png")}
    return sweep


__all__ = ["METHODS", "ExperimentConfig", "Setup", "load_experiment_config", "run_experiment",
           "run_job", "run_sweep", "substrates", "task_seed"]
