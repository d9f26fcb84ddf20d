"""``peel experiment grid``: the experiment across plant severity levels and sequences, one report.

For every (level, sequence) cell, :func:`peel_experiments.experiment.run_experiment` peels ``tasks``
substrates per method and seed (its own ``results.json``, Fig. 11, Table 1 in ``OUT/<cell>/``;
a cell whose ``results.json`` was made with the same settings is reused, so an interrupted grid
resumes). Then one summary: ``summary.json``, ``summary.md``, ``headroom.png`` (headroom closed
against level) and ``fig11_levels.png`` (Fig. 11 per level and sequence).

Definitions (docs/experiments.md, "Plant levels"), per seed s and task k, all methods peel the
same substrate:

* headroom ``H_s(k) = J_B1 - J_oracle``: Baseline 1's gap to the oracle;
* closed ``C_s^m(k) = J_B1 - J_m``: what method m has gained over Baseline 1;
* fraction of headroom closed by m at task k: ``sum C / sum H`` over the tasks of the window
  ``[k - w, k + w]`` (clipped to the run, w = ``window``) -- one peel's J is too noisy (the
  substrates differ) to divide peel by peel. Given per seed and pooled over seeds (sum over
  seeds of numerator and denominator), with the mean and a 95 % t-interval of the per-seed
  values.

Every other metric is the mean over the tasks of one seed, then mean and 95 % t-interval over
seeds (t quantile of n - 1 degrees of freedom; with 3 seeds the interval is wide: it says how
little 3 seeds can show).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from .experiment import run_experiment
from .experiment_config import ORACLE, ExperimentConfig

#: tasks at which the fraction of headroom closed is reported (5, 10, 20: docs/experiments.md)
CHECK_TASKS: tuple[int, ...] = (5, 10, 20)
#: targets (docs/experiments.md): fraction closed by OL-MPPI at the strongest level
TARGET_CLOSED = {5: 0.70, 10: 0.85}
_T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306,
         9: 2.262, 10: 2.228}


def ci95(values: Sequence[float]) -> dict[str, Any]:
    """Mean and 95 % t-interval half width over seeds (``None`` with one value)."""
    v = np.array([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if v.size == 0:
        return {"mean": None, "ci95": None, "n": 0, "values": []}
    half = None
    if v.size > 1:
        t = _T975.get(v.size - 1, 1.96)
        half = float(t * v.std(ddof=1) / math.sqrt(v.size))
    return {"mean": float(v.mean()), "ci95": half, "n": int(v.size),
            "values": [float(x) for x in v]}


def cell_name(level: int, sequence: str) -> str:
    return f"L{level}_{sequence}"


def _costs(runs: Mapping[str, Any], seed: str, method: str) -> np.ndarray:
    return np.array([r["cost"] for r in runs[seed][method]["tasks"]], dtype=float)


def closed_fraction(runs: Mapping[str, Any], method: str, task: int, window: int = 2
                    ) -> dict[str, Any]:
    """Fraction of the headroom method has closed around ``task`` (module docstring)."""
    per_seed, num_all, den_all, n_all = [], 0.0, 0.0, 0
    for s in runs:
        b1, orc, m = (_costs(runs, s, x) for x in ("baseline1", ORACLE, method))
        n = min(len(b1), len(orc), len(m))
        if task > n:
            continue
        lo, hi = max(0, task - 1 - window), min(n, task + window)
        num, den = float(np.sum(b1[lo:hi] - m[lo:hi])), float(np.sum(b1[lo:hi] - orc[lo:hi]))
        num_all += num
        den_all += den
        n_all += hi - lo
        per_seed.append(num / den if abs(den) > 1e-9 else float("nan"))
    out = ci95(per_seed)
    out["pooled"] = num_all / den_all if abs(den_all) > 1e-9 else None
    out["window"] = [task - window, task + window]
    # the headroom the fraction divides by (mean J_B1 - J_oracle per peel of the window): near
    # zero the fraction is meaningless, whatever its value
    out["headroom_in_window"] = den_all / n_all if n_all else None
    return out


def _per_seed_mean(runs: Mapping[str, Any], method: str, key: str) -> list[float]:
    return [float(np.mean([r[key] for r in runs[s][method]["tasks"]])) for s in runs]


def _peak(r: Mapping[str, Any]) -> float:
    return max(float(r["max_abs_fx"]), float(r["max_abs_fz"]))


def cell_summary(results: Mapping[str, Any], window: int = 2) -> dict[str, Any]:
    """Headroom, fractions closed and the per-method metrics of one (level, sequence) cell."""
    runs = results["runs"]
    methods = [m for m in results["methods"]]
    tasks = results["tasks"]
    out: dict[str, Any] = {"level": results["plant"]["level"], "plant": results["plant"]["name"],
                           "sequence": results["sequence"], "seeds": results["seeds"],
                           "tasks": tasks}
    if ORACLE in methods and "baseline1" in methods:
        hb = [float(np.mean(_costs(runs, s, "baseline1") - _costs(runs, s, ORACLE)))
              for s in runs]
        rel = [float(np.mean(_costs(runs, s, "baseline1")) / np.mean(_costs(runs, s, ORACLE))
                     - 1.0) for s in runs]
        out["headroom"] = ci95(hb)
        out["headroom_rel"] = ci95(rel)
        out["closed"] = {m: {str(k): closed_fraction(runs, m, k, window)
                             for k in CHECK_TASKS if k <= tasks}
                         for m in methods if m not in ("baseline1", ORACLE)}
    metrics: dict[str, Any] = {}
    for m in methods:
        recs = [r for s in runs for r in runs[s][m]["tasks"]]
        metrics[m] = {
            "cost": ci95(_per_seed_mean(runs, m, "cost")),
            "cost_last5": ci95([float(np.mean(_costs(runs, s, m)[-5:])) for s in runs]),
            "t_cpl": ci95(_per_seed_mean(runs, m, "t_cpl")),
            "sum_fx": ci95(_per_seed_mean(runs, m, "sum_fx")),
            "sum_fz": ci95(_per_seed_mean(runs, m, "sum_fz")),
            "peak_force": ci95([float(np.mean([_peak(r) for r in runs[s][m]["tasks"]]))
                                for s in runs]),
            "peak_force_max": max(_peak(r) for r in recs),
            "safety_stops": sum(r["outcome"] == "safety_stop" for r in recs),
            "near_misses": sum(_peak(r) > 18.0 for r in recs),
            "peels": len(recs),
        }
    out["metrics"] = metrics
    t = results["timing"]
    out["timing"] = {k: t.get(k) for k in ("wall_s", "ol_mppi_update_s_mean",
                                           "ol_mppi_update_s_max", "baseline2_update_s_mean")}
    if "ol-mppi" in methods and "baseline2" in methods:
        d = [float(np.mean(_costs(runs, s, "ol-mppi")[-5:] - _costs(runs, s, "baseline2")[-5:]))
             for s in runs]
        out["ol_minus_b2_last5"] = ci95(d)
    return out


def _same_settings(path: Path, want: Mapping[str, Any], level: int,
                   methods: Sequence[str]) -> bool:
    """Whether the cell's results.json was made with these settings, level and arms."""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return (all(old.get(k) == v for k, v in want.items())
            and old.get("plant", {}).get("level") == level
            and list(old.get("config", {}).get("methods", ())) == list(methods))


