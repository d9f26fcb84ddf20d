"""``peel fast-report``: what the fast step inside the peel bought, from a ``peel experiment``
results.json that ran ``ol-mppi-fast`` beside the paper's arms and the oracle (docs/experiments.md,
"The fast step inside the peel").

Per arm, the fraction of headroom closed at single tasks (window 0 of
:func:`peel_experiments.grid.closed_fraction`: pooled over seeds, and the mean and 95 %
t-interval of the per-seed values); for ``ol-mppi-fast`` the one-step force error (Eq. 39, both
channels) of the model in use over task 1's second half against the pretrained model's on the
same samples (per seed and the ratio of the means), the fast steps' and updates' times, and a
PNG of task 1's error per sample. Per OL-MPPI arm against the baselines, task by task (the same
substrate in every arm): J_arm - J_B2 and J_arm - J_B1, mean and 95 % t-interval over seeds;
"not shown no worse than Baseline 2" at a task is an upper end above 0 (the target asks for <=
0), "above Baseline 1 beyond noise" a lower end above 0; the largest single peel over
Baseline 1; and J_arm - J_B2 over tasks 11-15, the five peels after the batch switch
(docs/experiments.md, "Plant levels"). Writes
``fast_report.json``, ``fast_report.md`` and ``fast_task1_error.png`` to ``--out``; prints the
JSON.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.cliargs import ArgumentParser, int_list, run_main
from peel_msgs_py.errors import PeelError
from peel_msgs_py.outputs import check_location

from .fast_arm import FAST
from .grid import ci95, closed_fraction

ARMS = (FAST, "ol-mppi", "baseline2")
#: the OL-MPPI arms compared with the baselines task by task
OL_ARMS = (FAST, "ol-mppi")
#: the tasks after the batch switch (the new pad batch arrives at task 11)
AFTER_SWITCH = (11, 15)


def _fast_records(runs: Mapping[str, Any], task: int) -> list[dict[str, Any]]:
    return [runs[s][FAST]["tasks"][task - 1]["fast"] for s in runs
            if len(runs[s][FAST]["tasks"]) >= task]


def within_task(runs: Mapping[str, Any]) -> dict[str, Any]:
    """Task 1's second-half one-step errors of ``ol-mppi-fast``: model in use vs pretrained."""
    recs = _fast_records(runs, 1)
    use = [r["error_in_use_second_half_n"] for r in recs]
    pre = [r["error_pretrained_second_half_n"] for r in recs]
    return {"in_use_n": ci95(use), "pretrained_n": ci95(pre),
            "ratio_per_seed": ci95([u / p for u, p in zip(use, pre, strict=True)]),
            "ratio_of_means": float(np.mean(use) / np.mean(pre)) if recs else None,
            "target_ratio": 0.7}


def timing(runs: Mapping[str, Any]) -> dict[str, Any]:
    """Fast-step times (every step of every task and seed) and between-peel update times."""
    fast = [t for s in runs for rec in runs[s][FAST]["tasks"] for t in rec["fast"]["fast_s"]]
    steps = [(rec["fast"]["steps"], rec["fast"]["accepted"]) for s in runs
             for rec in runs[s][FAST]["tasks"]]
    out: dict[str, Any] = {
        "fast_s_median": float(np.median(fast)) if fast else None,
        "fast_s_p95": float(np.percentile(fast, 95)) if fast else None,
        "fast_s_max": float(np.max(fast)) if fast else None,
        "fast_steps": int(sum(n for n, _ in steps)), "fast_accepted": int(sum(a for _, a in steps)),
    }
    for m in (FAST, "ol-mppi", "baseline2"):
        ups = [rec["next_update_s"] for s in runs for rec in runs[s].get(m, {}).get("tasks", [])
               if "next_update_s" in rec]
        out[f"{m}_update_s_mean"] = float(np.mean(ups)) if ups else None
        out[f"{m}_update_s_max"] = float(np.max(ups)) if ups else None
    plans = [rec["plan_s"] for s in runs for m in (FAST, "ol-mppi", "baseline1", "baseline2")
             for rec in runs[s].get(m, {}).get("tasks", [])]
    out["plan_s_task_mean_max"] = float(np.max(plans)) if plans else None  # learned models
    return out


def _paired(runs: Mapping[str, Any], arm: str, base: str, n: int) -> np.ndarray:
    """(seeds, n) array of J_arm - J_base, task by task."""
    return np.array([[runs[s][arm]["tasks"][k]["cost"] - runs[s][base]["tasks"][k]["cost"]
                      for k in range(n)] for s in runs], dtype=float)


