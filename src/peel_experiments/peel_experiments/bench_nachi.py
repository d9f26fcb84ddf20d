"""``peel bench nachi-graph``: the simulator bridge and the Nachi bridge side by side, same seed.

    peel bench nachi-graph [--tasks 5] [--seed 7] [--plant plant] [--speed 1.0]
                           [--params FILE] [--out DIR]

Runs ``peel graph --plant PLANT --tasks K --seed S`` (the simulator bridge, lockstep), then
``peel nachi-emulator --plant PLANT --seed S --speed X`` with ``peel graph --plant nachi`` against
it (the Nachi bridge over TCP; the emulator peels the same substrates, task ``k`` from
``(S, k)``), one after the other, each graph in ``OUT/sim`` and ``OUT/nachi``. Prints one JSON
object: per task the outcome, J (Eq. 3), T_cpl, the force sums and the model version of each
run, the mean J of each, the model versions each planner announced, the wall time of each run
and the machine's load average before and after (docs/nachi.md).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from peel_msgs_py import discovery
from peel_msgs_py.cliargs import ArgumentParser, float_arg, nonnegative_int, positive_int
from peel_msgs_py.errors import PeelError
from peel_msgs_py.machine import run_context

#: The fields of each task of ``summary.json`` that the comparison keeps.
FIELDS = ("outcome", "J", "t_cpl_s", "sum_fx_n", "sum_fz_n", "model_version")


def _peel(*args: str) -> list[str]:
    return [sys.executable, "-m", "peel_bringup.cli", *args]


def run_graph(args: list[str], out: Path, timeout_s: float) -> dict[str, Any]:
    """One ``peel graph`` run; its ``summary.json`` with the wall time."""
    t0 = time.monotonic()
    res = subprocess.run(_peel("graph", *args, "--out", str(out)), capture_output=True,
                         text=True, timeout=timeout_s)
    wall = time.monotonic() - t0
    if res.returncode != 0 or not (out / "summary.json").is_file():
        raise PeelError(f"bench nachi-graph: peel graph {' '.join(args)} exited "
                        f"{res.returncode}: {res.stderr.strip()[-500:]}")
    summary = json.loads((out / "summary.json").read_text())
    summary["wall_s"] = round(wall, 1)
    return summary


def with_emulator(plant: str, seed: int, speed: float, run: Any) -> Any:
    """``run(port)`` while ``peel nachi-emulator`` serves on a free port."""
    emu = subprocess.Popen(_peel("nachi-emulator", "--port", "0", "--plant", plant, "--seed",
                                 str(seed), "--speed", repr(speed)),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert emu.stdout is not None
        first = emu.stdout.readline()  # "listening on 127.0.0.1:PORT (...)"
        if not first.startswith("listening on "):
            raise PeelError(f"bench nachi-graph: the emulator did not start: {first.strip()}")
        return run(first.split(":")[1].split()[0])
    finally:
        emu.terminate()
        emu.wait(timeout=30)


def _tasks(summary: dict[str, Any]) -> list[dict[str, Any]]:
    return [{k: r[k] for k in FIELDS} for r in summary["results"]]


def _mean_j(summary: dict[str, Any]) -> float:
    js = [r["J"] for r in summary["results"]]
    return round(sum(js) / len(js), 4) if js else float("nan")


def measure(tasks: int, seed: int, plant: str, speed: float, params: str | None,
            out: Path) -> dict[str, Any]:
    common = ["--tasks", str(tasks), "--seed", str(seed)] + (["--params", params] if params else [])
    load_before = os.getloadavg()
    sim = run_graph(["--plant", plant, *common], out / "sim", 1800)
    nachi = with_emulator(plant, seed, speed, lambda port: run_graph(
        ["--plant", "nachi", "--nachi-host", "127.0.0.1", "--nachi-port", port, *common],
        out / "nachi", 1800))
    return {
        "benchmark": "nachi-graph", "plant": plant, "seed": seed, "tasks": tasks,
        "emulator_speed": speed, "params": params,
        "commands": [f"peel graph --plant {plant} {' '.join(common)}",
                     f"peel nachi-emulator --plant {plant} --seed {seed} --speed {speed:g} & "
                     f"peel graph --plant nachi --nachi-port PORT {' '.join(common)}"],
        "simulator_bridge": _tasks(sim), "nachi_bridge": _tasks(nachi),
        "mean_J": {"simulator_bridge": _mean_j(sim), "nachi_bridge": _mean_j(nachi)},
        "model_versions": {"simulator_bridge": sim["model_versions"],
                           "nachi_bridge": nachi["model_versions"]},
        "wall_s": {"simulator_bridge": sim["wall_s"], "nachi_bridge": nachi["wall_s"]},
        **run_context(load_before),
    }


def main(argv: list[str]) -> int:
    ap = ArgumentParser(prog="peel bench nachi-graph", description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=positive_int, default=5, help="tasks per run (default 5)")
    ap.add_argument("--seed", type=nonnegative_int, default=7,
                    help="task-sequence seed (default 7)")
    ap.add_argument("--plant", choices=("sim", "plant"), default="plant",
                    help="what both bridges peel on (default plant)")
    # the bridge's 300 ms stall rule needs the 100 ms samples faster than 1/3 of real time
    ap.add_argument("--speed", type=float_arg(0.34, 100.0), default=1.0,
                    help="emulator speed X (default 1: real time, as a robot)")
    ap.add_argument("--params", metavar="FILE", default=None,
                    help="parameter file for both graphs (as peel graph --params)")
    ap.add_argument("--out", metavar="DIR", default=None,
                    help="run directories (default runs/bench_nachi/<time>)")
    args = ap.parse_args(argv)
    out = Path(args.out or Path("runs/bench_nachi") / time.strftime("%Y%m%d-%H%M%S"))
    if (out / "sim").exists() or (out / "nachi").exists():
        raise PeelError(f"--out: {out} already holds a comparison")
    discovery.confine()  # the graphs and the emulator inherit it
    print(json.dumps(measure(args.tasks, args.seed, args.plant, args.speed, args.params, out),
                     indent=2))
    return 0
