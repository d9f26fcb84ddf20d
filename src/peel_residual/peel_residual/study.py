"""The power study of ``peel residual``: random undeclared effects, detection and false alarms.

A study is a list of :class:`Job` s, each fully determined by its fields (so the results do not
depend on how many workers run them or in which order):

* an **effect job** draws one effect (:func:`~.inject.draw`: family given, amplitude given,
  sign, channel and shape drawn from ``[seed, index]``) and adds it, measurement side, to a
  clean task set (:meth:`~.inject.Injection.apply`);
* a **clean job** analyses a clean task set as it is;
* a **speed job** (``speed_scale``, ``speed_offset``) draws a plant-side speed error
  (:meth:`~.inject.Injection.speed_error`): its caller records the task set, and the fresh
  tasks, in the plant with that error, from the same seeds as the clean set.

Each job runs :func:`~.analysis.analyse` (held-out tasks inside it, as ``peel residual`` does)
and records (:func:`run_job`): what was named, the per-channel verdicts, the held-out open-loop
RMSE of the model as given, its after / before on the affected channel, and the same ratio on
*fresh* tasks that the analysis never saw (the held-out tasks take part in the held-out
decision, :mod:`.decide`), and the best after / before any correction could reach there
(:func:`ceiling`).

Detection (:func:`detected`): the injected family named on the injected channel; a between-task
offset counts when a drift across tasks is flagged on its channel. A false alarm on clean data:
any force term named, or any drift across tasks flagged (the speed channel's actuator lag is the
level-3 plant's documented difference, counted apart).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from peel_model.effect_terms import FORCE_CHANNELS
from peel_msgs_py.trajectory import Trajectory

from .analysis import analyse
from .config import ResidualConfig
from .data import horizons
from .decide import open_loop_rmse
from .inject import DRAWN_SIZE, SPEED_RANGES, TASK_OFFSET, Injection, draw

CLEAN = "clean"


@dataclass(frozen=True)
class Job:
    """One analysis of the study; ``family`` is :data:`CLEAN` for clean data."""

    index: int
    family: str
    amplitude_n: float
    n_tasks: int
    data_seed: int
    seed: int

    def injection(self) -> Injection | None:
        """The drawn effect (None for clean data), from ``[seed, index]`` alone."""
        if self.family == CLEAN:
            return None
        return draw(self.family, self.amplitude_n, np.random.default_rng([self.seed, self.index]))


def plan_jobs(families: Sequence[str], amplitudes: Sequence[float], n_tasks: Sequence[int],
              draws: int, clean: int, seed: int) -> list[Job]:
    """``draws`` effect jobs per (family, amplitude, task count) -- a between-task offset and
    a speed family once per task count, their size drawn -- and ``clean`` clean jobs per task
    count. Draw ``d`` uses
    the clean task set with data seed ``seed * 1000 + d``; clean job ``c`` uses data seed
    ``seed * 1000 + c``: the effects are added to the same recordings that are analysed clean."""
    jobs: list[Job] = []
    for n in n_tasks:
        for fam in families:
            for amp in ([0.0] if fam in DRAWN_SIZE else amplitudes):
                for d in range(draws):
                    jobs.append(Job(len(jobs), fam, float(amp), int(n), seed * 1000 + d, seed))
        for c in range(clean):
            jobs.append(Job(len(jobs), CLEAN, 0.0, int(n), seed * 1000 + c, seed))
    return jobs


def _ratio(after: float | None, before: float | None) -> float | None:
    return None if not before or after is None else float(after / before)


def run_job(job: Job, tasks: Sequence[Trajectory], fresh: Sequence[Trajectory], model: Any,
            cfg: ResidualConfig, dt_s: float = 0.1) -> dict[str, Any]:
    """Inject, analyse, score one job (module docstring); ``fresh`` are clean tasks the
    analysis never sees, given the same injection for the independent after / before. For a
    plant-side injection ``tasks`` and ``fresh`` are already recorded with it."""
    inj = job.injection()
    rewrite = inj is not None and not inj.plant_side
    data = inj.apply(tasks) if rewrite else list(tasks)
    t0 = time.perf_counter()
    r = analyse(data, model, cfg, dt_s=dt_s)
    wall = time.perf_counter() - t0
    named = [(f.candidate.family, f.candidate.key, f.channel)
             for tr in r.traces.values() for f in tr.findings]
    rec: dict[str, Any] = {
        **asdict(job), "injection": inj.to_json() if inj else None,
        "named": [f"{k}@{ch}" for _, k, ch in named],
        "named_families": sorted({f"{fam}@{ch}" for fam, _, ch in named}),
        "task_drift": {ch: bool(d["drift"]) for ch, d in r.task_drift.items()},
        "heldout_open_loop_ratio": {ch: _ratio(r.rmse_after[ch]["open_loop"],
                                                r.rmse_before[ch]["open_loop"])
                                    for ch in (*FORCE_CHANNELS, "v")},
        "heldout_open_loop_rmse_before": {ch: r.rmse_before[ch]["open_loop"]
                                          for ch in (*FORCE_CHANNELS, "v")},
        "wall_s": round(wall, 2)}
    hz = horizons(inj.apply(fresh) if rewrite else list(fresh), int(model.h), cfg.horizon_steps,
                  cfg.stride)
    before = open_loop_rmse(model, hz)
    after = open_loop_rmse(r.corrected, hz) if r.corrected is not None else before
    rec["fresh_open_loop_ratio"] = {ch: _ratio(after[ch], before[ch]) for ch in before}
    if rewrite:  # exact for a measurement-side effect only (ceiling)
        hold = [tasks[i] for i in r.holdout_tasks]
        rec["heldout_open_loop_ceiling"] = ceiling(model, hold, inj.apply(hold), cfg)
        rec["fresh_open_loop_ceiling"] = ceiling(model, fresh, inj.apply(fresh), cfg)
    rec["detected"] = detected(rec)
    rec["claimed"] = claimed(rec)
    return rec


def ceiling(model: Any, clean: Sequence[Trajectory], injected: Sequence[Trajectory],
            cfg: ResidualConfig) -> dict[str, float | None]:
    """The best after / before any correction can reach, per force channel: the model's
    open-loop RMSE on the clean tasks over that on the same tasks with the effect. Exact for a
    measurement-side effect: the compensated model with the injected term itself, F =
    f_theta(x - g, v) + g, rolls out the clean prediction plus g, so its residual on the
    injected tasks is the model's residual on the clean ones."""
    h = int(model.h)
    a = open_loop_rmse(model, horizons(clean, h, cfg.horizon_steps, cfg.stride))
    b = open_loop_rmse(model, horizons(injected, h, cfg.horizon_steps, cfg.stride))
    return {ch: _ratio(a[ch], b[ch]) for ch in FORCE_CHANNELS}


