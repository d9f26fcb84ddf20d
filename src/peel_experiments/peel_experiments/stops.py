"""Which prewarnings could have been avoided (docs/planner.md, "Stops the planner cannot avoid").

A prewarning (|F_RX| or |F_RZ| >= 20 N, paper 4.2) ends a peel unpeeled. Some substrates of
the drifting and switched plant sequences are stuck so hard that the force passes 20 N at
whatever admissible speed the blade takes: the build-up is a function of the blade's travel,
not of its speed. A stop there says nothing about the planner. :func:`peelable` asks of one
substrate whether anything finishes it: the oracle (the shipped planner with the plant's true
dynamics as its model, :mod:`.oracle`) and each of :func:`constant_speeds` held for the whole
peel. A substrate none of them finishes is ``peelable: false``.

* :func:`oracle_on_stops`: :func:`peelable` on every substrate some bench arm stopped on, and
  each arm's ``prewarnings_avoidable`` (``peel bench safety --oracle-on-stops``);
* :func:`experiment_cells`: the same for the runs of ``peel experiment`` output folders (every
  method's peels, with learning): per method the prewarnings, the avoidable ones, the peels
  over 18 N, J, T_cpl and the peak force (``peel bench safety --experiments DIR ...``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from peel_msgs_py.errors import PeelError
from peel_planner_node.config import PlannerConfig

from .bench_common import interval, wilson

Peel = tuple[int, dict[str, float] | None]  # (env seed, plant parameters or None)


class ConstantSpeed:
    """A policy that commands one speed u (mm/s) for the whole peel."""

    def __init__(self, u: float) -> None:
        self.u = float(u)

    def reset(self) -> None:
        """Nothing to forget between peels."""

    def __call__(self, history: Any) -> float:
        return self.u


def constant_speeds(cfg: PlannerConfig) -> list[float]:
    """The constant speeds tried on a stopped substrate: u_min, 1, 2, 4 mm/s and u_max."""
    m = cfg.mppi
    return sorted({float(m.u_min), *(u for u in (1.0, 2.0, 4.0) if m.u_min < u < m.u_max),
                   float(m.u_max)})


def outcome_and_peak(env: Any, policy: Any, peel: Peel) -> tuple[str, float]:
    """One peel of ``policy`` on ``env``: its outcome and largest |F_RX| or |F_RZ|, N."""
    from peel_sim_node.episode import run_episode

    from .planner_studies import peak_force

    policy.reset()
    traj = run_episode(env, policy, seed=peel[0], params=peel[1])
    return traj.outcome, float(peak_force(traj))


def peelable(env: Any, peel: Peel, cfg: PlannerConfig) -> dict[str, Any]:
    """Whether one substrate can be peeled without the prewarning: the oracle (planner
    configuration ``cfg``, its ``mppi.seed``) and each of :func:`constant_speeds`."""
    from peel_planner_node.cost import Cost

    from .oracle import oracle_planner

    out, peak = outcome_and_peak(env, oracle_planner(env, cfg, Cost(cfg.cost)), peel)
    const = {u: outcome_and_peak(env, ConstantSpeed(u), peel)[0] for u in constant_speeds(cfg)}
    return {"out": out, "peak": round(peak, 3),
            "constant": {f"{u:g}": o for u, o in const.items()},
            "peelable": out == "done" or "done" in const.values()}


def oracle_on_stops(env: Any, peels: list[Peel], outcomes: dict[str, list[str]],
                    base: PlannerConfig, pseed: int) -> tuple[list[dict[str, Any]], dict[str, int]]:
    """:func:`peelable` on each task index where some arm's peel (any planner seed: an arm's
    ``outcomes`` run seed-major over ``peels``) was a safety stop; returns the verdicts and
    each arm's avoidable prewarnings (its stops on peelable substrates)."""
    k = len(peels)
    stopped = sorted({i % k for outs in outcomes.values() for i, o in enumerate(outs)
                      if o == "safety_stop"})
    cfg = base.replace(**{"mppi.seed": pseed})
    checked = [{"task": i, **peelable(env, peels[i], cfg)} for i in stopped]
    feasible = {c["task"] for c in checked if c["peelable"]}
    avoidable = {arm: sum(o == "safety_stop" and i % k in feasible for i, o in enumerate(outs))
                 for arm, outs in outcomes.items()}
    return checked, avoidable


def read_results(folder: Path) -> dict[str, Any]:
    """A ``peel experiment`` folder's results.json; one-line errors for what is missing."""
    path = Path(folder) / "results.json"
    try:
        res = json.loads(path.read_text())
    except FileNotFoundError:
        raise PeelError(f"--experiments: {path} does not exist (a peel experiment --out "
                        "folder?)") from None
    except json.JSONDecodeError as exc:
        raise PeelError(f"--experiments: {path} is not JSON ({exc.msg}, line "
                        f"{exc.lineno})") from None
    if not isinstance(res, dict) or "runs" not in res or "plant" not in res:
        raise PeelError(f"--experiments: {path} holds no runs of peel experiment")
    return res


def peak(rec: dict[str, Any]) -> float:
    """The larger of a peel's two force peaks |F_RX|, |F_RZ| (N)."""
    return max(rec["max_abs_fx"], rec["max_abs_fz"])