def against_baselines(runs: Mapping[str, Any], arm: str, n: int) -> dict[str, Any]:
    """Task by task, ``arm`` against Baseline 2 and Baseline 1 (module docstring)."""
    d2, d1 = _paired(runs, arm, "baseline2", n), _paired(runs, arm, "baseline1", n)
    b1 = np.array([[runs[s]["baseline1"]["tasks"][k]["cost"] for k in range(n)] for s in runs])
    per2 = [ci95(d2[:, k]) for k in range(n)]
    per1 = [ci95(d1[:, k]) for k in range(n)]

    def upper_above_0(per: list[dict[str, Any]]) -> list[int]:
        return [k + 1 for k, c in enumerate(per) if c["ci95"] is not None and c["mean"] + c["ci95"] > 0]

    def lower_above_0(per: list[dict[str, Any]]) -> list[int]:
        return [k + 1 for k, c in enumerate(per) if c["ci95"] is not None and c["mean"] - c["ci95"] > 0]

    worst = np.unravel_index(int(np.argmax(d1)), d1.shape)
    out: dict[str, Any] = {
        "minus_b2": per2, "minus_b1": per1,
        "tasks_b2_upper_end_above_0": upper_above_0(per2),
        "tasks_above_b1_beyond_noise": lower_above_0(per1),
        "max_above_b1": {"seed": list(runs)[worst[0]], "task": int(worst[1]) + 1,
                         "j_minus_b1": float(d1[worst]), "relative": float(d1[worst] / b1[worst])},
    }
    lo, hi = AFTER_SWITCH
    if n >= hi:
        out["minus_b2_tasks_11_15"] = ci95(d2[:, lo - 1:hi].mean(axis=1))
    return out


def summarize(results: Mapping[str, Any], tasks: Sequence[int]) -> dict[str, Any]:
    runs = results["runs"]
    seed0 = next(iter(runs))
    missing = [m for m in (*ARMS, "baseline1", "oracle") if m not in runs[seed0]]
    if missing:
        raise PeelError(f"results.json lacks the arm(s) {', '.join(missing)}")
    n = min(len(runs[s]["baseline1"]["tasks"]) for s in runs)
    closed = {m: {str(k): closed_fraction(runs, m, k, window=0) for k in tasks if k <= n}
              for m in ARMS}
    stops = {m: sum(r["outcome"] == "safety_stop" for s in runs for r in runs[s][m]["tasks"])
             for m in runs[seed0]}
    return {"seeds": list(runs), "tasks": n, "plant": results.get("plant", {}).get("name"),
            "sequence": results.get("sequence"), "command": results.get("command"),
            "closed": closed, "against_baselines": {m: against_baselines(runs, m, n) for m in OL_ARMS},
            "within_task1": within_task(runs), "timing": timing(runs),
            "safety_stops": stops}