def run_grid(cfg: ExperimentConfig, *, levels: Sequence[int], sequences: Sequence[str],
             checkpoint: str, out: Path, sim_overrides: str | None = None,
             planner_overrides: str | None = None, learner_overrides: str | None = None,
             command: str = "", window: int = 2, report_only: bool = False) -> dict[str, Any]:
    """Every (level, sequence) cell, then ``summary.{json,md}``, ``headroom.png`` and
    ``fig11_levels.png`` in ``out``. ``report_only``: run nothing, report the cells already in
    ``out`` (made with the same seeds and tasks) and list the others as ``missing``."""
    from . import report as rp

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cells: dict[str, Any] = {}
    missing: list[str] = []
    for level in levels:
        for seq in sequences:
            name = cell_name(level, seq)
            cdir = out / name
            ccfg = replace(cfg, plant_level=int(level), sequence=seq)
            want = {"tasks": ccfg.tasks, "seeds": list(ccfg.seeds), "checkpoint": str(checkpoint),
                    "sequence": seq}
            res_path = cdir / "results.json"
            if _same_settings(res_path, want, level, ccfg.methods):
                results = json.loads(res_path.read_text())
            elif report_only:
                missing.append(name)
                continue
            else:
                results = run_experiment(ccfg, checkpoint=checkpoint, out=cdir,
                                         sim_overrides=sim_overrides,
                                         planner_overrides=planner_overrides,
                                         learner_overrides=learner_overrides,
                                         command=f"{command} [cell {name}]")
            cells[name] = {"summary": cell_summary(results, window),
                           "methods": rp.flat_methods(results)}
    summary = {"command": command, "checkpoint": str(checkpoint), "levels": list(levels),
               "sequences": list(sequences), "seeds": list(cfg.seeds), "tasks": cfg.tasks,
               "window": window, "check_tasks": list(CHECK_TASKS), "missing": missing,
               "cells": {k: v["summary"] for k, v in cells.items()}}
    summary["targets"] = grid_targets(summary)
    rp.write_json(out / "summary.json", summary)
    rp.write_text(out / "summary.md", summary_markdown(summary))
    plot_headroom(summary, out / "headroom.png")
    plot_fig11_levels({k: v["methods"] for k, v in cells.items()}, summary,
                      out / "fig11_levels.png")
    summary["files"] = {"json": str(out / "summary.json"), "md": str(out / "summary.md"),
                        "headroom_png": str(out / "headroom.png"),
                        "fig11_png": str(out / "fig11_levels.png")}
    return summary


