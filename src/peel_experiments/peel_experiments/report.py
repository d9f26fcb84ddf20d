"""Results of ``peel experiment`` as JSON, Markdown and PNG figures (paper 4.4-4.5).

* Fig. 11: total cost J (Eq. 3) per task for every method and the oracle (mean over seeds, with
  the min-max band when there are several seeds);
* Table 1: T_cpl, sum F_RX, sum F_RZ (and J) of the last task (the paper's 20th);
* Fig. 12: velocity and the two forces over time in the last task (first seed);
* Table 2 (``peel experiment sweep``): total cost for N, H, lambda one factor at a time.

Gap to the oracle. J can be negative (the progress reward of Eq. 4 is -w_dis over a full peel),
so the gap is reported both as ``J - J_oracle`` and relative to ``|J_oracle|``.
Everything is written atomically (temporary file in the same directory + ``os.replace``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.atomic import atomic_write, atomic_write_text

#: Per-task keys that are averaged over seeds.
NUMERIC_KEYS: tuple[str, ...] = ("cost", "t_cpl", "sum_fx", "sum_fz", "update_s", "plan_s",
                                 "max_abs_fx", "max_abs_fz")
#: Outcomes from best to worst; the aggregate of several seeds is the worst one.
OUTCOME_ORDER: tuple[str, ...] = ("done", "timeout", "aborted", "running", "safety_stop")
ORACLE = "oracle"
#: A peel whose peak |F| exceeds this came close to the 20 N safety stop (90 % of it), N.
NEAR_MISS_N: float = 18.0


# ------------------------------------------------------------------------------ atomic files


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` atomically."""
    return atomic_write_text(path, text)


def write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as indented JSON atomically (NaN/inf become null)."""
    return write_text(path, json.dumps(_clean(obj), indent=1, allow_nan=False) + "\n")


def _clean(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, np.generic):
        return _clean(obj.item())
    if isinstance(obj, np.ndarray):
        return [_clean(x) for x in obj.tolist()]
    if isinstance(obj, Mapping):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(x) for x in obj]
    return obj


def _savefig(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    def write(tmp: str) -> None:
        fig.savefig(tmp, format="png", dpi=120, bbox_inches="tight")

    try:
        return atomic_write(path, write)
    finally:
        plt.close(fig)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ------------------------------------------------------------------------------ aggregation


def worst_outcome(outcomes: Sequence[str]) -> str:
    """The worst of several outcomes (``OUTCOME_ORDER``)."""
    rank = {o: i for i, o in enumerate(OUTCOME_ORDER)}
    return max(outcomes, key=lambda o: rank.get(o, len(rank)))


def aggregate(runs: Mapping[str, Mapping[str, Sequence[Mapping[str, Any]]]]
              ) -> dict[str, list[dict[str, Any]]]:
    """Per method, per task: mean, std, min and max over seeds of the numeric keys.

    ``runs[seed][method]`` is that seed's list of per-task records. The aggregate record keeps
    the required keys (``cost`` = mean, ...), adds ``<key>_std/_min/_max``, ``outcome`` (the
    worst over seeds), ``outcomes`` (per seed) and ``n_seeds``.
    """
    seeds = list(runs)
    methods = list(runs[seeds[0]])
    out: dict[str, list[dict[str, Any]]] = {}
    for m in methods:
        n_tasks = min(len(runs[s][m]) for s in seeds)
        recs = []
        for k in range(n_tasks):
            per = [runs[s][m][k] for s in seeds]
            rec: dict[str, Any] = {"task": per[0].get("task", k + 1), "n_seeds": len(per)}
            for key in NUMERIC_KEYS:
                vals = np.array([float(p[key]) for p in per if p.get(key) is not None])
                if vals.size == 0:
                    continue
                rec[key] = float(vals.mean())
                rec[f"{key}_std"] = float(vals.std())
                rec[f"{key}_min"] = float(vals.min())
                rec[f"{key}_max"] = float(vals.max())
            rec["outcomes"] = [p["outcome"] for p in per]
            rec["outcome"] = worst_outcome(rec["outcomes"])
            rec["model_version"] = per[0].get("model_version")
            recs.append(rec)
        out[m] = recs
    return out


def gaps_to_oracle(methods: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, Any]:
    """Per method: per-task ``J - J_oracle`` and ``(J - J_oracle) / |J_oracle|``."""
    if ORACLE not in methods:
        return {}
    ref = [r["cost"] for r in methods[ORACLE]]
    out: dict[str, Any] = {}
    for m, recs in methods.items():
        if m == ORACLE:
            continue
        n = min(len(ref), len(recs))
        absolute = [recs[k]["cost"] - ref[k] for k in range(n)]
        rel = [absolute[k] / abs(ref[k]) if abs(ref[k]) > 1e-9 else float("nan")
               for k in range(n)]
        out[m] = {"abs": absolute, "rel": rel,
                  "last_abs": absolute[-1] if n else None, "last_rel": rel[-1] if n else None,
                  "mean_abs": float(np.mean(absolute)) if n else None}
    return out


def table1(methods: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, dict[str, Any]]:
    """Table 1: the last task's T_cpl, sum F_RX, sum F_RZ, J and outcome per method."""
    out = {}
    for m, recs in methods.items():
        if not recs:
            continue
        r = recs[-1]
        out[m] = {"task": r.get("task", len(recs)), "t_cpl": r["t_cpl"], "sum_fx": r["sum_fx"],
                  "sum_fz": r["sum_fz"], "cost": r["cost"], "outcome": r["outcome"]}
        for key in ("t_cpl", "sum_fx", "sum_fz", "cost"):
            if f"{key}_std" in r:
                out[m][f"{key}_std"] = r[f"{key}_std"]
    return out