def plot_task1(runs: Mapping[str, Any], path: Path) -> Path:
    """Task 1's one-step error per sample, model in use vs pretrained, one panel per seed."""
    from .report import _pyplot, _savefig

    plt = _pyplot()
    seeds = list(runs)
    fig, axes = plt.subplots(1, len(seeds), figsize=(4 * len(seeds), 3.2), squeeze=False)
    for ax, s in zip(axes[0], seeds, strict=True):
        rec = runs[s][FAST]["tasks"][0]["fast"]
        pre, use = np.asarray(rec["error_pretrained_n"]), np.asarray(rec["error_in_use_n"])
        k = np.arange(1, len(pre) + 1)
        ax.plot(k, pre, color="tab:blue", lw=1, label="pretrained")
        ax.plot(k, use, color="tab:purple", lw=1, label="model in use (fast step)")
        for r in rec["results"]:
            if r["accepted"]:
                ax.axvline(r["n_samples"], color="tab:purple", alpha=0.2, lw=0.8)
        ax.axvspan(len(pre) // 2, len(pre), color="grey", alpha=0.08)
        ax.set_title(f"seed {s}: 2nd half {rec['error_in_use_second_half_n']:.2f} vs "
                     f"{rec['error_pretrained_second_half_n']:.2f} N", fontsize=9)
        ax.set_xlabel("target sample k+1 of task 1")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("one-step error ||F - f|| (N)")
    axes[0][0].legend(fontsize=8)
    return _savefig(fig, path)


def _fmt(c: Mapping[str, Any]) -> str:
    if c.get("mean") is None:
        return "-"
    half = "" if c.get("ci95") is None else f" ± {c['ci95']:.2f}"
    pooled = "" if c.get("pooled") is None else f" (pooled {c['pooled']:.2f})"
    return f"{c['mean']:.2f}{half}{pooled}"


def markdown(s: Mapping[str, Any]) -> str:
    ks = sorted({k for m in s["closed"].values() for k in m}, key=int)
    lines = [f"# The fast step inside the peel: {s['plant']}, {s['sequence']}, seeds "
             f"{', '.join(s['seeds'])}", "", "Fraction of headroom closed at task k (one task; "
             "mean ± 95 % t-interval over seeds, pooled beside):", "",
             "| arm | " + " | ".join(f"task {k}" for k in ks) + " |",
             "|---|" + "---|" * len(ks)]
    for m, per in s["closed"].items():
        lines.append(f"| {m} | " + " | ".join(_fmt(per[k]) for k in ks) + " |")
    w, t = s["within_task1"], s["timing"]
    lines += ["", f"Task 1, second half, one-step error: model in use {_fmt(w['in_use_n'])} N, "
              f"pretrained {_fmt(w['pretrained_n'])} N; ratio per seed "
              f"{_fmt(w['ratio_per_seed'])}, of the means {w['ratio_of_means']:.3f} "
              f"(target <= {w['target_ratio']}).", "",
              f"Fast steps: {t['fast_steps']} taken, {t['fast_accepted']} used; time median "
              f"{t['fast_s_median']:.3f} s, p95 {t['fast_s_p95']:.3f} s, max {t['fast_s_max']:.3f}"
              f" s. Updates between peels: ol-mppi-fast {t[f'{FAST}_update_s_mean']:.2f} s mean, "
              f"ol-mppi {t['ol-mppi_update_s_mean']:.2f} s, baseline 2 "
              f"{t['baseline2_update_s_mean']:.2f} s. Safety stops: {s['safety_stops']}.", "",
              "![task 1 error](fast_task1_error.png)", ""]
    return "\n".join(lines + _against_markdown(s["against_baselines"]))


def _against_markdown(against: Mapping[str, Any]) -> list[str]:
    arms = list(against)
    n = len(against[arms[0]]["minus_b2"])
    lines = ["J of each OL-MPPI arm minus Baseline 2's and Baseline 1's on the same substrate "
             "(mean ± 95 % t-interval over seeds):", "",
             "| task | " + " | ".join(f"{m} - B2 | {m} - B1" for m in arms) + " |",
             "|---|" + "---|---|" * len(arms)]
    for k in range(n):
        lines.append(f"| {k + 1} | " + " | ".join(
            f"{_fmt(against[m]['minus_b2'][k])} | {_fmt(against[m]['minus_b1'][k])}" for m in arms) + " |")
    lines.append("")
    for m in arms:
        a, w = against[m], against[m]["max_above_b1"]
        after = a.get("minus_b2_tasks_11_15")
        lines.append(f"- {m}: interval against Baseline 2 with its upper end above 0 at tasks "
                     f"{a['tasks_b2_upper_end_above_0'] or 'none'}; "
                     f"above Baseline 1 beyond noise (lower end > 0) at tasks "
                     f"{a['tasks_above_b1_beyond_noise'] or 'none'}; largest single peel over Baseline 1: "
                     f"{w['j_minus_b1']:+.2f} ({w['relative']:+.0%}), seed {w['seed']} task {w['task']}"
                     + (f"; tasks 11-15 against Baseline 2: {_fmt(after)}" if after else "") + ".")
    return [*lines, ""]


def read_results(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PeelError(f"{path}: cannot read results ({exc})") from None


def merge(parts: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Several experiments' results as one: their seeds' runs together (a seed in two, or a
    different plant or sequence, is refused), every command listed."""
    runs: dict[str, Any] = {}
    for part in parts:
        for seed, run in part["runs"].items():
            if seed in runs:
                raise PeelError(f"seed {seed} is in two of the results files")
            runs[seed] = run
    first = parts[0]
    if any(p.get("plant", {}).get("name") != first.get("plant", {}).get("name")
           or p.get("sequence") != first.get("sequence") for p in parts):
        raise PeelError("the results files are of different plants or sequences")
    return {**first, "runs": runs, "command": [p.get("command") for p in parts]}


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="peel fast-report", description=__doc__.split("\n\n")[0])
    p.add_argument("results", type=Path, nargs="+",
                   help="results.json of peel experiment; several: their seeds together")
    p.add_argument("--out", type=Path, required=True, help="folder for the report files")
    p.add_argument("--tasks", type=int_list(min=1), default=[1, 2, 3, 5],
                   help="tasks at which the fraction closed is given (default 1,2,3,5)")
    args = p.parse_args(argv)
    check_location(args.out, "--out")
    results = merge([read_results(path) for path in args.results])
    summary = summarize(results, args.tasks)
    args.out.mkdir(parents=True, exist_ok=True)
    plot_task1(results["runs"], args.out / "fast_task1_error.png")
    text = json.dumps(summary, indent=1)
    atomic_write_text(args.out / "fast_report.json", text + "\n")
    atomic_write_text(args.out / "fast_report.md", markdown(summary))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(run_main("peel fast-report", main, sys.argv[1:]))
