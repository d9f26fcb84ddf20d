"""``peel bench nachi``: how fast the bridge answers a force over the 20 N prewarning with STOP.

Runs the bridge core against the emulator over loopback TCP (one process, two threads) with a
force spike (F_RX = 22 N) in the sample at t = 0.5 s of every task, and prints one JSON object:

* ``stop_delay_ms``: the bridge's own measure, from the ``recv`` that completed the sample's line
  to ``STOP`` handed to the kernel (:attr:`~.bridge.BridgeStats.stop_delays_s`);
* ``round_trip_ms``: the emulator's, from sending the spiked sample to reading ``STOP``;
* ``same_sample``: tasks in which the emulator had sent no later sample when STOP arrived.
"""

from __future__ import annotations

import json
import os
import threading

import numpy as np

from peel_msgs_py.cliargs import ArgumentParser, float_arg, positive_int
from peel_msgs_py.errors import PeelError
from peel_msgs_py.machine import run_context
from peel_nachi_bridge import protocol as p
from peel_nachi_bridge.bridge import NachiBridge
from peel_nachi_bridge.config import load_config
from peel_nachi_bridge.task import TaskResult

from .emulator import ControllerEmulator, EmulatorOptions
from .faults import Fault

SPIKE_T = 0.5


class _Planner:
    """Listener that commands 3 mm/s at every control instant and collects the results."""

    def __init__(self) -> None:
        self.bridge: NachiBridge | None = None
        self.results: list[TaskResult] = []
        self.ended = threading.Event()

    def on_sample(self, index: int, s: p.Sample) -> None:
        if round(s.t * 10) % 5 == 0 and self.bridge is not None:
            self.bridge.command(3.0, index)

    def on_task_end(self, result: TaskResult) -> None:
        self.results.append(result)
        self.ended.set()

    def on_log(self, level: str, text: str) -> None:
        pass


def _summary(values_s: list[float]) -> dict[str, float]:
    ms = np.asarray(values_s) * 1e3
    return {"median": round(float(np.median(ms)), 4), "p95": round(float(np.percentile(ms, 95)), 4),
            "max": round(float(ms.max()), 4)}


def measure(tasks: int, speed: float) -> dict[str, object]:
    load_before = os.getloadavg()
    faults = tuple(Fault("spike", t=SPIKE_T, task=k, f=22.0) for k in range(tasks))
    emu = ControllerEmulator(EmulatorOptions(port=0, speed=speed, faults=faults),
                             log=lambda text: None).start()
    planner = _Planner()
    cfg = load_config({"link.port": emu.port})
    bridge = NachiBridge(cfg.link, cfg.safety, planner)
    planner.bridge = bridge
    bridge.start()
    try:
        for k in range(tasks):
            planner.ended.clear()
            bridge.request_task(k)
            if not planner.ended.wait(60.0):
                raise PeelError(f"bench nachi: task {k} did not end within 60 s")
    finally:
        bridge.close()
        emu.close()
    stops = emu.of_kind("stop")
    same = sum(abs(e.data["sample_t"] - SPIKE_T) < 1e-9 for e in stops)
    return {
        "benchmark": "nachi", "tasks": tasks, "emulator_speed": speed,
        "outcomes": sorted({f"{r.outcome}/{r.reason}" for r in planner.results}),
        "stop_delay_ms": _summary(bridge.stats.stop_delays_s),
        "round_trip_ms": _summary([e.data["since_sample_s"] for e in stops]),
        "same_sample": f"{same}/{len(stops)}",
        **run_context(load_before),
    }


def main(argv: list[str]) -> int:
    ap = ArgumentParser(prog="peel bench nachi", description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=positive_int, default=20,
                    help="tasks, one spike each (default 20)")
    ap.add_argument("--speed", type=float_arg(0.0, 100.0, min_open=True), default=2.0,
                    help="emulator speed X (default 2)")
    args = ap.parse_args(argv)
    print(json.dumps(measure(args.tasks, args.speed), indent=2))
    return 0
