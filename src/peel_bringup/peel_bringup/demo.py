"""``peel demo``: the main job. A few tasks through the node graph on the plant, with a bag.

    peel demo [--tasks 3] [--out DIR [--force]] [--params FILE] [--seed S] [--plant plant|sim]
              [--live [PORT] [--live-host HOST]]

Runs ``peel graph --plant plant --tasks 3 --record OUT/bag`` with the shipped checkpoint (the
planner starts from :func:`peel_model.checkpoint.shipped_checkpoint`; the learner's
Algorithm 1 updates it after every task), prints one line per task, then reads the bag back
with ``rosbags`` (:mod:`peel_bag.bagread`) and draws, per task, the blade velocity (measured
v and command u) and the contact forces F_RX, F_RZ against the task time: ``OUT/demo.png``.
``OUT/demo.md`` (with ``OUT/summary.json`` beside it) describes the run. ``--live [PORT]``
serves the running graph on a Foxglove WebSocket meanwhile (``peel graph --live``).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.atomic import atomic_write, atomic_write_text
from peel_msgs_py.cliargs import ArgumentParser, nonnegative_int, positive_int, run_main
from peel_msgs_py.errors import PeelError
from peel_msgs_py.outputs import OutputDir


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="peel demo", description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", type=positive_int, default=3, metavar="K", help="tasks (default 3)")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="run directory (default runs/demo/<time>)")
    p.add_argument("--force", action="store_true", help="replace an earlier run in --out")
    p.add_argument("--params", metavar="FILE", default=None, help="parameter override file")
    p.add_argument("--seed", type=nonnegative_int, default=None, help="seed of the task sequence")
    p.add_argument("--plant", choices=("sim", "plant"), default="plant",
                   help="where the tasks run (default: the plant)")
    from .graph import add_live_args

    add_live_args(p)
    return p


def split_tasks(topics: dict[str, dict[str, np.ndarray]]) -> list[dict[str, Any]]:
    """Per task (``header.frame_id`` = ``peel_task_<k>``): time in the task (s) and the arrays
    v (mm/s), u (mm/s), F_RX, F_RZ (N), each as ``(t, value)``; re-sent samples dropped."""
    import peel_msgs_py.topics as T

    pose = topics.get(T.POSE)
    if pose is None or not len(pose["t_s"]):
        raise PeelError("the bag has no /peel/pose messages")
    out = []
    for task in sorted(int(k) for k in np.unique(pose["task"]) if k >= 0):
        t0 = float(pose["t_s"][pose["task"] == task].min())

        def cut(topic: str, col: str, task: int = task, t0: float = t0) -> tuple[np.ndarray, ...]:
            d = topics.get(topic)
            if d is None:
                return np.zeros(0), np.zeros(0)
            keep = d["task"] == task
            tt, vv = d["t_s"][keep] - t0, d[col][keep]
            _, first = np.unique(np.round(tt, 6), return_index=True)
            return tt[first], vv[first]

        out.append({"task": task, "v": cut(T.TWIST, "v_mmps"), "u": cut(T.CMD_VEL, "u_mmps"),
                    "fx": cut(T.WRENCH, "fx_n"), "fz": cut(T.WRENCH, "fz_n")})
    return out


def lockstep_speed(topics: dict[str, dict[str, np.ndarray]]) -> dict[str, float]:
    """Simulated time per wall second in lockstep, from the bag: per task, the recorder's
    receive times of consecutive commands (one per 0.5 s control period of simulated time);
    the median wall time per period and the ratio of simulated to wall time."""
    import peel_msgs_py.topics as T

    cmd = topics.get(T.CMD_VEL)
    if cmd is None or len(cmd["t_s"]) < 3:
        return {}
    walls, sims = [], []
    for task in np.unique(cmd["task"]):
        keep = cmd["task"] == task
        t, log = cmd["t_s"][keep], cmd["log_ns"][keep] / 1e9
        _, first = np.unique(np.round(t, 6), return_index=True)
        t, log = t[first], log[first]
        walls += np.diff(log).tolist()
        sims += np.diff(t).tolist()
    if not walls:
        return {}
    wall = float(np.median(walls))
    return {"periods": len(walls), "wall_ms_per_period_median": round(wall * 1e3, 1),
            "sim_per_wall": round(float(np.median(sims)) / wall, 1) if wall > 0 else float("inf")}


def plot_tasks(tasks: list[dict[str, Any]], path: Path, title: str) -> Path:
    """Velocity and forces per task (one column per task), written atomically as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(tasks)
    fig, axes = plt.subplots(2, n, figsize=(4.2 * n, 6.0), squeeze=False, sharey="row")
    for i, d in enumerate(tasks):
        ax = axes[0][i]
        ax.plot(*d["v"], label="v measured")
        ax.step(*d["u"], where="post", label="u command")
        ax.set_title(f"task {d['task'] + 1}")
        ax.set_xlabel("t in task [s]")
        ax.grid(alpha=0.3)
        ax = axes[1][i]
        ax.plot(*d["fx"], label="F_RX")
        ax.plot(*d["fz"], label="F_RZ")
        ax.axhline(20.0, color="red", lw=0.8, ls="--", label="20 N prewarning")
        ax.set_xlabel("t in task [s]")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("blade (TCP) velocity [mm/s]")
    axes[1][0].set_ylabel("contact force [N]")
    axes[0][0].legend(loc="best", fontsize=8)
    axes[1][0].legend(loc="best", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))
    plt.close(fig)
    return path


