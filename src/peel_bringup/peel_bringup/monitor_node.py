"""The launcher's own node (``peel_graph``): it listens to ``/peel/trajectory``,
``/peel/model_version``, ``/peel/model_info`` and ``/peel/model_update`` so that ``peel graph``
can print a line per finished task and per update of the learner, and know which model versions
the planner took (docs/graph.md). A message that does not decode, or a trajectory holding
non-finite values, is dropped with a counted, rate-limited warning
(:class:`~peel_msgs_py.wire.DropLog`); nothing on the wire ends the launcher."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

import rclpy
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Float64MultiArray, Int64, String

from peel_msgs_py import inbox, topics
from peel_msgs_py.modelinfo import SWAPPED, UpdateWait
from peel_msgs_py.wire import DropLog

NODE_NAME = "peel_graph"
#: The names of peel's nodes (launcher, bridges, planner, learner, recorder, live view): one on the
#: domain, besides this launcher, is another peel graph.
PEEL_NODES = (NODE_NAME, "peel_sim_node", "peel_nachi_bridge", "peel_planner_node",
              "model_learner_node", "peel_recorder", "peel_live")


class GraphMonitor(Node):
    """Collects the finished trajectories, the model versions the planner announces and the
    learner's updates (``updates``: the planner's records and the reports of ``learner``).

    A version counts as the planner's when any record of it arrives: the number on
    ``/peel/model_version`` or the record on ``/peel/model_info`` (the planner publishes both at
    once, latched), a finished trajectory's ``model_versions`` (the versions its bridge saw
    during the task), or the learner's report of an update the planner swapped in. The latched
    samples alone are not enough: in 2 of about 1400 graph runs of the test suite the
    launcher's reader of ``/peel/model_version`` received nothing for a whole run while every
    other topic flowed, and in a demo run the launcher saw v0 only after task 1 had finished.
    """

    def __init__(self, learner: str, cell: str = "") -> None:
        # a cell's monitor (peel fleet) reads that cell's topics: the table's names moved
        super().__init__(NODE_NAME, namespace=cell or "/",
                         cli_args=topics.namespace_remaps() if cell else None)
        self.updates = UpdateWait(learner)
        self.trajectories: list[Any] = []
        self.version: int | None = None
        self.versions: list[int] = []
        self.drops = DropLog()
        self.create_subscription(Float64MultiArray, topics.TRAJECTORY, self.on_trajectory,
                                 topics.qos_profile(topics.TRAJECTORY, subscriber=True))
        # a deeper reader history than the latched profile's 1: quick successive swaps all count
        self.create_subscription(Int64, topics.MODEL_VERSION, self.on_version, topics.qos_profile(
            dataclasses.replace(topics.topic(topics.MODEL_VERSION).sub_qos, depth=16)))
        self.create_subscription(String, topics.MODEL_INFO, self.on_model_info,
                                 topics.qos_profile(topics.MODEL_INFO, subscriber=True))
        self.create_subscription(String, topics.MODEL_UPDATE, self.on_model_update,
                                 topics.qos_profile(topics.MODEL_UPDATE, subscriber=True))

    def peers(self) -> list[str]:
        """What of another peel graph discovery shows now: nodes of a peel name (this launcher
        excepted) and publishers of a ``/peel`` topic."""
        names = [f"{ns.rstrip('/')}/{n}" for n, ns in self.get_node_names_and_namespaces()
                 if n in PEEL_NODES]
        own = self.get_fully_qualified_name()
        if own in names:
            names.remove(own)
        pubs = [f"a publisher of {t}" for t, _ in self.get_topic_names_and_types()
                if t.startswith("/peel/") and self.count_publishers(t) > 0]
        return sorted(names) + pubs

    def drop(self, topic: str, name: str, why: str) -> None:
        """Count a refused message; warn when :class:`DropLog` says a line is due."""
        line = self.drops.drop(topic, name, why)
        if line is not None:
            self.warn(line)

    @staticmethod
    def warn(line: str) -> None:
        print(f"peel graph: warning: {line}", file=sys.stderr, flush=True)

    def on_trajectory(self, msg: Float64MultiArray) -> None:
        traj = inbox.take(self.drops, topics.TRAJECTORY, inbox.trajectory, msg, self.warn)
        if traj is None:
            return
        self.trajectories.append(traj)
        for v in traj.meta.get("model_versions") or []:
            if isinstance(v, int) and v >= 0:
                self.announced(v)

    def on_version(self, msg: Int64) -> None:
        if msg.data < 0:
            self.drop(topics.MODEL_VERSION, "data", f"is negative ({msg.data})")
            return
        self.announced(int(msg.data))

    def announced(self, version: int) -> None:
        """A version the planner announced; ``version`` is the newest (versions only grow, and a
        latched sample may be delivered again after a newer one)."""
        self.version = version if self.version is None else max(self.version, version)
        self.versions.append(version)

    def on_model_info(self, msg: String) -> None:
        rec = inbox.take(self.drops, topics.MODEL_INFO, inbox.model_record, msg, self.warn)
        if rec is None:
            return
        self.updates.add_record(rec)
        self.announced(rec.version)

    def on_model_update(self, msg: String) -> None:
        rep = inbox.take(self.drops, topics.MODEL_UPDATE, inbox.update_report, msg, self.warn)
        if rep is None:
            return
        self.updates.add_report(rep)
        if rep.producer == self.updates.producer and rep.status == SWAPPED \
                and rep.version is not None:
            self.announced(rep.version)


def open_monitor(learner: str) -> GraphMonitor:
    """rclpy up (the launcher keeps its own SIGINT handling) and the monitor node created."""
    rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
    return GraphMonitor(learner)


def open_cell_monitors(cells: dict[str, str]) -> list[GraphMonitor]:
    """``peel fleet``: rclpy up and one monitor per cell (cell namespace -> the producer name
    its updates carry)."""
    rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
    return [GraphMonitor(producer, cell) for cell, producer in cells.items()]


def spin_once(mon: GraphMonitor, timeout_s: float) -> None:
    rclpy.spin_once(mon, timeout_sec=timeout_s)


def close_monitor(mon: GraphMonitor) -> None:
    mon.destroy_node()
    rclpy.try_shutdown()
