"""An outside rclpy node for the lifecycle tests (test_lifecycle_nodes.py): it drives managed
nodes only through their standard services (``<node>/change_state``, ``<node>/get_state``,
``lifecycle_msgs``) and counts what the graph publishes, in its own rclpy context on the test's
ROS domain (the ``ros_domain`` fixture), spun in a thread.

With ``answer`` it commands like a planner: every control sample (every 5th of a task) on
``/peel/wrench`` gets a ``/peel/cmd_vel`` of ``answer`` mm/s stamped like it; with
``announce`` it publishes model v0 on ``/peel/model_version`` + ``/peel/model_info`` as the
planner does, so a bridge starts its first task.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped, WrenchStamped
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, Int64, String

from peel_msgs_py import codec, topics
from peel_msgs_py.lifecycle import TRANSITIONS
from peel_msgs_py.modelinfo import ModelRecord
from peel_msgs_py.units import mmps_to_mps

qos = topics.qos_profile
#: Seconds an unanswered lifecycle request waits before it is followed up (class Outside).
RESEND_S = 5.0


def wait(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Wait for ``cond``; a timeout (only a hang reaches it) fails naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"no {what} within {timeout_s:g} s"
        time.sleep(0.05)


class Outside:
    """Lifecycle client and message counter (module docstring)."""

    def __init__(self, domain: str | int, slot_s: float, answer: float | None = None,
                 announce: bool = False) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=int(domain))
        self.node = Node("peel_lifecycle_test", context=self.ctx)
        self.slot_s, self.answer = slot_s, answer
        self.lock = threading.Lock()
        self.wrenches: list[tuple[int, str]] = []  # (stamp ns, frame) of every sample
        self.commands: list[int] = []  # stamp ns of every /peel/cmd_vel
        self.trajectories: list[Float64MultiArray] = []
        self.diagnostics: list[tuple[str, int, str]] = []  # (name, level, message)
        self.clients: dict[str, Any] = {}  # the lifecycle service clients, by service name
        n = self.node
        n.create_subscription(WrenchStamped, topics.WRENCH, self.on_wrench,
                              qos(topics.WRENCH, subscriber=True))
        n.create_subscription(TwistStamped, topics.CMD_VEL, self.on_cmd,
                              qos(topics.CMD_VEL, subscriber=True))
        n.create_subscription(Float64MultiArray, topics.TRAJECTORY, self.trajectories.append,
                              qos(topics.TRAJECTORY, subscriber=True))
        n.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self.on_diagnostics,
                              qos(topics.DIAGNOSTICS, subscriber=True))
        self.pub_cmd = n.create_publisher(TwistStamped, topics.CMD_VEL, qos(topics.CMD_VEL))
        if announce:
            n.create_publisher(Int64, topics.MODEL_VERSION, qos(topics.MODEL_VERSION)).publish(
                Int64(data=0))
            rec = ModelRecord(0, "0" * 64, "rig_v0.safetensors", None, None)
            n.create_publisher(String, topics.MODEL_INFO, qos(topics.MODEL_INFO)).publish(
                String(data=rec.to_json()))
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(n)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    # -- what the graph publishes ---------------------------------------------------------------
    def on_wrench(self, msg: WrenchStamped) -> None:
        stamp = codec.join_stamp(msg.header.stamp)
        with self.lock:
            self.wrenches.append((round(stamp * 1e9), msg.header.frame_id))
        task = codec.task_from_frame_id(msg.header.frame_id)
        if self.answer is not None and round((stamp - task * self.slot_s) * 10) % 5 == 0:
            self.command(msg.header, self.answer)

    def command(self, header: object, u_mmps: float) -> None:
        """``/peel/cmd_vel`` of ``u_mmps`` with ``header`` (the sample it answers)."""
        cmd = TwistStamped()
        cmd.header = header
        cmd.twist.linear.x = float(mmps_to_mps(u_mmps))
        self.pub_cmd.publish(cmd)

    def on_cmd(self, msg: TwistStamped) -> None:
        with self.lock:
            self.commands.append(round(codec.join_stamp(msg.header.stamp) * 1e9))

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self.lock:
            self.diagnostics += [(s.name, s.level[0], s.message) for s in msg.status]

    def count(self, what: str) -> int:
        with self.lock:
            return len(getattr(self, what))

    def statuses(self, name: str) -> list[tuple[int, str]]:
        """(level, message) of every status called ``name`` so far."""
        with self.lock:
            return [(lvl, m) for n, lvl, m in self.diagnostics if n == name]

    def resent(self) -> int:
        """How many times in a row the latest sample came (1: once; more: re-sent)."""
        with self.lock:
            last = self.wrenches[-1] if self.wrenches else None
            return sum(1 for w in reversed(self.wrenches) if w == last) if last else 0

    def publishers(self, topic: str) -> int:
        return self.node.count_publishers(topic)

    # -- the standard lifecycle services --------------------------------------------------------
    # A response can be lost while discovery of a client is under way (ros2/rmw_fastrtps#390),
    # so an unanswered get_state is asked again every RESEND_S, and an unanswered change_state
    # is followed by get_state: its goal state is the answer, its start state a lost request.
    def _client(self, target: str, kind: type, name: str) -> Any:
        key = f"/{target}/{name}"
        if key not in self.clients:
            self.clients[key] = self.node.create_client(kind, key)
        client = self.clients[key]
        assert client.wait_for_service(timeout_sec=120.0), f"no {key}"
        return client

    def state(self, target: str, timeout_s: float = 120.0) -> str:
        """``target``'s state label (``get_state``, asked again while unanswered)."""
        client = self._client(target, GetState, "get_state")
        deadline = time.monotonic() + timeout_s
        while True:
            future = client.call_async(GetState.Request())
            resend = time.monotonic() + RESEND_S
            while not future.done() and time.monotonic() < min(resend, deadline):
                time.sleep(0.05)
            if future.done():
                return future.result().current_state.label  # type: ignore[union-attr]
            assert time.monotonic() < deadline, \
                f"no answer of /{target}/get_state within {timeout_s:g} s"

    def change(self, target: str, transition: str, timeout_s: float = 120.0) -> bool:
        """``change_state`` by label; its ``success`` (or get_state's, after a lost answer)."""
        client = self._client(target, ChangeState, "change_state")
        req = ChangeState.Request()
        req.transition.label = transition
        starts, goal = TRANSITIONS[transition]
        deadline = time.monotonic() + timeout_s
        while True:
            future = client.call_async(req)
            resend = time.monotonic() + RESEND_S
            while not future.done() and time.monotonic() < min(resend, deadline):
                time.sleep(0.05)
            if future.done():
                return bool(future.result().success)  # type: ignore[union-attr]
            assert time.monotonic() < deadline, \
                f"no answer of /{target}/change_state within {timeout_s:g} s"
            label = self.state(target, deadline - time.monotonic())
            if label == goal or label not in starts:
                return label == goal

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()
