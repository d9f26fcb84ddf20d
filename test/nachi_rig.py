"""Test rig for the Nachi bridge node: real rclpy in the test process.

* :class:`Rig` joins the test's ROS domain (the ``ros_domain`` fixture of conftest.py; its own
  rclpy context), records every peel topic to
  a bag with the project's :class:`~peel_bag.bag.BagWriter` (messages serialized with
  ``rclpy.serialization.serialize_message``), and, unless a real planner runs, commands the
  blade: at every control instant (every 5th sample of a task) it publishes ``/peel/cmd_vel``
  with ``speed(task, t)`` (mm/s; None = stay silent), stamped with the sample it answers;
  with ``guard_reports`` it sends before each command the planner's guard report on
  ``/peel/planner_safety`` (:class:`~peel_planner_node.guard.GuardStats`, as the planner node).
* :func:`bridge_cmd` gives the command line that starts the bridge node as a real process (it
  inherits the test's domain and LOCALHOST discovery from the environment).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray, Int64, String

from peel_bag.bag import BagWriter
from peel_msgs_py import codec, topics
from peel_msgs_py.modelinfo import ModelRecord
from peel_msgs_py.units import mmps_to_mps
from peel_planner_node.guard import GuardStats

SLOT_S = 100.0
TYPES = {topics.WRENCH: WrenchStamped, topics.TWIST: TwistStamped, topics.POSE: PoseStamped,
         topics.CMD_VEL: TwistStamped, topics.TRAJECTORY: Float64MultiArray,
         topics.MODEL_VERSION: Int64, topics.CLOCK: Clock}


qos = topics.qos_profile


def bridge_cmd(port: int, **params: object) -> list[str]:
    """``python -m peel_nachi_bridge.node`` with the shipped file and ``-p`` settings."""
    root = Path(__file__).resolve().parents[1]
    cmd = [sys.executable, "-m", "peel_nachi_bridge.node", "--ros-args", "--params-file",
           str(root / "config" / "peel_nachi_bridge.yaml"), "-p", f"link.port:={port}"]
    for key, value in params.items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        cmd += ["-p", f"{key}:={text}"]
    return cmd


class Rig:
    """Recorder + commander (+ a latched model version and record) in the test process."""

    def __init__(self, domain: str | int, bag: Path,
                 speed: Callable[[int, float], float | None] | None = None,
                 model_version: int | None = 0, guard_reports: bool = False) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=int(domain))
        self.node = Node("peel_test_rig", context=self.ctx)
        self.speed = speed
        #: task -> the guard reports sent on /peel/planner_safety (``guard_reports``), in order
        self.reports: dict[int, list[dict]] | None = {} if guard_reports else None
        self.guards: dict[int, GuardStats] = {}
        self.lock = threading.Lock()
        self.trajectories: list[Float64MultiArray] = []
        self.bag = BagWriter(bag).open()
        self.subs = {}
        for name, cls in TYPES.items():
            spec = topics.topic(name)
            self.bag.add_topic(name, spec.type, [spec.qos])
            self.subs[name] = self.node.create_subscription(cls, name, self._recorder(name),
                                                            qos(name, subscriber=True))
        self.pub_cmd = self.node.create_publisher(TwistStamped, topics.CMD_VEL,
                                                  qos(topics.CMD_VEL))
        self.pub_version = self.node.create_publisher(Int64, topics.MODEL_VERSION,
                                                      qos(topics.MODEL_VERSION))
        self.pub_info = self.node.create_publisher(String, topics.MODEL_INFO,
                                                   qos(topics.MODEL_INFO))
        self.pub_safety = self.node.create_publisher(String, topics.PLANNER_SAFETY,
                                                     qos(topics.PLANNER_SAFETY))
        if model_version is not None:
            self.announce(model_version)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def announce(self, version: int, producer: str | None = None, task: int | None = None) -> None:
        """Announce a model as the planner does: ``/peel/model_version`` and its record on
        ``/peel/model_info`` (``producer``'s update after ``task``, or None)."""
        rec = ModelRecord(version, f"{version:064x}", f"rig_v{version}.safetensors", producer, task)
        self.pub_version.publish(Int64(data=version))
        self.pub_info.publish(String(data=rec.to_json()))

    def wait_matched(self, name: str, publishers: int, timeout_s: float = 120.0) -> None:
        """Wait until the recorder's reader of ``name`` has matched ``publishers`` writers of
        other nodes (a node's publisher matched late loses its first messages to this bag). The
        reader matches the rig's own writer of ``name`` too, so that one is not counted."""
        own = sum(1 for p in self.node.publishers if p.topic_name == name)
        deadline = time.monotonic() + timeout_s
        while self.subs[name].get_publisher_count() < own + publishers:
            assert time.monotonic() < deadline, f"{publishers} publishers of {name} not matched"
            time.sleep(0.05)

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)
            with self.lock:
                self.bag.tick()

    def _recorder(self, name: str) -> Callable[[object], None]:
        def record(msg: object) -> None:
            with self.lock:
                self.bag.write(name, serialize_message(msg), time.time_ns())
            if name == topics.TRAJECTORY:
                self.trajectories.append(msg)  # type: ignore[arg-type]
            elif name == topics.WRENCH and self.speed is not None:
                self._command(msg)  # type: ignore[arg-type]
        return record

    def _command(self, msg: WrenchStamped) -> None:
        task = codec.task_from_frame_id(msg.header.frame_id)
        t = codec.join_stamp(msg.header.stamp) - task * SLOT_S
        if round(t * 10) % 5:
            return
        u = self.speed(task, t) if self.speed else None
        if u is None:
            return
        if self.reports is not None:  # as the planner node: the guard report before the command
            self._report(task, u)
        cmd = TwistStamped()
        cmd.header = msg.header
        cmd.twist.linear.x = float(mmps_to_mps(u))
        self.pub_cmd.publish(cmd)

    def _report(self, task: int, u: float) -> None:
        """The planner's guard report of one plan: margin 0.5 N on RX, every 3rd command a
        fallback (GuardStats, the fields a real planner sends)."""
        g = self.guards.setdefault(task, GuardStats())
        g.record(np.array([0.5, 0.0]), u, u, g.plans % 3 == 2, False)
        report = {"task": task, **g.as_dict()}
        assert self.reports is not None
        self.reports.setdefault(task, []).append(report)
        self.pub_safety.publish(String(data=json.dumps(report)))

    def wait_trajectories(self, n: int, timeout_s: float) -> list[Float64MultiArray]:
        deadline = time.monotonic() + timeout_s
        while len(self.trajectories) < n and time.monotonic() < deadline:
            time.sleep(0.05)
        return list(self.trajectories)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        with self.lock:
            self.bag.close()
        self.node.destroy_node()
        self.ctx.try_shutdown()
