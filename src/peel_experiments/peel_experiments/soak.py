"""``peel soak``: many consecutive peels through the node graph, with every node's memory.

    peel soak [--tasks 100] [--plant plant|sim] [--out DIR [--force]] [--params FILE]
              [--seed S] [--warmup 10] [--max-growth-mb 25] [--interval 5]

Runs ``peel graph --plant PLANT --tasks N --out DIR/graph`` (online learning after every task,
Algorithm 1) as a child process and uses only what that command offers the outside: its task
lines on stdout (``task i/N: <outcome> ...``), its ``summary.json``, and its process tree. At
every finished task and every ``--interval`` seconds it reads the resident set size (``VmRSS``
of ``/proc/<pid>/status``) of the launcher and of each descendant process, named by the node
module in its command line (``peel_sim_node``, ``peel_planner_node``, ``model_learner_node``,
the recorder), so it works whatever runtime the nodes use.

It reports, per node, the RSS at the first task, at task ``--warmup`` and at the last task, the
maximum, the growth after the warm-up and the least-squares slope over the tasks after it
(MB per task); a node is *flat* when it grew by at most ``--max-growth-mb`` after the warm-up.
Each node's ``verdict`` says which of four cases holds: ``flat``, ``grew``, ``too_few_tasks``
(the run ended before two tasks after the warm-up) or ``no_sample_after_warmup`` (the node was
not running when any task after the warm-up was read, e.g. the graph had begun stopping its nodes
when the last task's line arrived). ``flat`` is true or false in the first two cases and null in
the other two, and so is the run's ``memory_flat`` when any node is undetermined: the soak then
warns on stderr and does not fail on memory (an undetermined node is no measured growth).
It counts the outcomes (``safety_stop`` = the 20 N prewarning ended a peel, section 4.2).
Files: ``DIR/soak.json``, ``DIR/soak.md`` and ``DIR/soak_rss.png`` (RSS per node over tasks);
the graph's own run folder (models, logs, summary) is ``DIR/graph``. The JSON summary is printed
on stdout. Exit status: the graph's when it failed (3: a model update failed), else 1 when a task
is missing, a peel ended in a safety stop or a node's memory is not flat, else 0.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.atomic import atomic_write, atomic_write_text
from peel_msgs_py.cliargs import (
    ArgumentParser,
    float_arg,
    nonnegative_int,
    positive_float,
    positive_int,
    run_main,
)
from peel_msgs_py.errors import PeelError
from peel_msgs_py.outputs import OutputDir

#: Node names, and the modules / console scripts that run them.
NODES = {"peel_sim_node": "peel_sim_node", "peel_planner_node": "peel_planner_node",
         "model_learner_node": "model_learner_node", "peel_bag.recorder_cli": "recorder",
         "peel_recorder": "recorder"}
LAUNCHER = "peel_graph"
TASK_LINE = re.compile(r"^task (\d+)/(\d+): (\S+)")


# ------------------------------------------------------------------------------ process memory
def _children(pid: int) -> list[int]:
    """Direct children of ``pid`` (``/proc/*/stat`` field 4 = parent pid)."""
    out = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(OSError):
            stat = Path(f"/proc/{entry.name}/stat").read_text()
            ppid = int(stat[stat.rindex(")") + 2:].split()[1])  # after "(comm) state"
            if ppid == pid:
                out.append(int(entry.name))
    return out


def descendants(pid: int) -> list[int]:
    """Every process below ``pid``, breadth first."""
    found, todo = [], [pid]
    while todo:
        kids = _children(todo.pop(0))
        found += kids
        todo += kids
    return found


def rss_mb(pid: int) -> float | None:
    """Resident set size of ``pid`` in MB (``VmRSS``), None when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        return None
    return None


def process_name(pid: int) -> str | None:
    """The node a process runs: ``python -m <module>`` or a console script (None: not ours)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return None
    if "-m" in argv[:-1]:
        module = argv[argv.index("-m") + 1]
        return NODES.get(module, NODES.get(module.split(".")[0]))
    scripts = [Path(a).name for a in argv[:2]]
    return next((NODES[s] for s in scripts if s in NODES), None)


def sample_tree(root: int) -> dict[str, float]:
    """RSS (MB) of the launcher ``root`` and of each named node below it."""
    out: dict[str, float] = {}
    mb = rss_mb(root)
    if mb is not None:
        out[LAUNCHER] = mb
    for pid in descendants(root):
        name = process_name(pid)
        mb = rss_mb(pid)
        if name is not None and mb is not None:
            out[name] = out.get(name, 0.0) + mb  # a node's helper processes count with it
    return out


# ------------------------------------------------------------------------------ the run
@dataclass
class Watch:
    """What the soak sees of the running graph."""

    t0: float = field(default_factory=time.monotonic)
    tasks: list[dict[str, Any]] = field(default_factory=list)
    samples: list[dict[str, Any]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def sample(self, root: int, task: int | None = None, outcome: str | None = None) -> None:
        rss = sample_tree(root)
        rec = {"t_s": round(time.monotonic() - self.t0, 2), "rss_mb": rss}
        with self.lock:
            self.samples.append(rec)
            if task is not None:
                self.tasks.append({"task": task, "outcome": outcome, **rec})


def _follow(proc: subprocess.Popen[str], watch: Watch, echo: Any) -> None:
    """Read the graph's stdout: echo it, sample memory at every finished task."""
    assert proc.stdout is not None
    for line in proc.stdout:
        echo.write(line)
        echo.flush()
        m = TASK_LINE.match(line.strip())
        if m:
            watch.sample(proc.pid, int(m.group(1)), m.group(3))


def graph_command(args: Any, run_dir: Path) -> list[str]:
    """The ``peel graph`` invocation of the soak (public CLI only)."""
    cmd = [sys.executable, "-m", "peel_bringup.cli", "graph", "--plant", args.plant, "--tasks",
           str(args.tasks), "--out", str(run_dir / "graph"), "--seed", str(args.seed)]
    return cmd + (["--params", str(args.params)] if args.params else [])


def run_soak(args: Any, run_dir: Path) -> tuple[int, Watch, bool]:
    """Run the graph and watch it; returns (graph exit status, watch, interrupted)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    watch = Watch()
    with open(run_dir / "graph.stderr.log", "wb") as err:
        proc = subprocess.Popen(graph_command(args, run_dir), stdout=subprocess.PIPE,
                                stderr=err, text=True, env=env)
    reader = threading.Thread(target=_follow, args=(proc, watch, sys.stderr), daemon=True)
    reader.start()
    interrupted = False
    try:
        while proc.poll() is None:
            watch.sample(proc.pid)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=args.interval)
    except KeyboardInterrupt:
        interrupted = True
        proc.send_signal(signal.SIGINT)  # the graph stops its nodes in order
        proc.wait()
    reader.join(timeout=10)
    return proc.returncode, watch, interrupted


# ------------------------------------------------------------------------------ analysis
def memory_summary(tasks: list[dict[str, Any]], warmup: int, max_growth_mb: float,
                   ) -> dict[str, dict[str, Any]]:
    """Per process: RSS at the first, warm-up and last task, max, growth and slope after the
    warm-up (MB per task, least squares), whether it is flat, and the verdict (module
    docstring)."""
    names = sorted({n for t in tasks for n in t["rss_mb"]})
    last_task = max((t["task"] for t in tasks), default=0)
    out: dict[str, dict[str, Any]] = {}
    for name in names:
        pts = [(t["task"], t["rss_mb"][name]) for t in tasks if name in t["rss_mb"]]
        k = np.array([p[0] for p in pts], dtype=float)
        mb = np.array([p[1] for p in pts])
        out[name] = _node_memory(k, mb, warmup, max_growth_mb, enough=last_task > warmup)
    return out


def _node_memory(k: np.ndarray, mb: np.ndarray, warmup: int, max_growth_mb: float,
                 enough: bool) -> dict[str, Any]:
    """One process's memory record from its per-task samples (task indices ``k``, MB ``mb``);
    ``enough``: the run itself reached two tasks from the warm-up on."""
    after = k >= warmup
    rec: dict[str, Any] = {"rss_mb_first": round(float(mb[0]), 1),
                           "rss_mb_last": round(float(mb[-1]), 1),
                           "rss_mb_max": round(float(mb.max()), 1),
                           "rss_mb_at_warmup": None, "growth_after_warmup_mb": None,
                           "slope_mb_per_task": None, "flat": None}
    if not enough:
        return {**rec, "verdict": "too_few_tasks"}
    if after.sum() < 2:
        return {**rec, "verdict": "no_sample_after_warmup"}
    base = float(mb[after][0])
    rec["rss_mb_at_warmup"] = round(base, 1)
    rec["growth_after_warmup_mb"] = round(float(mb[-1]) - base, 1)
    rec["slope_mb_per_task"] = round(float(np.polyfit(k[after], mb[after], 1)[0]), 3)
    rec["flat"] = bool(float(mb[after].max()) - base <= max_growth_mb)
    return {**rec, "verdict": "flat" if rec["flat"] else "grew"}


def build_report(args: Any, status: int, watch: Watch, summary: dict[str, Any] | None,
                 wall_s: float) -> dict[str, Any]:
    """The soak's JSON report."""
    results = (summary or {}).get("results") or [{"task": t["task"], "outcome": t["outcome"]}
                                                 for t in watch.tasks]
    outcomes: dict[str, int] = {}
    for r in results:
        outcomes[r["outcome"]] = outcomes.get(r["outcome"], 0) + 1
    nodes = memory_summary(watch.tasks, args.warmup, args.max_growth_mb)
    flat = [v["flat"] for v in nodes.values()]
    return {
        "command": "peel soak " + " ".join(args.argv),
        "tasks": args.tasks, "tasks_finished": len(results), "plant": args.plant,
        "seed": args.seed, "params": str(args.params) if args.params else None,
        "graph_exit_status": status, "wall_s": round(wall_s, 1),
        "outcomes": outcomes, "safety_stops": outcomes.get("safety_stop", 0),
        "model_versions": (summary or {}).get("model_versions"),
        "dead_nodes": (summary or {}).get("dead_nodes"),
        "failed_updates": (summary or {}).get("failed_updates"),
        "warmup_tasks": args.warmup, "max_growth_mb": args.max_growth_mb,
        "memory_flat": None if any(f is None for f in flat) or not flat else all(flat),
        "nodes": nodes,
        "per_task": [{"task": t["task"], "outcome": t["outcome"], "rss_mb": t["rss_mb"]}
                     for t in watch.tasks],
        "samples": watch.samples,
        "results": results,
    }


def _markdown(rep: dict[str, Any]) -> str:
    lines = [
        "# peel soak", "",
        f"{rep['tasks_finished']} of {rep['tasks']} consecutive peels on the {rep['plant']} "
        f"through the node graph with online learning (seed {rep['seed']}), "
        f"{rep['wall_s']:.0f} s wall time. Command: `{rep['command']}`.", "",
        f"Outcomes: {', '.join(f'{k} {v}' for k, v in sorted(rep['outcomes'].items())) or '-'}; "
        f"**safety stops: {rep['safety_stops']}**; graph exit status "
        f"{rep['graph_exit_status']}; model versions "
        f"{rep['model_versions'][0] if rep['model_versions'] else '-'} .. "
        f"{rep['model_versions'][-1] if rep['model_versions'] else '-'}; failed model updates "
        f"after tasks: {', '.join(map(str, rep['failed_updates'] or [])) or 'none'}.", "",
        f"Memory (VmRSS, MB) per process; flat = grew by at most {rep['max_growth_mb']:g} MB "
        f"after task {rep['warmup_tasks']}:", "",
        "| process | task 1 | warm-up | last | max | growth after warm-up | slope MB/task | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, v in rep["nodes"].items():
        cells = [v["rss_mb_first"], v["rss_mb_at_warmup"], v["rss_mb_last"], v["rss_mb_max"],
                 v["growth_after_warmup_mb"], v["slope_mb_per_task"], v["verdict"]]
        lines.append(f"| {name} | " + " | ".join("-" if c is None else str(c) for c in cells)
                     + " |")
    lines += ["", "![RSS per process over tasks](soak_rss.png)", "",
              "Per-task RSS and the time series: `soak.json`; the graph's run: `graph/`.", ""]
    return "\n".join(lines)


def _plot(rep: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for name in rep["nodes"]:
        pts = [(t["task"], t["rss_mb"][name]) for t in rep["per_task"] if name in t["rss_mb"]]
        if pts:
            ax.plot(*zip(*pts, strict=True), marker=".", label=name)
    ax.axvline(rep["warmup_tasks"], color="gray", ls="--", lw=0.8, label="end of warm-up")
    ax.set_xlabel("task")
    ax.set_ylabel("VmRSS [MB]")
    ax.set_title(f"peel soak: {rep['tasks_finished']} peels on the {rep['plant']}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100))
    plt.close(fig)


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="peel soak", description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", type=positive_int, default=100, help="consecutive peels (100)")
    p.add_argument("--plant", choices=("sim", "plant"), default="plant",
                   help="where the peels run (default: the plant)")
    p.add_argument("--out", type=Path, default=None, help="run folder (default runs/soak/<time>)")
    p.add_argument("--force", action="store_true", help="replace an earlier run in --out")
    p.add_argument("--params", type=Path, default=None, help="parameter override file (graph)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="seed of the task sequence")
    p.add_argument("--warmup", type=nonnegative_int, default=10,
                   help="tasks after which memory must stay flat (10)")
    p.add_argument("--max-growth-mb", type=float_arg(0.0), default=25.0,
                   help="largest RSS growth after the warm-up that counts as flat (25 MB)")
    p.add_argument("--interval", type=positive_float, default=5.0,
                   help="seconds between memory samples besides those at each task (5)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel soak``; returns the exit status."""
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if not Path("/proc/self/status").is_file():
        raise PeelError("peel soak reads process memory from /proc: Linux only")
    if args.params is not None:
        from peel_msgs_py.params import load_param_file

        load_param_file(args.params, "peel_bringup")  # missing / not UTF-8 / bad YAML: now
    out = OutputDir(args.out or Path("runs/soak") / time.strftime("%Y%m%d-%H%M%S"),
                    command="peel soak", force=args.force)
    with out as run_dir:
        t0 = time.monotonic()
        status, watch, interrupted = run_soak(args, run_dir)
        wall = time.monotonic() - t0
        summary_path = run_dir / "graph" / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None
        rep = build_report(args, status, watch, summary, wall)
        atomic_write_text(run_dir / "soak.json", json.dumps(rep, indent=1) + "\n")
        atomic_write_text(run_dir / "soak.md", _markdown(rep))
        if rep["per_task"]:
            _plot(rep, run_dir / "soak_rss.png")
    brief = {k: rep[k] for k in ("tasks", "tasks_finished", "outcomes", "safety_stops",
                                 "memory_flat", "graph_exit_status", "wall_s")}
    brief["nodes"] = {n: {k: v[k] for k in ("rss_mb_first", "rss_mb_at_warmup", "rss_mb_last",
                                            "growth_after_warmup_mb", "flat", "verdict")}
                      for n, v in rep["nodes"].items()}
    brief["report"] = str(run_dir / "soak.md")
    print(json.dumps(brief, indent=1))
    for name, v in rep["nodes"].items():
        if v["flat"] is None:
            print(f"warning: memory of {name} not judged: {v['verdict']}", file=sys.stderr)
    if interrupted:
        return 130
    if status != 0:
        return status
    ok = (rep["tasks_finished"] == args.tasks and rep["safety_stops"] == 0
          and rep["memory_flat"] is not False)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(run_main("peel soak", main))