def claimed(rec: dict[str, Any]) -> bool:
    """Any force term named or any drift across tasks flagged."""
    return any(not n.endswith("@v") for n in rec["named_families"]) or any(
        rec["task_drift"].values())


def detected(rec: dict[str, Any]) -> bool | None:
    """The injected effect found on its channel (None for clean data)."""
    inj = rec["injection"]
    if inj is None:
        return None
    if inj["family"] == TASK_OFFSET:
        return bool(rec["task_drift"][inj["channel"]])
    return f"{inj['family']}@{inj['channel']}" in rec["named_families"]


def _median(xs: list[float | None]) -> float | None:
    xs = [x for x in xs if x is not None]
    return float(np.median(xs)) if xs else None


#: The target's after / before on the affected channel (docs/residual.md, "Targets").
TARGET_RATIO = 0.8


def _reach(rs: Sequence[dict[str, Any]], chs: Sequence[str]) -> dict[str, Any]:
    """How many draws a perfect correction could bring to :data:`TARGET_RATIO` on fresh
    tasks (:func:`ceiling`), the median ceiling, and the detections among those draws."""
    if not any("fresh_open_loop_ceiling" in r for r in rs):  # plant-side effects: no exact one
        return {}
    ceil = [r.get("fresh_open_loop_ceiling", {}).get(c) for r, c in zip(rs, chs, strict=True)]
    ok = [x is not None and x <= TARGET_RATIO for x in ceil]
    return {"median_fresh_ceiling": _median(ceil), "reachable": int(sum(ok)),
            "detected_reachable": int(sum(bool(r["detected"]) and o
                                          for r, o in zip(rs, ok, strict=True)))}


