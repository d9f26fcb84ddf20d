"""``peel fleet-report RUN...``: where the wall time of ``peel fleet`` runs goes (docs/fleet.md).

For each run folder (``peel fleet --out RUN``), from its ``summary.json`` and the nodes' logs
(every rclpy log line carries its wall-clock stamp): per cell the wall s of each task (the
planner's ``task k starts`` to the bridge's ``task k: <outcome>``) and between tasks (the
lockstep wait for the cell's own update: Algorithm 1 of the tasks before it in the learner's
order, the swaps), the learner's Algorithm 1 times, and the wall s per peel from the first
task's start to the last task's end. Prints one JSON object, run folder name -> figures.
"""

from __future__ import annotations

import json
import re
import statistics
import sys
from pathlib import Path
from typing import Any

from peel_msgs_py.cliargs import ArgumentParser, run_main
from peel_msgs_py.errors import PeelError

_STAMP = r"\[(\d+\.\d+)\] \[[^\]]+\]: "
STARTS = r"task (\d+) starts"
ENDS = r"task (\d+): (?:done|timeout|safety_stop|aborted)"


def stamps(log: Path, pattern: str) -> dict[int, float]:
    """task k -> wall s of the first line of ``log`` matching ``pattern`` (group 1 = k)."""
    out: dict[int, float] = {}
    for line in log.read_text(errors="replace").splitlines():
        m = re.search(_STAMP + pattern, line)
        if m:
            out.setdefault(int(m.group(2)), float(m.group(1)))
    return out


def update_times(log: Path) -> list[float]:
    """Wall s of each run of Algorithm 1, as the learner logged them (its log file)."""
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return []
    return [float(x) for x in re.findall(r"Algorithm 1 done in ([0-9.]+) s", text)]


def _median(xs: list[float]) -> float | None:
    return round(statistics.median(xs), 2) if xs else None


def cell_times(logs: Path) -> dict[str, Any]:
    """One cell's task and between-task wall times from its planner's and bridge's logs."""
    start = stamps(logs / "peel_planner_node.log", STARTS)
    end = stamps(logs / "peel_sim_node.log", ENDS)
    ks = sorted(set(start) & set(end))
    return {"task_wall_s": [round(end[k] - start[k], 2) for k in ks],
            "between_tasks_s": [round(start[k + 1] - end[k], 2) for k in ks if k + 1 in start],
            "first_start": min((start[k] for k in ks), default=None),
            "last_end": max((end[k] for k in ks), default=None)}


def run_report(run: Path) -> dict[str, Any]:
    """The figures of one ``peel fleet`` run folder (module docstring)."""
    try:
        summary = json.loads((run / "summary.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PeelError(f"{run}: no readable summary.json of peel fleet ({exc})") from None
    cells = {c: cell_times(run / "logs" / c.strip("/")) for c in summary["cells"]}
    starts = [c["first_start"] for c in cells.values() if c["first_start"] is not None]
    ends = [c["last_end"] for c in cells.values() if c["last_end"] is not None]
    peels = sum(len(c["task_wall_s"]) for c in cells.values())
    span = max(ends) - min(starts) if starts and ends else None
    for c in cells.values():
        del c["first_start"], c["last_end"]
    updates = summary.get("learner_update_s", [])
    return {
        "cells": len(cells), "tasks_per_cell": summary["tasks"], "seed": summary["seed"],
        "status": summary["status"], "peels": peels,
        "task_wall_s_median": _median([x for c in cells.values() for x in c["task_wall_s"]]),
        "between_tasks_s_median": _median([x for c in cells.values()
                                           for x in c["between_tasks_s"]]),
        "learner_update_s_median": _median(updates), "learner_update_s": updates,
        "first_start_to_last_end_s": round(span, 1) if span is not None else None,
        "wall_s_per_peel": round(span / peels, 2) if span is not None and peels else None,
        "per_cell": cells,
    }


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel fleet-report``; prints the JSON."""
    p = ArgumentParser(prog="peel fleet-report", description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", metavar="RUN", help="peel fleet run folders (--out)")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    print(json.dumps({Path(r).name: run_report(Path(r)) for r in args.runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("peel fleet-report", main))
