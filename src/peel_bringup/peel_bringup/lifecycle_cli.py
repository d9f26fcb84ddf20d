"""``peel lifecycle``: drive managed nodes by hand, or from the launch file (docs/graph.md
"Lifecycle"), through their standard ``change_state`` / ``get_state`` services::

    peel lifecycle get NODE [NODE ...]              # {"nodes": {"/peel_planner_node": "inactive"}}
    peel lifecycle set TRANSITION NODE [NODE ...]   # configure, activate, deactivate, cleanup,
                                                    # shutdown: on every NODE at once
    peel lifecycle up NODE [NODE ...]               # configure all, then activate in order

Prints one JSON object: the transitions asked (``steps``: node, transition, success) and every
node's state after them (``nodes``; ``finalized`` after a shutdown, whose process then ends);
``error`` when one was refused or timed out. Exit status 0,
1 when a transition failed or a node did not answer within ``--timeout`` (wall s, default
``graph.lifecycle_timeout_s``). ROS arguments (``--ros-args ...``, as ``ros2 launch`` appends
them) are passed to rclpy; discovery is confined to this machine as ``peel graph``'s.
"""

from __future__ import annotations

import json
import sys

from peel_msgs_py import discovery
from peel_msgs_py.cliargs import ArgumentParser, positive_float, run_main
from peel_msgs_py.lifecycle import TRANSITIONS
from peel_msgs_py.params import load_node_params


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="peel lifecycle", description=__doc__.split("\n\n")[0])
    p.add_argument("--timeout", type=positive_float, default=None, metavar="S",
                   help="wall s for each node's services and answers (default "
                        "graph.lifecycle_timeout_s of config/peel_bringup.yaml)")
    sub = p.add_subparsers(dest="action", required=True)
    sub.add_parser("get", help="each node's state").add_argument("nodes", nargs="+")
    s = sub.add_parser("set", help="one transition on every node")
    s.add_argument("transition", choices=list(TRANSITIONS))
    s.add_argument("nodes", nargs="+")
    sub.add_parser("up", help="configure all, then activate in order").add_argument(
        "nodes", nargs="+")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel lifecycle``; prints JSON, returns the exit status."""
    from .lifecycle_node import drive, remove_ros_args

    full = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(remove_ros_args(full))
    timeout_s = args.timeout or load_node_params("peel_bringup")["graph.lifecycle_timeout_s"]
    discovery.confine()
    report = drive(args.action, getattr(args, "transition", None), args.nodes, timeout_s, full)
    print(json.dumps(report, indent=2), flush=True)
    return 1 if report.get("error") or "unknown" in report["nodes"].values() else 0


if __name__ == "__main__":
    sys.exit(run_main("peel lifecycle", main))
