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
import time
from typing import Any

from peel_msgs_py import discovery
from peel_msgs_py.cliargs import ArgumentParser, positive_float, run_main
from peel_msgs_py.lifecycle import FINALIZED, TRANSITIONS
from peel_msgs_py.params import load_node_params

from .lifecycle import Lifecycle, Sequence, absolute, bring_up, transitions

NODE_NAME = "peel_lifecycle"


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


def spin_until(node: Any, seq: Sequence) -> None:
    """Spin ``node`` until ``seq`` is done."""
    while not seq.done:
        _spin(node, 0.05)
        seq.step()


def states(lc: Lifecycle, nodes: list[str], timeout_s: float) -> dict[str, str]:
    """Each node's state label by its full name (``unknown``: no answer within ``timeout_s``)."""
    futures: dict[str, Any] = {}
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for n in nodes:
            if n not in futures and lc.ready(n):
                futures[n] = lc.state(n)
        if len(futures) == len(nodes) and all(f.done() for f in futures.values()):
            break
        _spin(lc.node, 0.05)
    out = {}
    for n in nodes:
        f = futures.get(n)
        result = f.result() if f is not None and f.done() else None
        out[absolute(n)] = result.current_state.label if result is not None else "unknown"
    return out


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel lifecycle``; prints JSON, returns the exit status."""
    import rclpy
    from rclpy.utilities import remove_ros_args

    full = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(remove_ros_args(["peel", *full])[1:])
    timeout_s = args.timeout or load_node_params("peel_bringup")["graph.lifecycle_timeout_s"]
    discovery.confine()
    rclpy.init(args=["peel", *full])
    node = rclpy.create_node(NODE_NAME)
    lc = Lifecycle(node)
    try:
        report: dict[str, Any] = {"action": args.action}
        if args.action != "get":
            seq = (bring_up(lc, args.nodes, timeout_s) if args.action == "up"
                   else transitions(lc, args.transition, args.nodes, timeout_s))
            spin_until(node, seq)
            report["steps"] = [{"node": s.target, "transition": s.transition,
                                "success": bool(s.success)} for s in seq.results]
            report["error"] = seq.error
            gone = [s.target for s in seq.results if s.transition == "shutdown" and s.success]
        else:
            gone = []
        report["nodes"] = {**states(lc, [n for n in args.nodes if n not in gone], timeout_s),
                           **{absolute(n): FINALIZED for n in gone}}  # their processes end
    finally:
        lc.close()
        node.destroy_node()
        rclpy.try_shutdown()
    print(json.dumps(report, indent=2), flush=True)
    return 1 if report.get("error") or "unknown" in report["nodes"].values() else 0


def _spin(node: Any, timeout_s: float) -> None:
    import rclpy

    rclpy.spin_once(node, timeout_sec=timeout_s)


if __name__ == "__main__":
    sys.exit(run_main("peel lifecycle", main))