def write_report(run_dir: Path, summary: dict[str, Any], png: Path, bag: Path,
                 wall_s: float, speed: dict[str, float]) -> Path:
    """``demo.md`` beside ``summary.json``."""
    lines = [
        "# peel demo", "",
        f"{summary['tasks']} tasks on the {summary['plant']} through the node graph "
        f"(seed {summary['seed']}), shipped checkpoint, online learning after every task. "
        f"Wall time {wall_s:.0f} s.", "",
        "| task | outcome | T_cpl [s] | J | sum F_RX [N] | sum F_RZ [N] | model |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in summary["results"]:
        lines.append(f"| {r['task']} | {r['outcome']} | {r['t_cpl_s']:.1f} | {r['J']:.2f} | "
                     f"{r['sum_fx_n']:.1f} | {r['sum_fz_n']:.1f} | v{r['model_version']} |")
    if speed:
        lines += ["", f"Lockstep: {speed['wall_ms_per_period_median']:.1f} ms of wall time per "
                  f"0.5 s control period (median of {speed['periods']}), simulated time at "
                  f"{speed['sim_per_wall']:.1f}x the wall clock (from the bag's receive times)."]
    lines += ["", f"![velocity and forces per task]({png.name})", "",
              f"Bag: `{bag}`; per-task numbers: `summary.json`; models: `models/`; "
              "node logs: `logs/`.", ""]
    path = run_dir / "demo.md"
    return atomic_write_text(path, "\n".join(lines))


def graph_argv(args: Any, run_dir: Path, bag: Path) -> list[str]:
    """The ``peel graph`` arguments of a demo: its tasks on its plant, recorded to ``bag``."""
    return (["--plant", args.plant, "--tasks", str(args.tasks), "--record", str(bag),
             "--out", str(run_dir)]
            + (["--force"] if args.force else [])
            + (["--params", args.params] if args.params else [])
            + (["--seed", str(args.seed)] if args.seed is not None else [])
            + (["--live", str(args.live), "--live-host", args.live_host] if args.live else []))


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel demo``; returns the exit status."""
    from . import graph

    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    run_dir = Path(args.out) if args.out else Path("runs/demo") / time.strftime("%Y%m%d-%H%M%S")
    OutputDir(run_dir, command="peel demo", force=args.force)  # refused here, before the graph
    bag = run_dir / "bag"
    print(f"peel demo: {args.tasks} tasks on the {args.plant} through the node graph "
          f"(shipped checkpoint, online learning); this takes a few minutes", flush=True)
    t0 = time.monotonic()
    gargs = graph._parser().parse_args(graph_argv(args, run_dir, bag))
    gargs.command = "peel demo"
    status = graph.run_graph(gargs)
    wall = time.monotonic() - t0
    if status == graph.RECORDING_FAILED:
        return status  # the bag is cut short: the graph printed the repair command
    if not bag.exists():
        print("peel demo: error: no bag was recorded", file=sys.stderr)
        return status or 1
    from peel_bag.bagread import read_topics

    topics = read_topics(bag)
    tasks = split_tasks(topics)
    png = plot_tasks(tasks, run_dir / "demo.png",
                     f"peel demo: {len(tasks)} tasks on the {args.plant} (read back from the bag)")
    summary = json.loads((run_dir / "summary.json").read_text())
    speed = lockstep_speed(topics)
    report = write_report(run_dir, summary, png, bag, wall, speed)
    if speed:
        print(f"peel demo: lockstep {speed['wall_ms_per_period_median']:.1f} ms wall per 0.5 s "
              f"control period: simulated time at {speed['sim_per_wall']:.1f}x the wall clock",
              flush=True)
    print(f"peel demo: figure {png}\npeel demo: report {report}\npeel demo: bag {bag}\n"
          f"peel demo: models {run_dir / 'models'}  logs {run_dir / 'logs'}", flush=True)
    return status


if __name__ == "__main__":
    sys.exit(run_main("peel demo", main))
