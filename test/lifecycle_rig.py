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

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped, WrenchStamped
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, Int64, String

from peel_msgs_py import codec, topics
from peel_msgs_py.modelinfo import ModelRecord
from peel_msgs_py.units import mmps_to_mps

qos = topics.qos_profile


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
    def _call(self, target: str, kind: type, name: str, req: object, timeout_s: float) -> object:
        client = self.node.create_client(kind, f"/{target}/{name}")
        try:
            assert client.wait_for_service(timeout_sec=timeout_s), f"no /{target}/{name}"
            future = client.call_async(req)
            wait(future.done, timeout_s, f"answer of /{target}/{name}")
            return future.result()
        finally:
            self.node.destroy_client(client)

    def state(self, target: str, timeout_s: float = 120.0) -> str:
        """``target``'s state label (``get_state``)."""
        res = self._call(target, GetState, "get_state", GetState.Request(), timeout_s)
        return res.current_state.label  # type: ignore[attr-defined]

    def change(self, target: str, transition: str, timeout_s: float = 120.0) -> bool:
        """``change_state`` by label; its ``success``."""
        req = ChangeState.Request()
        req.transition.label = transition
        return bool(self._call(target, ChangeState, "change_state", req, timeout_s).success)  # type: ignore[attr-defined]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()