def summarise(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Power rows per (family, amplitude, tasks) and false-alarm rows per task count."""
    groups: dict[tuple[str, float, int], list[dict[str, Any]]] = {}
    for r in records:
        groups.setdefault((r["family"], r["amplitude_n"], r["n_tasks"]), []).append(r)
    power, clean = [], []
    for (fam, amp, n), rs in sorted(groups.items()):
        if fam == CLEAN:
            worse = [any((x or 0) > 1.0 for ch, x in r["fresh_open_loop_ratio"].items()
                         if ch in FORCE_CHANNELS) for r in rs]
            clean.append({"n_tasks": n, "runs": len(rs),
                          "claimed": sum(r["claimed"] for r in rs),
                          "false_alarm_rate": float(np.mean([r["claimed"] for r in rs])),
                          "worse_on_fresh_tasks": int(sum(worse)),
                          "median_wall_s": _median([r["wall_s"] for r in rs])})
            continue
        chs = [r["injection"]["channel"] for r in rs]
        power.append({
            "family": fam, "amplitude_n": amp, "n_tasks": n, "draws": len(rs),
            "detected": int(sum(bool(r["detected"]) for r in rs)),
            "detection_rate": float(np.mean([bool(r["detected"]) for r in rs])),
            "median_heldout_ratio": _median([r["heldout_open_loop_ratio"][c]
                                             for r, c in zip(rs, chs, strict=True)]),
            "median_fresh_ratio": _median([r["fresh_open_loop_ratio"][c]
                                           for r, c in zip(rs, chs, strict=True)]),
            **_reach(rs, chs),
            "median_wall_s": _median([r["wall_s"] for r in rs])})
    return {"power": power, "clean": clean}


def _f(x: float | None, nd: int = 2) -> str:
    return "–" if x is None else f"{x:.{nd}f}"


def _size(family: str, amplitude_n: float) -> str:
    """The table's amplitude column: the drawn range for :data:`~.inject.DRAWN_SIZE`."""
    if family == TASK_OFFSET:
        return "0.3-0.5 N/task"
    if family in SPEED_RANGES:
        lo, hi = SPEED_RANGES[family]
        return f"x (1 ± {lo:g}-{hi:g})" if family == "speed_scale" else f"± {lo:g}-{hi:g} mm/s"
    return f"{amplitude_n:g} N"


def markdown(summary: dict[str, Any], command: str) -> str:
    """The power table and the false-alarm table."""
    L = ["# peel residual: power study", "", f"Command: `{command}`", "",
         "| family | amplitude | tasks | draws | detected | rate | open-loop after/before "
         "held-out (median) | on fresh tasks (median) | best reachable on fresh tasks (median) "
         "| draws where 0.8 is reachable | detected among them | wall s (median) |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for p in summary["power"]:
        amp = _size(p["family"], p["amplitude_n"])
        L.append(f"| {p['family']} | {amp} | {p['n_tasks']} | {p['draws']} | {p['detected']} | "
                 f"{p['detection_rate']:.0%} | {_f(p['median_heldout_ratio'])} | "
                 f"{_f(p['median_fresh_ratio'])} | {_f(p.get('median_fresh_ceiling'))} | "
                 f"{p.get('reachable', '–')} | {p.get('detected_reachable', '–')} | "
                 f"{_f(p['median_wall_s'], 1)} |")
    L += ["", "| clean data, tasks | runs | effect claimed | false-alarm rate | worse on fresh "
          "tasks | wall s (median) |", "|---|---|---|---|---|---|"]
    for c in summary["clean"]:
        L.append(f"| {c['n_tasks']} | {c['runs']} | {c['claimed']} | "
                 f"{c['false_alarm_rate']:.0%} | {c['worse_on_fresh_tasks']} | "
                 f"{_f(c['median_wall_s'], 1)} |")
    return "\n".join(L) + "\n"
