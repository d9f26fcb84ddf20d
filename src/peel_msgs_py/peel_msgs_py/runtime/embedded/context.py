"""The process-wide ROS context of the embedded runtime: init/shutdown, the DDS participant.

One Cyclone DDS domain participant per context (as ``rmw_cyclonedds_cpp`` has one per context),
created when the first node needs it, in domain ``ROS_DOMAIN_ID`` with the loopback-only
configuration of :mod:`.config` unless the network is opened. ``rclpy.init`` installs a SIGTERM
handler that shuts the context down, after which ``spin`` raises
:class:`ExternalShutdownException`; SIGINT keeps Python's default (``KeyboardInterrupt``).
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

from cyclonedds.core import DDSException
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.topic import Topic

from ...errors import PeelError
from . import args as ros_args
from . import config
from .logging import set_default_level


class ExternalShutdownException(Exception):
    """Raised by ``spin`` when the context was shut down from outside (SIGTERM, shutdown())."""


class NotInitializedException(PeelError):
    """A node or executor was used before ``rclpy.init()`` or after ``rclpy.shutdown()``."""


def delete_entity(entity: Any) -> None:
    """Delete a Cyclone DDS entity now (and its children), ignoring one already gone."""
    if entity is None:
        return
    with contextlib.suppress(DDSException):
        entity.__del__()


class DdsEntity:
    """Publisher, Subscription, Service, Client: ``destroy()`` goes through the owning node
    (which drops the entity and calls ``_delete``); ``_dds_handles()`` names the Cyclone DDS
    entities deleted then, in order."""

    _node: Any

    def _dds_handles(self) -> tuple[Any, ...]:
        raise NotImplementedError

    def destroy(self) -> bool:
        self._node._destroy_entity(self)
        return True

    def _delete(self) -> None:
        for handle in self._dds_handles():
            delete_entity(handle)


class Context:
    """``rclpy.context.Context``: lifetime of the ROS client library in this process."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._initialized = False
        self._shutdown = False
        self._external = False
        self.ros_args = ros_args.RosArgs()
        self.domain_id = 0
        self._domain: Domain | None = None
        self._participant: DomainParticipant | None = None
        self._topics: dict[str, Topic] = {}
        self._csid = 0
        self._callbacks: list[Callable[[], None]] = []
        self._nodes: list[Any] = []
        self._discovery: Any = None

    # ------------------------------------------------------------------ lifecycle
    def init(self, args: Sequence[str] | None = None, *, domain_id: int | None = None) -> None:
        with self._lock:
            if self._initialized and not self._shutdown:
                raise PeelError("rclpy.init() has already been called for this context")
            parsed, _ = ros_args.parse(sys.argv if args is None else args)  # rclpy: argv
            if parsed.log_level:
                set_default_level(parsed.log_level)
            did = config.domain_id() if domain_id is None else int(domain_id)
            if not 0 <= did <= config.MAX_DOMAIN_ID:
                raise PeelError(f"domain_id must lie in 0..{config.MAX_DOMAIN_ID}, got {did}")
            config.network_mode()  # validate PEEL_DDS_NETWORK early
            self.ros_args = parsed
            self.domain_id = did
            self._initialized = True
            self._shutdown = False
            self._external = False
            self._topics = {}

    def ok(self) -> bool:
        if self._external and self._initialized and not self._shutdown:
            # a SIGTERM arrived: finish the shutdown here, outside any DDS call
            self.try_shutdown()
        return self._initialized and not self._shutdown

    def shutdown(self) -> None:
        with self._lock:
            if not self._initialized or self._shutdown:
                raise PeelError("context is not initialized or has already been shut down")
            self._do_shutdown()

    def try_shutdown(self) -> None:
        with self._lock:
            if self._initialized and not self._shutdown:
                self._do_shutdown()

    def _do_shutdown(self) -> None:
        self._shutdown = True
        for cb in list(self._callbacks):
            with contextlib.suppress(Exception):  # a callback must not stop the shutdown
                cb()
        self._callbacks.clear()
        self._nodes = []
        self._discovery = None
        self._topics = {}
        delete_entity(self._participant)
        delete_entity(self._domain)
        self._participant = None
        self._domain = None

    def on_shutdown(self, callback: Callable[[], None]) -> None:
        self._callbacks.append(callback)

    @property
    def externally_shut_down(self) -> bool:
        return self._external

    # ------------------------------------------------------------------ DDS
    @property
    def participant(self) -> DomainParticipant:
        with self._lock:
            if not self._initialized or self._shutdown:
                raise NotInitializedException("rclpy.init() has not been called")
            if self._participant is None:
                xml = config.domain_config()
                try:
                    if xml is not None:
                        self._domain = Domain(self.domain_id, xml)
                    self._participant = DomainParticipant(self.domain_id)
                except DDSException as exc:
                    raise PeelError(
                        f"cannot create a DDS participant in domain {self.domain_id}: {exc}"
                    ) from None
            return self._participant

    def topic(self, dds_name: str, data_type: type[Any]) -> Topic:
        """The DDS topic ``dds_name`` of ``data_type``, created once per context."""
        with self._lock:
            key = f"{dds_name}\0{data_type.__idl_typename__}"
            top = self._topics.get(key)
            if top is None:
                try:
                    top = Topic(self.participant, dds_name, data_type)
                except DDSException as exc:
                    raise PeelError(
                        f"cannot create DDS topic {dds_name!r} of type "
                        f"{data_type.__idl_typename__}: {exc}"
                    ) from None
                self._topics[key] = top
            return top

    def graph_changed(self, node: Any, alive: bool = True) -> None:
        """A node or one of its entities came or went: republish ros_discovery_info."""
        with self._lock:
            if not self._initialized or self._shutdown:
                return
            if alive and node not in self._nodes:
                self._nodes.append(node)
            elif not alive and node in self._nodes:
                self._nodes.remove(node)
            if self._discovery is None:
                from .discovery import DiscoveryPublisher

                self._discovery = DiscoveryPublisher(self)
            self._discovery.publish(self._nodes)

    def next_client_service_id(self) -> bytes:
        """16-byte id: participant GUID prefix + big-endian counter (rmw_cyclonedds' csid)."""
        with self._lock:
            self._csid += 1
            prefix = self.participant.get_guid().bytes[:12]
            return prefix + self._csid.to_bytes(4, "big")


def csid_to_string(csid: bytes) -> str:
    """rmw_cyclonedds' text form: first byte 2-digit hex, the rest hex, '.'-separated."""
    return f"{csid[0]:2x}" + "".join(f".{b:x}" for b in csid[1:])


_default_context = Context()
_installed: dict[int, Any] = {}


def get_default_context() -> Context:
    return _default_context


def _on_sigterm(signum: int, frame: Any) -> None:
    # Only flag it: the handler may run in the middle of executor code using DDS entities.
    # ok() turns False at once; spin/spin_once finish the shutdown and raise
    # ExternalShutdownException.
    _default_context._external = True


def install_signal_handlers() -> None:
    """SIGTERM -> shut the default context down (spin then raises ExternalShutdownException)."""
    if threading.current_thread() is not threading.main_thread() or _installed:
        return
    _installed[signal.SIGTERM] = signal.signal(signal.SIGTERM, _on_sigterm)


def uninstall_signal_handlers() -> None:
    if threading.current_thread() is not threading.main_thread():
        return
    for signum, previous in list(_installed.items()):
        signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
        del _installed[signum]
