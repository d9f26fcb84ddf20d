#!/usr/bin/env python3
"""What the cells see when the learner dies and comes back (docs/fleet.md).

Usage: ``.venv/bin/python scripts/learner_restart.py --cells K --tasks T --seed S --kill-after U
--outage SECONDS --out DIR [--params FILE] [--reference DIR]``

Runs ``peel fleet`` (K cells, T tasks each, seed S, run directory DIR), SIGKILLs its learner once
U updates were swapped in, waits SECONDS, and starts a learner again with the dead one's very
command line (read from ``/proc/<pid>/cmdline``: the same parameters, ``node.resume`` as
configured). Prints one JSON object: per cell the model each task started with, the wall time
at which its end was printed and the gap since the cell's task before (the peel and the wait
for the update); what the second learner logged (the resumed line, the tasks it dropped as
learned and the updates it wrote); whether each cell's announced versions only went up; the
model files written and, with ``--reference DIR`` (the run directory of the same ``peel fleet``
without the kill), whether each holds the same bytes as the file of that name there. The
fleet's exit status is 1 by design (its learner died).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from peel_msgs_py import discovery

ROOT = Path(__file__).resolve().parents[1]
PEEL = ROOT / ".venv" / "bin" / "peel"


def _args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cells", type=int, default=2)
    p.add_argument("--tasks", type=int, default=4)
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--kill-after", type=int, default=2, help="updates swapped in before the kill")
    p.add_argument("--outage", type=float, default=20.0, help="wall s without a learner")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--params", default=None, help="a parameter file for every node")
    p.add_argument("--reference", type=Path, default=None,
                   help="the run directory of the same fleet without the kill: compare models")
    return p.parse_args()


def _fleet_cmd(a: argparse.Namespace) -> list[str]:
    cmd = [str(PEEL), "fleet", "--cells", str(a.cells), "--tasks", str(a.tasks), "--seed",
           str(a.seed), "--out", str(a.out)]
    return cmd + (["--params", a.params] if a.params else [])


class Lines:
    """The fleet's stdout lines, read on a thread, with the wall time of each."""

    def __init__(self, proc: subprocess.Popen[str], t0: float) -> None:
        self.lines: list[tuple[float, str]] = []
        self.t0 = t0
        threading.Thread(target=self._read, args=(proc,), daemon=True).start()

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.lines.append((round(time.monotonic() - self.t0, 2), line.rstrip("\n")))

    def at(self, pattern: str) -> float | None:
        """The wall time of the first line matching ``pattern``."""
        return next((t for t, line in self.lines if re.search(pattern, line)), None)

    def count(self, pattern: str) -> int:
        return sum(1 for _, line in self.lines if re.search(pattern, line))

    def first(self, pattern: str) -> re.Match[str] | None:
        return next((m for _, line in self.lines if (m := re.search(pattern, line))), None)


def _wait(cond: Any, what: str, proc: subprocess.Popen[str], timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        if proc.poll() is not None or time.monotonic() > end:
            raise SystemExit(f"learner_restart.py: error: {what} did not happen")
        time.sleep(0.1)


def _second_learner(log: str) -> dict[str, Any]:
    resumed = re.search(r"resumed from .*?\)", log)
    return {"resumed": resumed.group(0) if resumed else None,
            "dropped_tasks": [int(k) for k in re.findall(r"task (\d+): learned before", log)],
            "updates_written": re.findall(r"wrote (model_v\d+\.safetensors)", log)}


def _cells(summary: dict[str, Any], out: Lines, tasks: int) -> dict[str, Any]:
    """Per cell: each task's starting model and the wall time its end was printed (this
    script's clock), the gap since the task before, and the versions its planner announced."""
    cells = {}
    for cell, c in summary["cells"].items():
        rows, prev = [], 0.0
        for r in c["results"]:
            at = out.at(rf"^{re.escape(cell)} task {r['task']}/{tasks}:") or math.nan
            rows.append({"task": r["task"], "model_version": r["model_version"],
                         "model_sha256": r["model_sha256"], "ended_wall_s": at,
                         "gap_s": round(at - prev, 2), "update": (r["update"] or {}).get("status")})
            prev = at
        versions = [m["version"] for m in c["models"]]
        cells[cell] = {"tasks": rows, "versions_announced": versions,
                       "versions_only_go_up": versions == sorted(set(versions)),
                       "tasks_done": len(rows)}
    return cells


def _models(run_dir: Path, reference: Path | None) -> dict[str, Any]:
    """The model files written, each one's SHA-256, and whether the run without the kill
    wrote the same bytes under the same name."""
    def sha(p: Path) -> str:
        return hashlib.sha256(p.read_bytes()).hexdigest()

    files = sorted((run_dir / "models").glob("model_v*.safetensors"))
    out: dict[str, Any] = {"files": [p.name for p in files]}
    if reference is not None:
        ref = {p.name: sha(p) for p in (reference / "models").glob("model_v*.safetensors")}
        out["same_bytes_as_reference"] = {p.name: ref.get(p.name) == sha(p) for p in files}
        out["reference_files"] = len(ref)
    return out


def main() -> int:
    a = _args()
    claim = discovery.claim_domain(os.getpid())
    env = dict(os.environ, ROS_DOMAIN_ID=str(claim.domain), PYTHONUNBUFFERED="1")
    discovery.confine(env)
    t0 = time.monotonic()
    fleet = subprocess.Popen(_fleet_cmd(a), env=env, stdout=subprocess.PIPE, text=True)
    out = Lines(fleet, t0)
    _wait(lambda: out.first(r"started model_learner_node \(pid (\d+)\)"), "the learner's start",
          fleet, 120)
    pid = int(out.first(r"started model_learner_node \(pid (\d+)\)").group(1))
    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")[:-1]
    _wait(lambda: out.count(r"update \d+/\d+: swapped in") >= a.kill_after,
          f"{a.kill_after} swaps", fleet, 1800)
    os.kill(pid, signal.SIGKILL)
    killed_at = time.monotonic() - t0
    time.sleep(a.outage)
    log_path = a.out / "logs" / "model_learner_node.restarted.log"
    with log_path.open("w") as log:
        second = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        back_at = time.monotonic() - t0
        rc = fleet.wait(timeout=3600)
        # the fleet ends with its cells (its learner is dead): let the second learner finish
        # its updates on the last tasks first
        last = re.compile(rf"task {a.tasks}: Algorithm 1 done")
        end = time.monotonic() + 300
        while len(last.findall(log_path.read_text())) < a.cells and time.monotonic() < end \
                and second.poll() is None:
            time.sleep(0.5)
        second.send_signal(signal.SIGINT)
        second.wait(timeout=60)
    summary = json.loads((a.out / "summary.json").read_text())
    result = {"cells": a.cells, "tasks": a.tasks, "seed": a.seed, "kill_after": a.kill_after,
              "outage_s": a.outage, "fleet_exit": rc, "killed_at_wall_s": round(killed_at, 2),
              "restarted_at_wall_s": round(back_at, 2),
              "second_learner": _second_learner(log_path.read_text()),
              "per_cell": _cells(summary, out, a.tasks), "models": _models(a.out, a.reference)}
    print(json.dumps(result, indent=2))
    claim.release()
    return 0


if __name__ == "__main__":
    sys.exit(main())
