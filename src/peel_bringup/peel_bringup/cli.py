"""``peel``: the one command-line tool, with subcommands.

Each subcommand lives in the package that owns the capability and is imported lazily, so
``peel --help`` is fast and a missing optional dependency only affects its own subcommand. Every
subcommand is a ``main(argv: list[str]) -> int`` function. Bad input raises
:class:`~peel_msgs_py.errors.PeelError` (argument parsers are
:class:`peel_msgs_py.cliargs.ArgumentParser`, whose usage errors are PeelErrors too); the one
top-level handler, :func:`peel_msgs_py.cliargs.run_main`, prints it as one line and exits 2.
"""

from __future__ import annotations

import importlib
import os
import sys

from peel_msgs_py.cliargs import run_main

#: name -> ("module:function", one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("peel_bringup.demo:main", "the main job: a few tasks through the node graph on the plant"),
    "dataset": ("peel_sim_node.dataset_cli:main", "generate a simulator or plant dataset (3.2)"),
    "train": ("model_learner_node.train_cli:main", "train the forward model offline (3.3)"),
    "figures": ("model_learner_node.figures_cli:main", "Fig. 9 and Fig. 10: loss ablation and model comparison"),
    "bench": ("peel_experiments.bench:main", "benchmarks printing JSON: sim, model, planner, ros, nachi, nachi-graph"),
    "experiment": ("peel_experiments.experiment_cli:main",
                   "20 consecutive peels per method (4.4), the sweep (4.5), grid, fleet"),
    "fast-report": ("peel_experiments.fast_report:main",
                    "what the fast step inside the peel bought, from an experiment's results"),
    "graph": ("peel_bringup.graph:main", "run the ROS 2 node graph as separate processes"),
    "lifecycle": ("peel_bringup.lifecycle_cli:main",
                  "drive managed nodes: get, set a transition, up (configure + activate)"),
    "live": ("peel_bringup.live_node:main",
             "serve a running graph's live view on a Foxglove WebSocket (127.0.0.1)"),
    "fleet": ("peel_bringup.fleet:main", "K peeling cells under their own namespaces and one learner"),
    "fleet-report": ("peel_bringup.fleet_report:main", "where the wall time of peel fleet runs goes (JSON)"),
    "record": ("peel_bag.recorder_cli:main", "record the /peel topics and /clock to an MCAP bag"),
    "nachi-emulator": ("peel_nachi_emulator.emulator_cli:main",
                       "emulate the Nachi controller (NACHI-PEEL 1 over TCP) over the plant"),
    "soak": ("peel_experiments.soak:main", "many consecutive peels through the graph: safety stops, "
             "every node's memory"),
    "residual": ("peel_residual.cli:main",
                 "trace the model's residual on bags to physical effects, add them, report"),
}


def _usage() -> str:
    width = max(len(n) for n in SUBCOMMANDS)
    lines = ["usage: peel <command> [options]", "", "commands:"]
    for name, (_, text) in SUBCOMMANDS.items():
        lines.append(f"  {name:<{width}}  {text}")
    lines += ["", "Run 'peel <command> --help' for the options of one command."]
    return "\n".join(lines)


#: Commands whose process ends at once after its work (files closed, children stopped): the
#: interpreter's teardown of torch took 1-1.5 s after every demo on a loaded 2-core machine.
FAST_EXIT = frozenset({"demo", "graph", "fleet"})


def main(argv: list[str] | None = None) -> int:
    """Dispatch ``peel <command> ...``; returns the process exit status."""
    if argv is None and sys.argv[1:2] and sys.argv[1] in FAST_EXIT:
        status = main(sys.argv[1:])
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        os._exit(status)
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"peel: error: unknown command '{name}'\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, func_name = SUBCOMMANDS[name][0].split(":")

    def run(args: list[str]) -> int:
        return getattr(importlib.import_module(module_name), func_name)(args)

    return run_main(f"peel {name}", run, rest)


if __name__ == "__main__":
    sys.exit(main())
