"""``model_learner_node``: online learning of the forward model as a ROS 2 node (docs/graph.md).

Subscribes ``/peel/trajectory`` (trajectory codec); after each task a worker thread runs
Algorithm 1 (:class:`~model_learner_node.online.OnlineLearner`: replay pool, MAML Eq. 26-27 or
baseline 2, versioned safetensors written atomically), so the callbacks never wait for it; then
asks the planner to swap the new model in by setting its ``model.path`` through the planner's
standard ``SetParameters`` service. A refused swap is logged with the planner's reason; the
learner keeps training its own copy.
"""

from __future__ import annotations

import queue
import sys
import threading
from pathlib import Path
from typing import Any

import torch
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from peel_msgs_py import codec, topics
from peel_msgs_py.errors import PeelError
from peel_msgs_py.ros.main import run_node
from peel_msgs_py.ros.parameters import NamedRefusals, declare
from peel_msgs_py.trajectory import Trajectory

from .online import OnlineLearner
from .parameters import NODE_NAME, SPECS


class LearnerNode(NamedRefusals, Node):
    """The trajectory subscription, the swap client and the Algorithm 1 worker thread."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        values = declare(self, SPECS)
        torch.set_num_threads(values["node.threads"])
        self.learner = OnlineLearner(values)
        self.timeout_s = float(values["node.swap_timeout_s"])
        service = values["node.planner_node"].rstrip("/") + "/set_parameters"
        self.client = self.create_client(SetParameters, service)
        self.queue: queue.Queue[Trajectory | None] = queue.Queue()
        self.create_subscription(Float64MultiArray, topics.TRAJECTORY, self.on_trajectory,
                                 topics.qos_profile(topics.TRAJECTORY, subscriber=True))
        self.worker = threading.Thread(target=self.work, name="algorithm1", daemon=True)
        self.worker.start()
        self.get_logger().info(f"learner ready: {self.learner.describe()}")

    def on_trajectory(self, msg: Float64MultiArray) -> None:
        try:
            self.queue.put(codec.trajectory_from_msg(msg))
        except PeelError as exc:
            self.get_logger().error(f"ignoring a malformed {topics.TRAJECTORY} message: {exc}")

    def work(self) -> None:
        """Worker thread: one update per finished task, then the swap request."""
        while (traj := self.queue.get()) is not None:
            try:
                path = self.learner.learn(traj, self.get_logger())
            except Exception as exc:  # keep the node alive; the planner keeps its model
                self.get_logger().error(f"update after task {self.learner.n_tasks} failed: "
                                        f"{type(exc).__name__}: {exc}")
                continue
            if path is None:
                continue
            ok, reason = self.request_swap(path)
            if ok:
                self.get_logger().info(f"planner swapped to v{self.learner.version}")
            else:
                self.get_logger().warn(f"planner refused v{self.learner.version}: {reason}")

    def request_swap(self, path: Path) -> tuple[bool, str]:
        """Set the planner's ``model.path``; wait (in this worker thread) for the answer."""
        if not self.client.wait_for_service(timeout_sec=self.timeout_s):
            return False, f"service {self.client.srv_name} not available after {self.timeout_s:g} s"
        req = SetParameters.Request(parameters=[ParameterMsg(name="model.path", value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=str(path.resolve())))])
        done = threading.Event()
        future = self.client.call_async(req)
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(self.timeout_s):
            self.client.remove_pending_request(future)
            return False, f"no answer from the planner within {self.timeout_s:g} s"
        resp: Any = future.result()
        if resp is None or not resp.results:
            return False, "empty answer"
        return bool(resp.results[0].successful), str(resp.results[0].reason)

    def destroy_node(self) -> None:
        self.queue.put(None)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``model_learner_node`` (``--ros-args --params-file ... -p ...``)."""
    return run_node(NODE_NAME, LearnerNode, args)


if __name__ == "__main__":
    sys.exit(main())
