"""The ``main`` every peel node shares, in the shape of ros2/examples::

    def main(args=None):
        return run_node(NODE_NAME, PlannerNode, args)

* Parameter overrides are checked by name before ROS starts
  (:func:`peel_msgs_py.params.ros_args_overrides`: unknown sections and names refused).
* ``rclpy.init``; the node is built (parameters declared with descriptors; a refused value
  raises :class:`~peel_msgs_py.errors.ParameterError`) and spun until it says it is done
  (``node.done``) or a signal arrives.
* Bad input of any kind prints ``<node>: error: <message>`` (one line) and exits 2.
* SIGINT or SIGTERM stop the node cleanly with status 0: rclpy's signal handler shuts the
  context down, ``spin`` returns (or raises ``KeyboardInterrupt`` /
  ``ExternalShutdownException``), and from then on further signals are ignored, so the teardown
  (``destroy_node``) is never interrupted and no traceback reaches the log.
* Run as a program (``args`` None), the process then ends at once (:func:`exit_now`): the node
  and the context are closed, files are written atomically, and the interpreter's own teardown
  (torch's thread pools) took 1-4 s per node on a loaded 2-core machine.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from ..errors import PeelError
from ..params import ros_args_overrides

#: How often (s) the spin loop looks at ``node.done``.
POLL_S = 0.2


def spin_until_done(node: Node) -> int:
    """Spin ``node`` until ``node.done`` (if it has one) or shutdown; its ``exit_status``."""
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while rclpy.ok() and not getattr(node, "done", False):
            executor.spin_once(timeout_sec=POLL_S)
    finally:
        executor.remove_node(node)
        executor.shutdown(timeout_sec=1.0)
    return int(getattr(node, "exit_status", 0) or 0)


def _ignore_signals() -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def run_node(name: str, make: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Run one node process; returns its exit status (module docstring)."""
    argv = list(sys.argv if args is None else args)
    node: Node | None = None
    status = 0
    try:
        ros_args_overrides(argv, name)
        rclpy.init(args=argv)
        node = make()
        status = spin_until_done(node)
    except PeelError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr, flush=True)
        status = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        status = 0
    finally:
        _ignore_signals()  # one signal stops the node; the teardown runs to its end
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if args is None:
        exit_now(status)
    return status


def exit_now(status: int) -> None:
    """Flush stdout and stderr, then end the process with ``status`` (no interpreter teardown)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(status)
