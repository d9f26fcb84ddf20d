"""The ``main`` every peel node shares, in the shape of ros2/examples::

    def main(args=None):
        return run_node(NODE_NAME, PlannerNode, args)

* Parameter overrides are checked by name before ROS starts
  (:func:`peel_msgs_py.params.ros_args_overrides`: unknown sections and names refused).
* ``rclpy.init`` with the topics of the table relative to the node's namespace
  (:func:`peel_msgs_py.topics.namespace_remaps`: ``-r __ns:=/cell_a`` moves a whole cell);
  the node is built (parameters declared with descriptors; a refused value
  raises :class:`~peel_msgs_py.errors.ParameterError`) and spun until it says it is done
  (``node.done``) or a signal arrives.
* Bad input of any kind prints ``<node>: error: <message>`` (one line) and exits 2 (a managed
  node's failed configure with the status its error names,
  :class:`~peel_msgs_py.lifecycle.ConfigureError`).
* SIGINT or SIGTERM stop the node cleanly with status 0 and no traceback, whenever they come
  (while the node is built, spinning or torn down): rclpy's signal handler shuts the context
  down and wakes the executor, and the Python-level handler it chains to only notes the signal
  (no ``KeyboardInterrupt`` raised at some arbitrary line); an error that follows from the
  shutdown (an entity created on a closed context) ends the node quietly too; a second signal
  changes nothing.
* While it spins, the node looks every :data:`TWIN_CHECK_S` for a second node of its own name
  on the ROS domain (another graph, or the same node started twice by hand) and warns once,
  naming the domain: two such nodes answer each other's topics and services.
* A managed node shut down after a failed configure ends as if it had raised that error
  (:meth:`~peel_msgs_py.ros.lifecycle.ManagedNode.exit_error`).
* Run as a program (``args`` None), the process then ends at once (:func:`exit_now`): the node
  and the context are closed, files are written atomically, and the interpreter's own teardown
  (torch's thread pools) took 1-4 s per node on a loaded 2-core machine.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from .. import held_signals
from ..errors import PeelError
from ..params import ros_args_overrides
from ..topics import namespace_remaps

#: How often (s) the spin loop looks at ``node.done``.
POLL_S = 0.2
#: How often (s) a spinning node looks for a second node of its name.
TWIN_CHECK_S = 2.0


class TwinWatch:
    """Warns once when a second node of ``node``'s name and namespace appears on the domain."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.next_s = time.monotonic() + TWIN_CHECK_S
        self.warned = False

    def check(self) -> None:
        now = time.monotonic()
        if self.warned or now < self.next_s or not self.node.context.ok():
            return
        self.next_s = now + TWIN_CHECK_S
        own = (self.node.get_name(), self.node.get_namespace())
        twins = sum(1 for pair in self.node.get_node_names_and_namespaces() if pair == own)
        if twins > 1:
            self.warned = True
            domain = os.environ.get("ROS_DOMAIN_ID") or "0"
            self.node.get_logger().warn(
                f"a second node named {self.node.get_fully_qualified_name()} is on ROS domain "
                f"{domain}: two graphs on one domain mix their data; stop one, or give it a "
                f"domain of its own (ROS_DOMAIN_ID)")


def spin_until_done(node: Node) -> int:
    """Spin ``node`` until ``node.done`` (if it has one) or shutdown; its ``exit_status``."""
    if not rclpy.ok():  # a signal during the node's construction: nothing to spin
        return 0
    try:
        executor = SingleThreadedExecutor()
    except Exception:
        if rclpy.ok():
            raise
        return 0  # a signal shut the context down between the check above and here
    executor.add_node(node)
    twins = TwinWatch(node)
    try:
        while rclpy.ok() and not getattr(node, "done", False):
            executor.spin_once(timeout_sec=POLL_S)
            twins.check()
    finally:
        executor.remove_node(node)
        executor.shutdown(timeout_sec=1.0)
    return int(getattr(node, "exit_status", 0) or 0)


class _Signals:
    """Python-level SIGINT/SIGTERM handler under rclpy's: notes the signal, raises nothing."""

    def __init__(self) -> None:
        self.received: int | None = None
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self.note)
        self._unraisable = sys.unraisablehook
        sys.unraisablehook = self.unraisable

    def note(self, signum: int, frame: object) -> None:
        self.received = signum

    def unraisable(self, info: object) -> None:
        """After a signal, rclpy objects half-built on the closed context complain from their
        ``__del__``; that is the shutdown we asked for, not an error worth a traceback."""
        if self.received is None:
            self._unraisable(info)  # type: ignore[arg-type]


def run_node(name: str, make: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Run one node process; returns its exit status (module docstring)."""
    argv = list(sys.argv if args is None else args)
    node: Node | None = None
    status, started = 0, False
    signals = _Signals()  # before rclpy.init: rclpy's handler chains to this one
    held_signals.release()  # a signal held since the process started (launcher) arrives now
    try:
        ros_args_overrides(argv, name)
        rclpy.init(args=[*argv, *namespace_remaps()])  # topics move with the namespace
        started = True
        if signals.received is None:  # else stopped before ROS started: nothing to build
            node = make()
            status = spin_until_done(node)
            failure = getattr(node, "exit_error", lambda: None)()
            if failure is not None:  # a managed node shut down after its configure failed
                raise failure
    except PeelError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr, flush=True)
        status = getattr(exc, "exit_status", 2)  # a failed configure may say 1 (lifecycle)
    except (KeyboardInterrupt, ExternalShutdownException):
        status = 0
    except Exception:
        if signals.received is None and (not started or rclpy.ok()):
            raise
        status = 0  # a consequence of the shutdown a signal asked for (its Python-level
        #             handler may not have run yet when rclpy's had shut the context down)
    finally:
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
