"""The shared ``main`` of every peel node: init, run, clean shutdown, one-line errors.

Each node's console entry point is ``run_node(NAME, make, spin, args)``: ``make(argv)`` builds the
node object (anything with ``close()``), ``spin(node)`` runs it and may return an exit status.
Bad input (:class:`~peel_msgs_py.errors.PeelError`) prints ``<name>: error: <message>`` and
exits 2; SIGINT (``KeyboardInterrupt``) and SIGTERM (``ExternalShutdownException``) are a clean
stop with status 0; the node is closed and the context shut down in every case.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any, Protocol

from ..errors import PeelError


class Closeable(Protocol):
    def close(self) -> None: ...


def run_node(name: str, make: Callable[[list[str]], Closeable],
             spin: Callable[[Any], int | None], args: list[str] | None = None) -> int:
    """Run one node process; returns its exit status (see the module docstring)."""
    from . import ExternalShutdownException, rclpy

    argv = list(sys.argv if args is None else args)
    node: Closeable | None = None
    status = 0
    try:
        rclpy.init(args=argv)
        node = make(argv)
        status = int(spin(node) or 0)
    except PeelError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        status = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        status = 0
    finally:
        if node is not None:
            node.close()
        if rclpy.ok():
            rclpy.shutdown()
    return status