def _pm(rec: Mapping[str, Any], key: str, fmt: str) -> str:
    val = format(rec[key], fmt)
    if f"{key}_std" in rec and rec.get("n_seeds", 1) > 1:
        val += " ± " + format(rec[f"{key}_std"], fmt)
    return val


def table1_markdown(methods: Mapping[str, Sequence[Mapping[str, Any]]]) -> str:
    """Table 1 as a Markdown table (mean ± std over seeds when there are several)."""
    rows = ["| Method | task | T_cpl (s) | ΣF_RX (N) | ΣF_RZ (N) | J | outcome |",
            "|---|---|---|---|---|---|---|"]
    for m, recs in methods.items():
        if not recs:
            continue
        r = recs[-1]
        rows.append(f"| {m} | {r.get('task', len(recs))} | {_pm(r, 't_cpl', '.1f')} | "
                    f"{_pm(r, 'sum_fx', '.1f')} | {_pm(r, 'sum_fz', '.1f')} | "
                    f"{_pm(r, 'cost', '.2f')} | {r['outcome']} |")
    return "\n".join(rows) + "\n"


def evaluate_targets(methods: Mapping[str, Sequence[Mapping[str, Any]]],
                     runs: Mapping[str, Mapping[str, Sequence[Mapping[str, Any]]]],
                     ol: str = "ol-mppi") -> dict[str, Any]:
    """The experiment's targets (docs/experiments.md), each measured (True/False/None when a method is missing)."""
    res: dict[str, Any] = {"n_seeds": len(runs)}
    if ol not in methods:
        return res
    c = [r["cost"] for r in methods[ol]]
    n = len(c)
    k = max(1, min(3, n // 4)) if n >= 2 else 1
    res["ol_cost_first"] = c[0]
    res["ol_cost_last"] = c[-1]
    res["ol_cost_first_mean_of"] = float(np.mean(c[:k]))
    res["ol_cost_last_mean_of"] = float(np.mean(c[-k:]))
    res["ol_cost_falls"] = bool(n >= 2 and np.mean(c[-k:]) < np.mean(c[:k]))
    if n >= 2:
        res["ol_cost_slope_per_task"] = float(np.polyfit(np.arange(n), c, 1)[0])
    for b in ("baseline1", "baseline2"):
        if methods.get(b):
            res[f"ol_last_below_{b}"] = bool(c[-1] < methods[b][-1]["cost"])
    if methods.get("baseline1"):
        b1, o = methods["baseline1"][-1], methods[ol][-1]
        res["ol_t_cpl_below_baseline1"] = bool(o["t_cpl"] < b1["t_cpl"])
        res["ol_sum_f_below_baseline1"] = bool(o["sum_fx"] < b1["sum_fx"]
                                               and o["sum_fz"] < b1["sum_fz"])
    stops = {m: sum(1 for s in runs for r in runs[s][m] if r["outcome"] == "safety_stop")
             for m in methods}
    res["safety_stops"] = stops
    res["ol_no_safety_stop"] = stops.get(ol, 0) == 0
    # J (Eq. 3) has no term for how close a peel came to the limit; report the peak force too
    peaks = {m: [max(float(r.get("max_abs_fx", 0.0)), float(r.get("max_abs_fz", 0.0)))
                 for s in runs for r in runs[s][m]] for m in methods}
    res["peak_force_mean"] = {m: float(np.mean(v)) if v else None for m, v in peaks.items()}
    res["near_misses"] = {m: int(sum(x > NEAR_MISS_N for x in v)) for m, v in peaks.items()}
    res["peels_per_method"] = {m: len(v) for m, v in peaks.items()}
    if methods.get(ORACLE) and methods.get("baseline1"):
        o_mean = float(np.mean([r["cost"] for r in methods[ORACLE]]))
        b_mean = float(np.mean([r["cost"] for r in methods["baseline1"]]))
        res["oracle_mean_cost"] = o_mean
        res["baseline1_mean_cost"] = b_mean
        res["oracle_below_baseline1"] = bool(o_mean < b_mean)
    gaps = gaps_to_oracle(methods).get(ol)
    if gaps is not None and n >= 5:
        rel = gaps["rel"]
        res["ol_rel_gap_task5"] = rel[4]
        res["ol_within_10pct_of_oracle_by_task5"] = bool(
            all(math.isfinite(g) and g <= 0.10 for g in rel[4:]))
    return res


# ------------------------------------------------------------------------------ figures

_STYLE = {"ol-mppi": ("tab:red", "o"), "ol-mppi-fast": ("tab:purple", "D"),
          "baseline1": ("tab:blue", "s"),
          "baseline2": ("tab:green", "^"), ORACLE: ("black", "")}


def plot_fig11(methods: Mapping[str, Sequence[Mapping[str, Any]]], path: Path,
               title: str = "Fig. 11: total cost per task") -> Path:
    """Cost J per task, one line per method (min-max band over seeds when there are several)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for m, recs in methods.items():
        color, marker = _STYLE.get(m, (None, "x"))
        x = [r.get("task", i + 1) for i, r in enumerate(recs)]
        y = [r["cost"] for r in recs]
        ls = "--" if m == ORACLE else "-"
        ax.plot(x, y, ls, color=color, marker=marker or None, ms=4, label=m)
        if recs and "cost_min" in recs[0] and recs[0].get("n_seeds", 1) > 1:
            ax.fill_between(x, [r["cost_min"] for r in recs], [r["cost_max"] for r in recs],
                            color=color, alpha=0.15, lw=0)
    ax.set_xlabel("task")
    ax.set_ylabel("total cost J (Eq. 3)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    return _savefig(fig, path)


def plot_fig12(traces: Mapping[str, Mapping[str, Sequence[float]]], path: Path,
               title: str = "Fig. 12: velocity and forces in the last task") -> Path:
    """Velocity (and command), F_RX and F_RZ over time, one line per method."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    for m, tr in traces.items():
        color, _ = _STYLE.get(m, (None, ""))
        ls = "--" if m == ORACLE else "-"
        axes[0].plot(tr["t"], tr["v"], ls, color=color, label=m)
        axes[1].plot(tr["t"], tr["fx"], ls, color=color, label=m)
        axes[2].plot(tr["t"], tr["fz"], ls, color=color, label=m)
    for ax, lab in zip(axes, ("v (mm/s)", "F_RX (N)", "F_RZ (N)"), strict=True):
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t (s)")
    axes[0].legend(fontsize=8)
    axes[0].set_title(title)
    return _savefig(fig, path)


# ------------------------------------------------------------------------------ report.md


def _fmt(x: Any, fmt: str = ".2f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    if isinstance(x, bool):
        return "yes" if x else "**no**"
    if isinstance(x, float):
        return format(x, fmt)
    return str(x)


def _fmt_map(d: Mapping[str, Any] | None) -> str:
    if not d:
        return "n/a"
    return ", ".join(f"{k} {_fmt(v)}" for k, v in d.items())


def cost_table_markdown(methods: Mapping[str, Sequence[Mapping[str, Any]]]) -> str:
    """Cost per task (the data of Fig. 11), one column per method, plus the relative gap."""
    names = list(methods)
    gaps = gaps_to_oracle(methods)
    head = "| task | " + " | ".join(names) + " | " + " | ".join(
        f"gap {m}" for m in names if m in gaps) + " |"
    sep = "|---" * (1 + len(names) + len(gaps)) + "|"
    rows = [head, sep]
    n = max(len(v) for v in methods.values())
    for k in range(n):
        cells = [str(k + 1)]
        for m in names:
            recs = methods[m]
            cells.append(_fmt(recs[k]["cost"]) + ("" if recs[k]["outcome"] == "done"
                                                  else f" ({recs[k]['outcome']})")
                         if k < len(recs) else "")
        for m in names:
            if m in gaps:
                rel = gaps[m]["rel"]
                cells.append(f"{100 * rel[k]:+.1f}%" if k < len(rel) and math.isfinite(rel[k])
                             else "n/a")
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def flat_methods(results: Mapping[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """``results["methods"][m]["tasks"]`` (the results.json layout) as ``{m: tasks}``."""
    return {m: list(v["tasks"]) if isinstance(v, Mapping) else list(v)
            for m, v in results["methods"].items()}


def report_markdown(results: Mapping[str, Any]) -> str:
    """report.md: what was run, Fig. 11, Table 1, Fig. 12, gaps, targets and timings."""
    methods = flat_methods(results)
    t = results.get("targets", {})
    lines = [
        "# OL-MPPI experiment (paper 4.4)",
        "",
        f"Command: `{results.get('command', '')}`",
        "",
        f"Seeds: {results.get('seeds')}; tasks per method: {results.get('tasks')}; "
        f"pretrained checkpoint: `{results.get('checkpoint')}`; planner: "
        f"N = {results.get('planner', {}).get('n_samples')}, "
        f"H = {results.get('planner', {}).get('horizon')}, "
        f"lambda = {results.get('planner', {}).get('lambda')}.",
        "Every method peels the same sequence of plant substrates (one set of plant parameters "
        "per task, drawn from the seed); the oracle is the same MPPI planning with the plant's "
        "true, noise-free dynamics (`PeelEnv.rollout`).",
        "",
        "## Fig. 11: total cost per task",
        "",
        "![Fig. 11](fig11_cost_per_task.png)",
        "",
        cost_table_markdown(methods),
        "Gap = (J - J_oracle) / |J_oracle| (mean over seeds of J; J can be negative, see "
        "docs/experiments.md).",
        "",
        f"## Table 1: the last task (task {results.get('tasks')})",
        "",
        table1_markdown(methods),
        "## Fig. 12: velocity and forces in the last task (first seed)",
        "",
        "![Fig. 12](fig12_task_traces.png)",
        "",
        "## Targets (docs/experiments.md), measured",
        "",
        "| target | result |",
        "|---|---|",
        f"| OL-MPPI's cost falls over the tasks (mean of first vs last few tasks) | "
        f"{_fmt(t.get('ol_cost_falls'))} ({_fmt(t.get('ol_cost_first_mean_of'))} -> "
        f"{_fmt(t.get('ol_cost_last_mean_of'))}) |",
        f"| OL-MPPI ends below Baseline 1 | {_fmt(t.get('ol_last_below_baseline1'))} |",
        f"| OL-MPPI ends below Baseline 2 | {_fmt(t.get('ol_last_below_baseline2'))} |",
        f"| T_cpl below Baseline 1 (last task) | {_fmt(t.get('ol_t_cpl_below_baseline1'))} |",
        f"| ΣF_RX and ΣF_RZ below Baseline 1 (last task) | "
        f"{_fmt(t.get('ol_sum_f_below_baseline1'))} |",
        f"| no safety stop for OL-MPPI | {_fmt(t.get('ol_no_safety_stop'))} "
        f"(stops per method: {t.get('safety_stops')}) |",
        f"| within 10% of the oracle from task 5 on | "
        f"{_fmt(t.get('ol_within_10pct_of_oracle_by_task5'))} (gap at task 5: "
        f"{_fmt(100 * t['ol_rel_gap_task5'] if t.get('ol_rel_gap_task5') is not None else None, '+.1f')}%) |",
        f"| seeds | {t.get('n_seeds')} |",
        "",
        "Peak force per peel (max of |F_RX|, |F_RZ|; J has no term for it), mean over all "
        f"peels: {_fmt_map(t.get('peak_force_mean'))}; peels above {NEAR_MISS_N:g} N "
        f"(near misses of the 20 N stop): {t.get('near_misses')} of "
        f"{t.get('peels_per_method')}. Mean J over all tasks: oracle "
        f"{_fmt(t.get('oracle_mean_cost'))}, Baseline 1 {_fmt(t.get('baseline1_mean_cost'))} "
        "(if the oracle is not below Baseline 1, a more accurate model cannot lower J here).",
        "",
        "## Timing",
        "",
    ]
    timing = results.get("timing", {})
    for key, val in timing.items():
        lines.append(f"- {key}: {_fmt(val, '.3f')}")
    if results.get("task20_model"):
        lines += ["", f"OL-MPPI's model of the last task: `{results['task20_model']}` "
                  "(input of `peel experiment sweep`)."]
    return "\n".join(lines) + "\n"


def write_experiment_outputs(results: dict[str, Any], out: Path) -> dict[str, Path]:
    """results.json, fig11, fig12, table1.md and report.md in ``out``."""
    out = Path(out)
    methods = flat_methods(results)
    paths = {
        "fig11": plot_fig11(methods, out / "fig11_cost_per_task.png"),
        "fig12": plot_fig12(results.get("traces", {}), out / "fig12_task_traces.png"),
        "table1": write_text(out / "table1.md", table1_markdown(methods)),
        "report": write_text(out / "report.md", report_markdown(results)),
    }
    paths["results"] = write_json(out / "results.json", results)
    return paths


# ------------------------------------------------------------------------------ Table 2


def sweep_markdown(sweep: Mapping[str, Any]) -> str:
    """Table 2: total cost (mean ± std over seeds) for each value of N, H and lambda."""
    rows = ["| Hyperparameter | Value | Total cost J (mean ± std) | min | max | T_cpl (s) | "
            "safety stops | seeds |", "|---|---|---|---|---|---|---|---|"]
    for factor, entries in sweep["table2"].items():
        for e in entries:
            rows.append(
                f"| {factor} | {e['value']:g} | {e['cost_mean']:.2f} ± {e['cost_std']:.2f} | "
                f"{e['cost_min']:.2f} | {e['cost_max']:.2f} | {e['t_cpl_mean']:.1f} | "
                f"{e['safety_stops']} | {e['n']} |")
    return "\n".join(rows) + "\n"


def plot_sweep(sweep: Mapping[str, Any], path: Path) -> Path:
    """Table 2 as three panels: mean cost with std error bars against each factor."""
    plt = _pyplot()
    table = sweep["table2"]
    fig, axes = plt.subplots(1, len(table), figsize=(4 * len(table), 3.2), squeeze=False)
    for ax, (factor, entries) in zip(axes[0], table.items(), strict=True):
        x = [e["value"] for e in entries]
        ax.errorbar(x, [e["cost_mean"] for e in entries], yerr=[e["cost_std"] for e in entries],
                    marker="o", capsize=3)
        ax.set_xlabel(factor)
        ax.set_ylabel("total cost J")
        if factor == "lambda":
            ax.set_xscale("log")
        ax.grid(alpha=0.3)
    fig.suptitle("Table 2: hyperparameters (one factor at a time)")
    return _savefig(fig, path)
