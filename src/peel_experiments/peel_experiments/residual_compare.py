"""Planner cost and safety margin per task, before and after a correction (docs/residual.md).

    python -m peel_experiments.residual_compare --before RUN BAG --after RUN BAG --out DIR
                                            [--force] [--label-before TEXT] [--label-after TEXT]

``RUN`` is a ``peel graph --out`` directory (its ``summary.json`` holds J of Eq. 3 per task),
``BAG`` the ``--record`` bag of that run (its ``/peel/trajectory`` messages give the peak forces).
The safety margin of a task is the 20 N prewarning (section 4.2, ``task.f_prewarn_n``) minus its
largest measured |F_RX| or |F_RZ|. Writes ``DIR/comparison.json``, ``DIR/comparison.md`` and
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
from peel_msgs_py.cliargs import ArgumentParser, run_main
from peel_msgs_py.errors import PeelError
from peel_msgs_py.outputs import OutputDir


def f_prewarn_n() -> float:
    """The safety prewarning on abs F_RX or abs F_RZ (section 4.2; ``task.f_prewarn_n`` of
    config/peel_sim_node.yaml, 20 N)."""
    from peel_sim_node.config import load_sim_config

    return float(load_sim_config().task.f_prewarn_n)


def run_tasks(run: Path, bag: Path) -> list[dict[str, Any]]:
    """Per task: J, outcome, T_cpl, model version, peak |F|, safety margin."""
    from peel_bag.bagread import read_trajectories

    try:
        summary = json.loads((run / "summary.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PeelError(f"{run}/summary.json: {exc}") from None
    trajs = read_trajectories(bag)
    results = summary.get("results", [])
    if len(trajs) != len(results):
        raise PeelError(f"{bag} holds {len(trajs)} tasks, {run}/summary.json {len(results)}")
    out, limit = [], f_prewarn_n()
    for res, tr in zip(results, trajs, strict=True):
        peak = float(max(np.abs(tr.fx).max(), np.abs(tr.fz).max())) if len(tr) else 0.0
        out.append({"task": res["task"], "J": res["J"], "outcome": res["outcome"],
                    "t_cpl_s": res["t_cpl_s"], "model_version": res.get("model_version"),
                    "peak_force_n": peak, "safety_margin_n": limit - peak})
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
    axes[1].set_ylabel("safety margin: prewarning - peak |F| (N)")
    for ax in axes:
        ax.set_xlabel("task")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def compare(b: list[dict[str, Any]], a: list[dict[str, Any]], args: argparse.Namespace,
            out: Path) -> dict[str, Any]:
    """Write the comparison files into ``out``; returns the JSON dict."""
    labels = (args.label_before, args.label_after)
    rep = {"before": {"run": str(args.before[0]), "bag": str(args.before[1]), "label": labels[0],
                      "summary": _stats(b), "tasks": b},
           "after": {"run": str(args.after[0]), "bag": str(args.after[1]), "label": labels[1],
                     "summary": _stats(a), "tasks": a},
           "f_prewarn_n": f_prewarn_n()}
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
    p = ArgumentParser(prog="python -m peel_experiments.residual_compare",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--before", nargs=2, type=Path, required=True, metavar=("RUN", "BAG"))
    p.add_argument("--after", nargs=2, type=Path, required=True, metavar=("RUN", "BAG"))
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--force", action="store_true", help="replace an earlier comparison in --out")
    p.add_argument("--label-before", default="before")
    p.add_argument("--label-after", default="after")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    out = OutputDir(args.out, command="residual_compare", force=args.force)
    before, after = run_tasks(*args.before), run_tasks(*args.after)
    with out as out_dir:
        rep = compare(before, after, args, out_dir)
    print(json.dumps({k: rep[k]["summary"] for k in ("before", "after")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("residual_compare", main))