def grid_targets(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The targets (docs/experiments.md) at the strongest level in the grid, each measured."""
    top = max(summary["levels"])
    res: dict[str, Any] = {"level": top}
    st = summary["cells"].get(cell_name(top, "stationary"))
    if st is not None and "closed" in st:
        res["headroom_rel"] = st["headroom_rel"]["mean"]
        res["baseline1_30pct_above_oracle"] = bool((st["headroom_rel"]["mean"] or 0) >= 0.30)
        ol = st["closed"].get("ol-mppi", {})
        for k, goal in TARGET_CLOSED.items():
            c = ol.get(str(k))
            if c is not None:
                res[f"ol_closed_task{k}"] = c["pooled"]
                res[f"ol_closed_task{k}_met"] = bool(c["pooled"] is not None
                                                    and c["pooled"] >= goal)
        res["ol_safety_stops"] = st["metrics"].get("ol-mppi", {}).get("safety_stops")
    dr = summary["cells"].get(cell_name(top, "drift"))
    if dr is not None and "ol_minus_b2_last5" in dr:
        d = dr["ol_minus_b2_last5"]
        res["drift_ol_minus_b2_last5"] = d
        res["drift_ol_ahead_of_b2"] = bool(d["mean"] is not None and d["mean"] < 0)
        res["drift_ol_ahead_of_b2_significant"] = bool(
            d["mean"] is not None and d["ci95"] is not None and d["mean"] + d["ci95"] < 0)
    return res


def _ci(c: Mapping[str, Any] | None, fmt: str = ".2f") -> str:
    if c is None or c.get("mean") is None:
        return "–"
    s = format(c["mean"], fmt)
    return s + (" ± " + format(c["ci95"], fmt) if c.get("ci95") is not None else "")


def summary_markdown(summary: Mapping[str, Any]) -> str:
    """The grid report: headroom and fractions closed, then the per-method metrics."""
    lines = ["# OL-MPPI across plant severity levels and sequences", "",
             f"Command: `{summary['command']}`  ", f"Checkpoint: `{summary['checkpoint']}`  ",
             f"Seeds {summary['seeds']}, {summary['tasks']} tasks per method and seed. "
             + (f"Cells not run: {', '.join(summary['missing'])}. " if summary.get("missing")
                else "") +
             "Values: mean ± 95 % t-interval half width over seeds. Fraction of headroom closed "
             f"at task k: sum over tasks k-{summary['window']}..k+{summary['window']} of "
             "(J_B1 - J_m) / (J_B1 - J_oracle), pooled over seeds (per-seed mean ± CI beside).",
             "", "## Headroom and fraction closed", "",
             "| level | sequence | headroom J_B1 - J_or | B1 / oracle - 1 | method | "
             + " | ".join(f"closed @ {k} (pooled (window headroom); per-seed)"
                          for k in summary["check_tasks"])
             + " | OL - B2, J tasks 16-20 |",
             "|---|---|---|---|---|" + "---|" * len(summary["check_tasks"]) + "---|"]
    for c in summary["cells"].values():
        if "closed" not in c:
            continue
        for m, ks in c["closed"].items():
            vals = []
            for k in summary["check_tasks"]:
                x = ks.get(str(k))
                vals.append("–" if x is None else
                            f"{_fmt(x['pooled'])} (H {_fmt(x.get('headroom_in_window'))}); "
                            f"{_ci(x)}")
            lines.append(f"| {c['level']} | {c['sequence']} | {_ci(c['headroom'])} | "
                         f"{_ci(c['headroom_rel'], '.1%')} | {m} | " + " | ".join(vals)
                         + f" | {_ci(c.get('ol_minus_b2_last5'))} |")
    lines += ["", "## Per method (mean over the tasks of a seed, then over seeds)", "",
              "| level | sequence | method | J | J tasks 16-20 | T_cpl (s) | ΣF_RX (N) | "
              "ΣF_RZ (N) | peak \\|F\\| (N) | max peak | stops | > 18 N | update s mean/max |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in summary["cells"].values():
        for m, x in c["metrics"].items():
            t = c["timing"]
            up = (f"{_fmt(t['ol_mppi_update_s_mean'])}/{_fmt(t['ol_mppi_update_s_max'])}"
                  if m == "ol-mppi" else "")
            lines.append(f"| {c['level']} | {c['sequence']} | {m} | {_ci(x['cost'])} | "
                         f"{_ci(x['cost_last5'])} | {_ci(x['t_cpl'])} | {_ci(x['sum_fx'], '.0f')} "
                         f"| {_ci(x['sum_fz'], '.0f')} | {_ci(x['peak_force'])} | "
                         f"{x['peak_force_max']:.1f} | {x['safety_stops']}/{x['peels']} | "
                         f"{x['near_misses']} | {up} |")
    lines += ["", "## Targets (strongest level)", "", "```json",
              json.dumps(summary.get("targets", {}), indent=1), "```", ""]
    return "\n".join(lines)


def _fmt(x: Any) -> str:
    return "–" if x is None else f"{x:.2f}"


#: fractions closed are drawn only where Baseline 1's mean J is this far above the oracle's;
#: below it the fraction divides by noise
MIN_HEADROOM_REL = 0.10


def _has_headroom(cell: Mapping[str, Any]) -> bool:
    h = cell.get("headroom_rel", {}).get("mean")
    return h is not None and h >= MIN_HEADROOM_REL


def plot_headroom(summary: Mapping[str, Any], path: Path) -> Path:
    """Fraction of headroom closed against level (one panel per sequence; only cells with
    ``MIN_HEADROOM_REL`` of headroom) and the headroom itself."""
    from .report import _pyplot, _savefig

    plt = _pyplot()
    seqs = summary["sequences"]
    fig, axes = plt.subplots(1, len(seqs) + 1, figsize=(4.2 * (len(seqs) + 1), 3.8))
    axes = np.atleast_1d(axes)
    styles = {"ol-mppi": "tab:red", "baseline2": "tab:green"}
    marks = {5: "o", 10: "s", 20: "^"}
    for ax, seq in zip(axes, seqs, strict=False):
        for m, col in styles.items():
            for k, mk in marks.items():
                xs, ys, es = [], [], []
                for lvl in summary["levels"]:
                    c = summary["cells"].get(cell_name(lvl, seq), {})
                    x = c.get("closed", {}).get(m, {}).get(str(k))
                    if x is None or x.get("pooled") is None or not _has_headroom(c):
                        continue
                    xs.append(lvl + (0.08 if m == "baseline2" else -0.08))
                    ys.append(x["pooled"])
                    es.append(x["ci95"] or 0.0)
                if xs:
                    ax.errorbar(xs, ys, es, color=col, marker=mk, capsize=2, lw=1,
                                label=f"{m} @ task {k}")
        ax.axhline(1.0, color="k", lw=0.6, ls="--")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylim(-1.5, 2.0)
        ax.set_xticks(summary["levels"])
        ax.set_xlabel("plant severity level")
        ax.set_ylabel("fraction of headroom closed")
        ax.set_title(f"{seq} (cells with headroom >= {MIN_HEADROOM_REL:.0%})", fontsize=9)
    axes[0].legend(fontsize=6)
    ax = axes[-1]
    for seq in seqs:
        xs, ys, es = [], [], []
        for lvl in summary["levels"]:
            c = summary["cells"].get(cell_name(lvl, seq), {})
            if "headroom_rel" in c and c["headroom_rel"]["mean"] is not None:
                xs.append(lvl)
                ys.append(c["headroom_rel"]["mean"])
                es.append(c["headroom_rel"]["ci95"] or 0.0)
        if xs:
            ax.errorbar(xs, ys, es, marker="o", capsize=2, label=seq)
    ax.axhline(0.30, color="k", lw=0.6, ls="--")
    ax.set_xticks(summary["levels"])
    ax.set_xlabel("plant severity level")
    ax.set_ylabel("headroom: mean J_B1 / J_oracle - 1")
    ax.legend(fontsize=7)
    fig.suptitle(f"Headroom closed by OL-MPPI and Baseline 2 (seeds {summary['seeds']})")
    fig.tight_layout()
    return _savefig(fig, Path(path))


def plot_fig11_levels(cells: Mapping[str, Mapping[str, Sequence[Mapping[str, Any]]]],
                      summary: Mapping[str, Any], path: Path) -> Path:
    """Fig. 11 (J per task, mean over seeds, min-max band) per level (columns) and sequence."""
    from .report import _STYLE, _pyplot, _savefig

    plt = _pyplot()
    levels, seqs = summary["levels"], summary["sequences"]
    fig, axes = plt.subplots(len(seqs), len(levels), figsize=(3.6 * len(levels),
                                                              2.8 * len(seqs)), squeeze=False)
    for i, seq in enumerate(seqs):
        for j, lvl in enumerate(levels):
            ax = axes[i][j]
            methods = cells.get(cell_name(lvl, seq), {})
            if not methods:
                ax.text(0.5, 0.5, "not run", ha="center", va="center", transform=ax.transAxes)
            for m, recs in methods.items():
                col, mk = _STYLE.get(m, ("grey", ""))
                k = [r["task"] for r in recs]
                ax.plot(k, [r["cost"] for r in recs], color=col, marker=mk, ms=3, label=m)
                if recs and "cost_min" in recs[0]:
                    ax.fill_between(k, [r["cost_min"] for r in recs],
                                    [r["cost_max"] for r in recs], color=col, alpha=0.1)
            ax.set_title(f"level {lvl}, {seq}", fontsize=9)
            ax.set_xlabel("task")
            ax.set_ylabel("J")
    axes[0][0].legend(fontsize=6)
    fig.suptitle("Fig. 11 per plant level and sequence: total cost J per task")
    fig.tight_layout()
    return _savefig(fig, Path(path))
