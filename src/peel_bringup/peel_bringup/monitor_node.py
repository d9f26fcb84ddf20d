"""The launcher's own node (``peel_graph``): it listens to ``/peel/trajectory`` and
``/peel/model_version`` so that ``peel graph`` can print a line per finished task and know
which model versions the planner took (docs/graph.md)."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

import rclpy
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Float64MultiArray, Int64

from peel_msgs_py import codec, topics
from peel_msgs_py.errors import PeelError

NODE_NAME = "peel_graph"


class GraphMonitor(Node):
    """Collects the finished trajectories and the model versions the planner announces."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        self.trajectories: list[Any] = []
        self.version: int | None = None
        self.versions: list[int] = []
        self.create_subscription(Float64MultiArray, topics.TRAJECTORY, self.on_trajectory,
                                 topics.qos_profile(topics.TRAJECTORY, subscriber=True))
        # a deeper reader history than the latched profile's 1: quick successive swaps all count
        self.create_subscription(Int64, topics.MODEL_VERSION, self.on_version, topics.qos_profile(
            dataclasses.replace(topics.topic(topics.MODEL_VERSION).sub_qos, depth=16)))

    def on_trajectory(self, msg: Float64MultiArray) -> None:
        try:
            self.trajectories.append(codec.trajectory_from_msg(msg))
        except PeelError as exc:
            print(f"peel graph: warning: bad {topics.TRAJECTORY} message: {exc}", file=sys.stderr)

    def on_version(self, msg: Int64) -> None:
        self.version = int(msg.data)
        self.versions.append(int(msg.data))


def open_monitor() -> GraphMonitor:
    """rclpy up (the launcher keeps its own SIGINT handling) and the monitor node created."""
    rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
    return GraphMonitor()


def spin_once(mon: GraphMonitor, timeout_s: float) -> None:
    rclpy.spin_once(mon, timeout_sec=timeout_s)


def close_monitor(mon: GraphMonitor) -> None:
    mon.destroy_node()
    rclpy.try_shutdown()
