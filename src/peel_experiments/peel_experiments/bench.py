"""``peel bench sim|model|planner|safety|ros|nachi|nachi-graph``: benchmarks are commands that print one JSON object.

Each target lives with the code it measures; this module only dispatches, so that
``peel bench --help`` lists them in one place.
"""

from __future__ import annotations

import importlib
import sys

from peel_msgs_py.errors import PeelError

TARGETS: dict[str, tuple[str, str]] = {
    "sim": ("peel_sim_node.bench:main", "simulator throughput against raw stepSimulation (docs/simulator.md)"),
    "model": ("model_learner_node.bench:main", "training samples/s and inference latency (docs/model.md)"),
    "planner": ("peel_experiments.bench_planner:main", "plan() latency and episode cost vs pytorch_mppi"),
    "safety": ("peel_experiments.bench_safety:main",
               "prewarnings and peak forces per plant level, guarded planner vs unguarded vs pytorch_mppi"),
    "ros": ("peel_msgs_py.ros.bench:main", "rclpy pub/sub and service round trips between two processes"),
    "nachi": ("peel_nachi_emulator.bench:main", "STOP delay of the Nachi bridge on a force spike"),
    "nachi-graph": ("peel_experiments.bench_nachi:main",
                    "cost per task, simulator bridge vs Nachi bridge on the emulator, same seed"),
}


def main(argv: list[str]) -> int:
    """Dispatch ``peel bench <target> [options]``."""
    if not argv or argv[0] in ("-h", "--help"):
        lines = ["usage: peel bench <target> [--json] [options]", "", "targets:"]
        lines += [f"  {name:<11} {text}" for name, (_, text) in TARGETS.items()]
        print("\n".join(lines))
        return 0 if argv else 2
    target, rest = argv[0], argv[1:]
    if target not in TARGETS:
        raise PeelError(f"unknown benchmark '{target}' (choose from {', '.join(TARGETS)})")
    module_name, func_name = TARGETS[target][0].split(":")
    return int(getattr(importlib.import_module(module_name), func_name)(rest) or 0)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
