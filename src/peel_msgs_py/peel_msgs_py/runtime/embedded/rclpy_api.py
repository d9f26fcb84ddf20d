"""The module-like ``rclpy`` of the embedded runtime: ``init``, ``spin``, ``shutdown`` ...

Used as ``from peel_msgs_py.runtime import rclpy``; the functions take the same arguments as
rclpy Jazzy's. ``spin``/``spin_once``/``spin_until_future_complete`` use a global
:class:`SingleThreadedExecutor` unless one is passed.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from .args import remove_ros_args
from .context import (
    Context,
    ExternalShutdownException,
    NotInitializedException,
    get_default_context,
    install_signal_handlers,
    uninstall_signal_handlers,
)
from .executor import SingleThreadedExecutor
from .services import Future

_global_executor: SingleThreadedExecutor | None = None


def init(
    *,
    args: Sequence[str] | None = None,
    context: Context | None = None,
    domain_id: int | None = None,
    signal_handler_options: Any = None,
) -> None:
    """Initialise the context from ``args`` (their ``--ros-args`` sections)."""
    ctx = context or get_default_context()
    ctx.init(args, domain_id=domain_id)
    if ctx is get_default_context():
        install_signal_handlers()


def ok(*, context: Context | None = None) -> bool:
    return (context or get_default_context()).ok()


def shutdown(*, context: Context | None = None, uninstall_handlers: bool | None = None) -> None:
    global _global_executor
    ctx = context or get_default_context()
    if _global_executor is not None and _global_executor.context is ctx:
        _global_executor.shutdown()
        _global_executor = None
    ctx.shutdown()
    if ctx is get_default_context():
        uninstall_signal_handlers()


def try_shutdown(*, context: Context | None = None, uninstall_handlers: bool | None = None) -> None:
    global _global_executor
    ctx = context or get_default_context()
    if _global_executor is not None and _global_executor.context is ctx:
        _global_executor.shutdown()
        _global_executor = None
    ctx.try_shutdown()
    if ctx is get_default_context():
        uninstall_signal_handlers()


def get_global_executor() -> SingleThreadedExecutor:
    global _global_executor
    if _global_executor is None or not _global_executor.context.ok():
        _global_executor = SingleThreadedExecutor()
    return _global_executor


def _executor_for(node: Any, executor: SingleThreadedExecutor | None) -> SingleThreadedExecutor:
    ex = executor or get_global_executor()
    if node is not None:
        ex.add_node(node)
    return ex


def spin(node: Any, executor: SingleThreadedExecutor | None = None) -> None:
    """Execute callbacks until shutdown; SIGTERM -> ExternalShutdownException."""
    ex = _executor_for(node, executor)
    try:
        ex.spin()
    finally:
        ex.remove_node(node)


def spin_once(
    node: Any, *, executor: SingleThreadedExecutor | None = None, timeout_sec: float | None = None
) -> None:
    ex = _executor_for(node, executor)
    try:
        ex.spin_once(timeout_sec)
    finally:
        ex.remove_node(node)


def spin_until_future_complete(
    node: Any,
    future: Future,
    executor: SingleThreadedExecutor | None = None,
    timeout_sec: float | None = None,
) -> None:
    ex = _executor_for(node, executor)
    try:
        ex.spin_until_future_complete(future, timeout_sec)
    finally:
        ex.remove_node(node)


def create_node(node_name: str, **kwargs: Any) -> Any:
    from .node import Node

    return Node(node_name, **kwargs)


__all__ = [
    "Context",
    "ExternalShutdownException",
    "Future",
    "NotInitializedException",
    "SingleThreadedExecutor",
    "create_node",
    "get_default_context",
    "get_global_executor",
    "init",
    "ok",
    "remove_ros_args",
    "shutdown",
    "spin",
    "spin_once",
    "spin_until_future_complete",
    "try_shutdown",
]
