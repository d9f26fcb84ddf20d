"""Planner cost and safety margin per task, before and after a correction (docs/residual.md).

    python -m peel_bringup.residual_compare --before RUN BAG --after RUN BAG --out DIR
                                            [--label-before TEXT] [--label-after TEXT]

``RUN`` is a ``peel graph --out`` directory (its ``summary.json`` holds J of Eq. 3 per task),
``BAG`` the ``--record`` bag of that run (its ``/peel/trajectory`` messages give the peak forces).
The safety margin of a task is the 20 N prewarning (section 4.2) minus its largest measured
|F_RX| or |F_RZ|. Writes ``DIR/comparison.json``, ``DIR/comparison.md`` and
``DIR/comparison.png``; prints the JSON. Used by ``scripts/residual_demo.sh``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.errors import PeelError

F_PREWARN_N = 20.0  # section 4.2; the same value as safety.f_prewarn_n in the configs


def run_tasks(run: Path, bag: Path) -> list[dict[str, Any]]:
    """Per task: J, outcome, T_cpl, model version, peak |F|, safety margin."""
    from peel_msgs_py.bagread import read_trajectories

    try:
        summary = json.loads((run / "summary.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PeelError(f"{run}/summary.json: {exc}") from None
    trajs = read_trajectories(bag)
    results = summary.get("results", [])
    if len(trajs) != len(results):
        raise PeelError(f"{bag} holds {len(trajs)} tasks, {run}/summary.json {len(results)}")
    out = []
    for res, tr in zip(results, trajs, strict=True):
        peak = float(max(np.abs(tr.fx).max(), np.abs(tr.fz).max())) if len(tr) else 0.0
        out.append({"task": res["task"], "J": res["J"], "outcome": res["outcome"],
                    "t_cpl_s": res["t_cpl_s"], "model_version": res.get("model_version"),
                    "peak_force_n": peak, "safety_margin_n": F_PREWARN_N - peak})
    return out


def _stats(tasks: list[dict[str, Any]]) -> dict[str, Any]:
    def col(k: str) -> np.ndarray:
        return np.array([t[k] for t in tasks], dtype=float)

    return {"tasks": len(tasks), "J_mean": float(col("J").mean()),
            "J_sum": float(col("J").sum()), "t_cpl_mean_s": float(col("t_cpl_s").mean()),
            "safety_margin_min_n": float(col("safety_margin_n").min()),
            "safety_margin_mean_n": float(col("safety_margin_n").mean()),
            "safety_stops": sum(t["outcome"] == "safety_stop" for t in tasks),
            "done": sum(t["outcome"] == "done" for t in tasks)}


def _figure(path: Path, before: list[dict], after: list[dict], labels: tuple[str, str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.0, 3.4))
    for tasks, label in ((before, labels[0]), (after, labels[1])):
        k = [t["task"] for t in tasks]
        axes[0].plot(k, [t["J"] for t in tasks], "o-", ms=3, label=label)
        axes[1].plot(k, [t["safety_margin_n"] for t in tasks], "o-", ms=3, label=label)
    axes[0].set_ylabel("planner cost J (Eq. 3)")
    axes[1].set_ylabel("safety margin 20 N - peak |F| (N)")
    for ax in axes:
        ax.set_xlabel("task")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def compare(before: tuple[Path, Path], after: tuple[Path, Path], out: Path,
            labels: tuple[str, str] = ("before", "after")) -> dict[str, Any]:
    """Write the comparison files into ``out``; returns the JSON dict."""
    b, a = run_tasks(*before), run_tasks(*after)
    rep = {"before": {"run": str(before[0]), "bag": str(before[1]), "label": labels[0],
                      "summary": _stats(b), "tasks": b},
           "after": {"run": str(after[0]), "bag": str(after[1]), "label": labels[1],
                     "summary": _stats(a), "tasks": a},
           "f_prewarn_n": F_PREWARN_N}
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "comparison.json", json.dumps(rep, indent=1) + "\n")
    lines = [f"# Planner cost and safety margin: {labels[0]} vs {labels[1]}", "",
             "| task | J before | J after | T_cpl before (s) | T_cpl after (s) | margin before "
             "(N) | margin after (N) | outcome before | outcome after |",
             "|---|---|---|---|---|---|---|---|---|"]
    for x, y in zip(b, a, strict=False):
        lines.append(f"| {x['task']} | {x['J']:.2f} | {y['J']:.2f} | {x['t_cpl_s']:.1f} | "
                     f"{y['t_cpl_s']:.1f} | {x['safety_margin_n']:.2f} | "
                     f"{y['safety_margin_n']:.2f} | {x['outcome']} | {y['outcome']} |")
    sb, sa = rep["before"]["summary"], rep["after"]["summary"]
    lines += ["", "| | before | after |", "|---|---|---|"]
    for key, text in (("J_mean", "mean J"), ("t_cpl_mean_s", "mean T_cpl (s)"),
                      ("safety_margin_mean_n", "mean safety margin (N)"),
                      ("safety_margin_min_n", "smallest safety margin (N)"),
                      ("safety_stops", "safety stops"), ("done", "done")):
        lines.append(f"| {text} | {sb[key]:.2f} | {sa[key]:.2f} |" if isinstance(sb[key], float)
                     else f"| {text} | {sb[key]} | {sa[key]} |")
    atomic_write_text(out / "comparison.md", "\n".join(lines) + "\n\n![](comparison.png)\n")
    _figure(out / "comparison.png", b, a, labels)
    return rep


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m peel_bringup.residual_compare",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--before", nargs=2, type=Path, required=True, metavar=("RUN", "BAG"))
    p.add_argument("--after", nargs=2, type=Path, required=True, metavar=("RUN", "BAG"))
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--label-before", default="before")
    p.add_argument("--label-after", default="after")
    args = p.parse_args(argv)
    try:
        rep = compare(tuple(args.before), tuple(args.after), args.out,
                      (args.label_before, args.label_after))
    except PeelError as exc:
        print(f"residual_compare: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: rep[k]["summary"] for k in ("before", "after")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
