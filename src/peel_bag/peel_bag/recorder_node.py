"""The recorder node: the /peel topics and /clock into an MCAP bag, as received.

Each topic of the table (:mod:`peel_msgs_py.topics`) gets an rclpy *raw* subscription (the
profile its publishers offer; ``/clock`` best effort, the model topics transient local so a late
recorder still records the current version and the planner's recent model records), so every
message is stored as the CDR bytes that arrived, with its receive time (``received_timestamp``
of the message info, ns since the epoch), as ``ros2 bag record`` does without
``--use-sim-time``. A topic's channel is registered once its publishers are known (a timer polls
the graph, a first message forces it): the bag holds the QoS profiles they offer and the type
hash (RIHS01) they announce, both from their endpoint info; the schema text is the Jazzy
definition from ``rosbags``' typestore. Chunks are flushed by size and by age
(:class:`~peel_bag.bag.BagWriter`); the same timer ticks the writer so that a quiet topic's open
chunk still reaches the disk within ``flush_interval_s``. A write that fails (a full disk) stops
the recording: :func:`record` raises the writer's :class:`~peel_bag.bag.BagWriteError` (bag
named, repair command included). With a ``cell`` (a namespace, docs/fleet.md) it records that
cell's topics (``/cell_0/peel/wrench``, ...) under the table's names (``/peel/wrench``): each
cell's bag has the one-cell layout.

``/peel/trajectory`` is the exception to "the profile its publishers offer": its publishers keep
their last 10 tasks for a learner that comes back (transient local, docs/interfaces.md), but those
are tasks peeled before the recording; the recorder reads it volatile (:data:`LIVE_ONLY`), so a bag
holds only the tasks that finished while it ran, whenever ``peel record`` is started.

The subscriptions keep ``RECORDER_DEPTH`` messages per topic (the publishers' own depth is 10):
a recorder whose executor is held up for a while (a loaded machine, a large chunk write) takes
what its DDS reader already holds instead of losing the oldest. On a stop the recorder first
takes every message its readers hold (:func:`drain`), so a message that reached the recorder's
process before the stop is in the bag.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import time
from collections.abc import Sequence
from functools import partial
from typing import Any

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy

from peel_msgs_py.ros.qos import profile_to_bag
from peel_msgs_py.topics import TRAJECTORY, qos_profile, topic, under

from .bag import BagWriteError, BagWriter, message_definition

NODE_NAME = "peel_recorder"
#: Period of the writer tick (s): graph poll, time-based chunk flushes, metadata refreshes.
TICK_PERIOD_S = 0.2
#: Messages each subscription's reader keeps until the executor takes them.
RECORDER_DEPTH = 1000
#: Topics whose kept history is past events, not current state: read volatile (module docstring).
LIVE_ONLY = frozenset({TRAJECTORY})
#: Longest time a stop spends taking the messages the readers hold (s).
DRAIN_LIMIT_S = 5.0


def message_class(type_name: str) -> Any:
    """The generated class of ``pkg/msg/Type`` (``geometry_msgs.msg.WrenchStamped``)."""
    pkg, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def rihs01(type_hash: Any) -> str | None:
    """``RIHS01_<hex>`` of an rclpy ``TypeHash`` (None when the publisher announced none)."""
    if type_hash is None or getattr(type_hash, "version", -1) != 1:
        return None
    return "RIHS01_" + bytes(type_hash.value).hex()


class RecorderNode(Node):
    """Records ``topics`` into an open :class:`BagWriter` (module docstring)."""

    def __init__(self, writer: BagWriter, topics: Sequence[str], *, name: str = NODE_NAME,
                 cell: str = "") -> None:
        super().__init__(name, namespace=cell or "/")
        self.writer = writer
        self.cell = cell  # the topics of this cell, stored under the table's names
        self.received = 0
        self.specs = {n: topic(n) for n in topics}
        self.registered: set[str] = set()
        for spec in self.specs.values():
            self.create_subscription(message_class(spec.type), under(cell, spec.name),
                                     partial(self.on_message, spec.name),
                                     recorder_qos(spec), raw=True)
        self.create_timer(TICK_PERIOD_S, self.on_tick)

    def on_message(self, topic_name: str, data: bytes, info: Any) -> None:
        if topic_name not in self.registered:
            self.register(topic_name, force=True)
        received = int(info.get("received_timestamp", 0)) if isinstance(info, dict) else 0
        with contextlib.suppress(BagWriteError):  # kept in writer.failure; record() ends
            self.writer.write(topic_name, data, received or time.time_ns())
            self.received += 1

    def on_tick(self) -> None:
        with contextlib.suppress(BagWriteError):
            for name in self.specs.keys() - self.registered:
                self.register(name, force=False)
            self.writer.tick()

    def register(self, name: str, *, force: bool) -> None:
        """Add the topic's channel with its publishers' offered QoS and type hash."""
        spec = self.specs[name]
        pubs = [p for p in self.get_publishers_info_by_topic(under(self.cell, name))
                if p.topic_type == spec.type]
        if not pubs and not force:
            return
        text, store_hash = message_definition(spec.type)
        offered = [profile_to_bag(p.qos_profile) for p in pubs] or [spec.qos.to_bag()]
        announced = {h for h in (rihs01(p.topic_type_hash) for p in pubs) if h}
        type_hash = sorted(announced)[0] if announced else store_hash
        if type_hash != store_hash:
            self.get_logger().warn(f"{name}: publishers announce {type_hash}, the Jazzy "
                                   f"definition hashes to {store_hash}")
        self.writer.add_topic(name, spec.type, offered, msgdef=text, rihs01=type_hash)
        self.registered.add(name)


def recorder_qos(spec: Any) -> Any:
    """The subscriber profile of ``spec`` with a history of at least ``RECORDER_DEPTH``, volatile
    for the :data:`LIVE_ONLY` topics."""
    profile = qos_profile(spec, subscriber=True)
    profile.depth = max(profile.depth, RECORDER_DEPTH)
    if spec.name in LIVE_ONLY:
        profile.durability = DurabilityPolicy.VOLATILE
    return profile


def drain(node: RecorderNode, limit_s: float = DRAIN_LIMIT_S) -> int:
    """Take the messages the node's readers hold, until one pass takes none (or ``limit_s``);
    returns how many were written."""
    start, t0 = node.received, time.monotonic()
    while time.monotonic() - t0 < limit_s:
        before = node.received
        for _ in range(50):
            rclpy.spin_once(node, timeout_sec=0.0)
        if node.received == before:
            break
    return node.received - start


def record(writer: BagWriter, names: Sequence[str], duration_s: float | None,
           stop: Any, cell: str = "") -> None:
    """Spin a :class:`RecorderNode` until ``duration_s`` (wall) or ``stop.requested``, then
    take what its readers hold (:func:`drain`); a write that failed ends it with the writer's
    :class:`~peel_bag.bag.BagWriteError`."""
    t0 = time.monotonic()
    rclpy.init(args=None, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = None
    try:
        node = RecorderNode(writer, names, cell=cell)
        print(f"peel record: recording {len(names)} topics to {writer.path}", file=sys.stderr,
              flush=True)
        while not stop.requested and rclpy.ok() and writer.failure is None:
            if duration_s is not None and time.monotonic() - t0 >= duration_s:
                break
            rclpy.spin_once(node, timeout_sec=0.05)
        if rclpy.ok() and writer.failure is None:
            drain(node)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if writer.failure is not None:
        raise writer.failure

