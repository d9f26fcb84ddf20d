"""``model_learner_node``: online learning of the forward model as a ROS 2 node (docs/graph.md).

Subscribes ``/peel/trajectory`` (trajectory codec); after each task a worker thread runs
Algorithm 1 (:class:`~model_learner_node.online.OnlineLearner`: replay pool, MAML Eq. 26-27 or
baseline 2, checked for finite outputs, safetensors written atomically with the node's name and
the task in their meta), so the callbacks never wait for it; then asks the planner to swap the
new model in by setting its ``model.path`` through the planner's standard ``SetParameters``
service. Every task's update ends in one report on ``/peel/model_update``
(:class:`~peel_msgs_py.modelinfo.UpdateReport`: swapped, refused with the planner's reason,
failed, skipped), so the simulator and ``peel graph`` go on at once instead of waiting for a
model that will not come. A starting model with non-finite outputs is refused (exit 2); after a
failed or refused update the learner keeps training its own last good weights. With
``node.cells`` it serves several cells instead (:mod:`~model_learner_node.cells`,
docs/fleet.md).

With ``online.fast_every`` > 0 the learner also takes the fast step inside the peel
(:mod:`~model_learner_node.in_peel_node`): on the running task's samples, swapped in mid-task
over the same service when it predicts better; one lock keeps it and Algorithm 1 apart.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, String

from peel_msgs_py import inbox, topics
from peel_msgs_py.diagnostics import Status
from peel_msgs_py.errors import PeelError
from peel_msgs_py.modelinfo import FAILED, OFFERED, REFUSED, SWAPPED, UpdateReport
from peel_msgs_py.ros.diagnostics import publish_diagnostics
from peel_msgs_py.ros.main import run_node
from peel_msgs_py.ros.parameters import NamedRefusals, declare
from peel_msgs_py.trajectory import Trajectory
from peel_msgs_py.wire import DropLog

from .cells_node import Cells
from .fast_step import FastStepConfig, FastStepper
from .health import LearnerHealth
from .in_peel import InPeel
from .in_peel_node import InPeelTopics
from .online import OnlineLearner, task_number
from .parameters import NODE_NAME, SPECS
from .resume import LearnerStateError

JOIN_TIMEOUT_S = 10.0  # wall s the worker gets to finish a running update at shutdown


class LearnerNode(NamedRefusals, Node):
    """The trajectory subscription, the swap client and the Algorithm 1 worker thread."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        values = declare(self, SPECS)
        torch.set_num_threads(values["node.threads"])
        try:
            self.learner = OnlineLearner(values, producer=self.get_fully_qualified_name())
        except LearnerStateError as exc:
            raise PeelError(f"parameter 'node.resume': {exc}") from None
        except PeelError as exc:
            raise PeelError(f"parameter 'node.init_model': {exc}") from None
        self.timeout_s = float(values["node.swap_timeout_s"])
        service = values["node.planner_node"].rstrip("/") + "/set_parameters"
        self.client = self.create_client(SetParameters, service)
        self.drops = DropLog()
        self.closing = threading.Event()
        self.lock = threading.Lock()  # Algorithm 1 and the fast step never run at once
        cells = [c for c in values["node.cells"] if c]
        if cells and values["online.fast_every"] > 0:
            raise PeelError("parameter 'online.fast_every': the fast step inside the peel "
                            "serves one cell; set it to 0 with node.cells")
        self.cells = Cells(self, cells, values["node.cell_wait_s"], self.timeout_s, self.decode,
                           self.learner, self.closing) if cells else None
        self.queue: Any = self.cells if self.cells is not None else queue.Queue()
        self.in_peel = self.fast_step(values)  # warmed up before the bridge sees the learner
        if self.cells is None:  # one cell: its topics in the learner's own namespace
            self.pub_update = self.create_publisher(String, topics.MODEL_UPDATE,
                                                    topics.qos_profile(topics.MODEL_UPDATE))
            self.create_subscription(Float64MultiArray, topics.TRAJECTORY, self.on_trajectory,
                                     topics.qos_profile(topics.TRAJECTORY, subscriber=True))
        self.health = LearnerHealth()
        publish_diagnostics(self, self.diagnostics)
        self.worker = threading.Thread(target=self.work, name="algorithm1", daemon=True)
        self.worker.start()
        self.get_logger().info(f"learner ready: {self.learner.describe()}")

    def fast_step(self, values: dict[str, Any]) -> InPeelTopics | None:
        """The fast step inside the peel when ``online.fast_every`` > 0, else None."""
        cfg = FastStepConfig.from_params(values)
        if not cfg.enabled:
            return None
        stepper = FastStepper(self.learner.predictor, cfg)
        self.get_logger().info(f"fast step inside the peel every {cfg.fast_every} samples "
                               f"(warm-up {stepper.warm_up():.1f} s)")
        return InPeelTopics(self, InPeel(stepper, self.learner.out_dir, self.learner.producer),
                            self.lock, self.request_swap, self.closing)

    def on_trajectory(self, msg: Float64MultiArray) -> None:
        """A finished task, queued for the worker (unless :meth:`decode` drops it); it ends
        the fast step's task."""
        traj = self.decode(msg)
        if traj is None or self.learned_already(traj):
            return
        if self.in_peel is not None:
            self.in_peel.end_task(task_number(traj, self.learner.n_tasks + 1) - 1)
        self.queue.put(traj)

    def learned_already(self, traj: Trajectory) -> bool:
        """True (and logged) for a task learned before a restart, received again from the
        bridge's history (``/peel/trajectory`` is transient local)."""
        if not self.learner.has_learned(traj):
            return False
        self.get_logger().info(f"task {task_number(traj, 0)}: learned before the restart; "
                               f"dropped")
        return True

    def decode(self, msg: Float64MultiArray) -> Trajectory | None:
        """The trajectory of ``msg``; None for one that does not decode or holds non-finite
        values, dropped here (counted, logged at most every few seconds)."""
        return inbox.take(self.drops, topics.TRAJECTORY, inbox.trajectory, msg, self.log_drop)

    def log_drop(self, line: str | None) -> None:
        if line is not None:
            self.get_logger().warn(line)

    def work(self) -> None:
        """Worker thread: one update per finished task, the swap request, the report."""
        while (traj := self.queue.get()) is not None and not self.closing.is_set():
            with self.lock:
                t0 = time.perf_counter()
                report = self.update(traj)
                update_s = time.perf_counter() - t0
                if self.closing.is_set():
                    return  # the node is shutting down: nothing is offered any more
                self.finish(report, update_s)

    def finish(self, report: UpdateReport, update_s: float) -> None:
        """Offer an update to the planner (to every cell's, with ``node.cells``); publish the
        report on ``/peel/model_update`` (each cell's, by :class:`Cells`)."""
        try:
            if self.cells is not None:  # every cell, each reported on its own topic
                report = self.cells.deliver(report)
            elif report.status == OFFERED:
                report = self.offer(report)
            if self.closing.is_set() or report.status == OFFERED:
                return  # stopped before the planner answered: nothing to report
            if self.cells is None:
                self.pub_update.publish(String(data=report.to_json()))
            self.health.record(report, update_s)
        except Exception as exc:  # rclpy refuses calls once the node is being destroyed
            if self.closing.is_set():
                return
            self.get_logger().error(f"task {report.task}: the update could not be offered: "
                                    f"{type(exc).__name__}: {exc}")

    def diagnostics(self) -> list[Status]:
        """The learner's health (:class:`~model_learner_node.health.LearnerHealth`), 1 Hz."""
        return [self.health.status(self.queue.qsize())]

    def update(self, traj: Trajectory) -> UpdateReport:
        """Algorithm 1 on the finished task; a failure becomes a ``failed`` report."""
        try:
            return self.learner.learn(traj, self.get_logger())
        except Exception as exc:  # e.g. the checkpoint could not be written
            task = task_number(traj, self.learner.n_tasks)
            self.get_logger().error(f"update after task {task} failed: "
                                    f"{type(exc).__name__}: {exc}")
            return UpdateReport(self.learner.producer, task, FAILED, f"{type(exc).__name__}: {exc}")

    def offer(self, report: UpdateReport) -> UpdateReport:
        """Ask the planner to swap the update in; ``swapped`` or ``refused`` with its reason."""
        name = Path(str(report.path)).name
        ok, reason = self.request_swap(Path(str(report.path)))
        if self.closing.is_set():
            return report  # stopped before the planner answered: nothing to report
        if ok:
            self.get_logger().info(f"task {report.task}: the planner swapped in {name}")
            return replace(report, status=SWAPPED)
        self.get_logger().warn(f"task {report.task}: the planner refused {name}: {reason}")
        return replace(report, status=REFUSED, reason=reason)

    def request_swap(self, path: Path) -> tuple[bool, str]:
        """Set the planner's ``model.path``; wait (in this worker thread) for the answer."""
        if not self.client.wait_for_service(timeout_sec=self.timeout_s):
            return False, f"service {self.client.srv_name} not available after {self.timeout_s:g} s"
        req = SetParameters.Request(parameters=[ParameterMsg(name="model.path", value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=str(path.resolve())))])
        done = threading.Event()
        future = self.client.call_async(req)
        future.add_done_callback(lambda _f: done.set())
        deadline = time.monotonic() + self.timeout_s
        while not done.wait(0.1):  # in slices, so that a shutdown does not wait for it
            if self.closing.is_set():
                self.client.remove_pending_request(future)
                return False, "the learner was stopped before the planner answered"
            if time.monotonic() > deadline:
                self.client.remove_pending_request(future)
                return False, f"no answer from the planner within {self.timeout_s:g} s"
        resp: Any = future.result()
        if resp is None or not resp.results:
            return False, "empty answer"
        return bool(resp.results[0].successful), str(resp.results[0].reason)

    def destroy_node(self) -> None:
        """Stop the worker first (it finishes a running update, offers nothing more), so no
        rclpy call races the destruction of the node."""
        self.closing.set()
        self.queue.put(None)
        if self.in_peel is not None:
            self.in_peel.stop()
            self.in_peel.thread.join(timeout=JOIN_TIMEOUT_S)
        self.worker.join(timeout=JOIN_TIMEOUT_S)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``model_learner_node`` (``--ros-args --params-file ... -p ...``)."""
    return run_node(NODE_NAME, LearnerNode, args)


if __name__ == "__main__":
    sys.exit(main())