def stop_record(rec: dict[str, Any], others: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """What a stopped peel was: the model version it started on, when it stopped, its peak and
    the guard's counts, and how every other method's peel of the same substrate ended."""
    guard = rec.get("planner_guard") or {}
    return {"model_version": rec.get("model_version"), "t_stop_s": rec["t_cpl"],
            "peak_n": round(peak(rec), 3), "fallbacks": guard.get("fallbacks"),
            "margin_max_n": guard.get("margin_max_n"),
            "others": {m: {"outcome": r["outcome"], "peak_n": round(peak(r), 3)}
                       for m, r in sorted(others.items())}}


def method_summary(tasks: list[tuple[int, dict[str, Any]]],
                   checked: dict[tuple[int, int], dict[str, Any]], over_n: float,
                   same: dict[tuple[int, int], dict[str, dict[str, Any]]] | None = None
                   ) -> dict[str, Any]:
    """Counts and intervals of one method's peels ``(seed, task record)`` with the
    :func:`peelable` verdict of each stop ``checked[(seed, task)]``; ``same[(seed, task)]``
    holds the other methods' records of that substrate (:func:`stop_record`)."""
    stops = [(s, r) for s, r in tasks if r["outcome"] == "safety_stop"]
    peaks = [peak(r) for _, r in tasks]
    return {"peels": len(tasks), "prewarnings": len(stops),
            "prewarnings_avoidable": sum(checked[(s, r["task"])]["peelable"] for s, r in stops),
            "stops": [{"seed": s, "task": r["task"], **checked[(s, r["task"])],
                       **stop_record(r, (same or {}).get((s, r["task"]), {}))}
                      for s, r in stops],
            "over_18n": int(sum(p >= over_n for p in peaks)),
            "J": interval([r["cost"] for _, r in tasks]),
            "t_cpl_s": interval([r["t_cpl"] for _, r in tasks]),
            "peak_n": {**interval(peaks), "max": round(max(peaks), 3)}}


def experiment_cell(folder: Path, over_n: float) -> dict[str, Any]:
    """One ``peel experiment`` folder: per method :func:`method_summary`, every stop's
    substrate replayed by :func:`peelable` (the oracle with the run's planner parameters and
    that task's ``mppi.seed``) on the plant of the run's level, sequence and effects, with the
    simulator's own parameters: results.json does not record ``--sim-params``, so a run made
    with them is replayed without them."""
    from peel_msgs_py.task import mppi_seed, task_seed
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.effects import load_effects
    from peel_sim_node.env import PeelEnv

    res = read_results(folder)
    level, sequence = int(res["plant"]["level"]), str(res["sequence"])
    cfg = PlannerConfig.from_params(res.get("config", {}).get("planner_params") or {})
    sim_cfg = load_sim_config()
    env = PeelEnv(sim_cfg, source="plant", seed=0, level=level,
                  effects=load_effects(res.get("effects") or []))
    checked: dict[tuple[int, int], dict[str, Any]] = {}
    methods: dict[str, Any] = {}
    try:
        for method in sorted({m for run in res["runs"].values() for m in run}):
            tasks = [(int(s), r) for s, run in res["runs"].items() if method in run
                     for r in run[method]["tasks"]]
            for s, r in tasks:
                if r["outcome"] == "safety_stop" and (s, r["task"]) not in checked:
                    if "substrate" not in r:
                        raise PeelError(f"--experiments: {folder}: seed {s} task {r['task']} "
                                        "has no substrate record")
                    k = r["task"] - 1
                    checked[(s, r["task"])] = peelable(
                        env, (task_seed(s, k), r["substrate"]),
                        cfg.replace(**{"mppi.seed": mppi_seed(s, k)}))
            same = {(s, r["task"]): {m: o for m, o in others(res, s, r["task"]).items()
                                     if m != method}
                    for s, r in tasks if r["outcome"] == "safety_stop"}
            methods[method] = method_summary(tasks, checked, over_n, same)
    finally:
        env.close()
    return {"level": str(level), "sequence": sequence, "folder": str(folder),
            "seeds": sorted(int(s) for s in res["runs"]), "methods": methods}


def others(res: dict[str, Any], seed: int | str, task: int) -> dict[str, dict[str, Any]]:
    """Every method's record of task ``task`` in seed ``seed``'s run (the same substrate)."""
    run = res["runs"][str(seed)]
    return {m: r for m, v in run.items() for r in v["tasks"] if r["task"] == task}


def experiment_cells(folders: list[Path], over_n: float) -> dict[str, Any]:
    """:func:`experiment_cell` of every folder, and per method the totals over all of them:
    peels, prewarnings (with their 95 % Wilson interval), avoidable ones, peels over 18 N."""
    cells = [experiment_cell(f, over_n) for f in folders]
    total: dict[str, dict[str, Any]] = {}
    for cell in cells:
        for m, s in cell["methods"].items():
            t = total.setdefault(m, {"peels": 0, "prewarnings": 0, "prewarnings_avoidable": 0,
                                     "over_18n": 0})
            for key in t:
                t[key] += s[key]
    for t in total.values():
        t["prewarning_rate"] = {"rate": round(t["prewarnings"] / t["peels"], 5),
                                "ci95_wilson": wilson(t["prewarnings"], t["peels"])}
        t["share_over_18n"] = round(t["over_18n"] / t["peels"], 4)
    return {"cells": cells, "total": total}
