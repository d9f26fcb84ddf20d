"""One learner for several peeling cells (docs/fleet.md): the rclpy side of ``node.cells``
(the order and the names without ROS: :mod:`model_learner_node.cells`).

Each cell is a namespace (``/cell_0``) holding a plant bridge and a planner. For every cell the
learner subscribes the cell's ``peel/trajectory`` and its planner's latched ``peel/model_info``,
publishes on the cell's ``peel/model_update`` and calls the planner's standard
``<cell>/peel_planner_node/set_parameters`` service (``model.path``), the same swap as one
cell's (docs/graph.md, "The model swap").

* The finished peels of all cells go into one replay pool and Algorithm 1 learns them in the
  order of :class:`~model_learner_node.cells.TaskOrder` (deterministic for a seed; what it
  depends on is said there). An update learned from task k of cell c is named
  ``<learner>@<c>`` in its checkpoint meta and reports (:func:`cell_producer`), so that cell
  c's bridge, whose ``node.learner_node`` is that name, waits for exactly its own update and
  takes every other cell's as a model swapped in "by anyone else".
* Every update goes to every cell: the swaps are requested at once, each answered on its own
  deadline, and each cell's outcome is published on that cell's ``peel/model_update`` as soon
  as it is known, the cell named (``UpdateReport.cell``). A cell whose planner's service is not
  there within :data:`READY_WAIT_S` is reported ``refused`` at once and not waited for.
* A cell that joins late gets the current model on start: the learner subscribes a cell's
  trajectories only once its planner's ``model_info`` (transient local, so a planner that
  starts after the learner is seen too) names the fleet's current model; until then it swaps
  that model in. The bridge does not start task 1 before its trajectory readers (the learner
  among them) are matched, so the late cell's first task runs on the current model. A planner
  that restarts (its model_info says version 0) is caught up the same way.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, String

from peel_msgs_py import topics
from peel_msgs_py.errors import PeelError
from peel_msgs_py.modelinfo import OFFERED, REFUSED, SWAPPED, ModelRecord, UpdateReport
from peel_msgs_py.trajectory import Trajectory

from .cells import TaskOrder, cell_producer, check_cells
from .online import task_number

#: Wall s a swap waits for a cell's planner service to appear before that cell is reported
#: refused (a cell that is down must not hold the others up; it is caught up on its return).
READY_WAIT_S = 1.0
PLANNER = "peel_planner_node"


def swap_request(path: str) -> SetParameters.Request:
    """``model.path := path`` for the planner's standard SetParameters service."""
    return SetParameters.Request(parameters=[ParameterMsg(name="model.path", value=ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value=str(Path(path).resolve())))])


def answer(future: Any) -> tuple[bool, str]:
    """(successful, reason) of a finished SetParameters call."""
    resp = future.result()
    if resp is None or not resp.results:
        return False, "empty answer"
    return bool(resp.results[0].successful), str(resp.results[0].reason)


@dataclass
class Cell:
    """One cell's endpoints and what the learner knows of its planner."""

    name: str
    client: Any
    pub_update: Any
    subscribed: bool = False
    catching_up: bool = False
    record: ModelRecord | None = None
    tasks_seen: int = 0


@dataclass
class Cells:
    """The learner's side of every cell (module docstring); ``get``/``put``/``qsize`` make it
    the node worker's queue."""

    node: Node
    names: Sequence[str]
    wait_s: float
    timeout_s: float
    decode: Callable[[Float64MultiArray], Trajectory | None]
    learner: Any  # the OnlineLearner: its producer names the cell of each update
    closing: threading.Event
    cells: dict[str, Cell] = field(default_factory=dict)
    current: UpdateReport | None = None  # the fleet's model: the last update swapped in

    def __post_init__(self) -> None:
        check_cells(self.names)
        self.base = self.learner.producer
        self.order = TaskOrder(list(self.names), self.wait_s)
        for name in self.names:
            client = self.node.create_client(SetParameters, f"{name}/{PLANNER}/set_parameters")
            pub = self.node.create_publisher(String, topics.under(name, topics.MODEL_UPDATE),
                                             topics.qos_profile(topics.MODEL_UPDATE))
            self.cells[name] = Cell(name, client, pub)
            self.node.create_subscription(
                String, topics.under(name, topics.MODEL_INFO),
                lambda msg, c=name: self.on_model_info(c, msg),
                topics.qos_profile(topics.MODEL_INFO, subscriber=True))

    # -- the worker's queue -----------------------------------------------------------------
    def get(self) -> Trajectory | None:
        """The next finished task in :class:`TaskOrder`'s order, the learner's producer set
        to its cell's name (:func:`cell_producer`); None once stopped."""
        got = self.order.get()
        if got is None:
            return None
        cell, _, traj = got
        self.learner.producer = cell_producer(self.base, cell)
        return traj

    def put(self, item: None) -> None:
        self.order.put(item)

    def qsize(self) -> int:
        return self.order.qsize()

    # -- subscriptions ----------------------------------------------------------------------
    def on_trajectory(self, cell: str, msg: Float64MultiArray) -> None:
        traj = self.decode(msg)
        if traj is not None:
            state = self.cells[cell]
            state.tasks_seen += 1
            self.order.add(cell, task_number(traj, state.tasks_seen), traj)

    def on_model_info(self, cell: str, msg: String) -> None:
        """The cell's planner announced a model: subscribe the cell once it plans with the
        fleet's current model, else swap that model in (a late or restarted planner)."""
        try:
            rec = ModelRecord.from_json(msg.data)
        except PeelError as exc:
            self.node.get_logger().warn(f"{cell}: dropped a model_info message: {exc}")
            return
        state, current = self.cells[cell], self.current
        state.record = rec
        if current is None or rec.sha256 == current.sha256:
            if not state.subscribed:
                state.subscribed = True
                self.node.create_subscription(
                    Float64MultiArray, topics.under(cell, topics.TRAJECTORY),
                    lambda m, c=cell: self.on_trajectory(c, m),
                    topics.qos_profile(topics.TRAJECTORY, subscriber=True))
                self.node.get_logger().info(f"{cell}: serving it (model v{rec.version})")
        elif (not state.subscribed or rec.version == 0) and not state.catching_up:
            self.catch_up(state, current)

    def catch_up(self, state: Cell, current: UpdateReport) -> None:
        """Swap the fleet's current model into ``state``'s planner, reported on its topic."""
        state.catching_up = True
        self.node.get_logger().info(f"{state.name}: swapping the current model in "
                                    f"({Path(str(current.path)).name})")
        future = state.client.call_async(swap_request(str(current.path)))

        def done(f: Any) -> None:
            state.catching_up = False
            ok, reason = answer(f)
            self.publish(state, replace(current, status=SWAPPED if ok else REFUSED,
                                        reason="" if ok else reason))
        future.add_done_callback(done)

    def publish(self, state: Cell, report: UpdateReport) -> None:
        state.pub_update.publish(String(data=replace(report, cell=state.name).to_json()))

    # -- one update to every cell -----------------------------------------------------------
    def deliver(self, report: UpdateReport) -> UpdateReport:
        """Offer ``report``'s update to every cell (or pass on a failed / skipped one), each
        cell's outcome on its own topic; returns the outcome at the cell the task came from
        (``offered`` when stopped before it was known)."""
        origin = report.producer.rpartition("@")[2]
        if report.status != OFFERED:
            for state in self.cells.values():
                self.publish(state, report)
            return replace(report, cell=origin)
        outcomes = self.swap_all(report)
        if any(r.status == SWAPPED for r in outcomes.values()):
            self.current = report
        return outcomes.get(origin, report)

    def swap_all(self, report: UpdateReport) -> dict[str, UpdateReport]:
        """Request the swap from every cell at once; publish each outcome when it is known."""
        name = Path(str(report.path)).name
        start = time.monotonic()
        todo = dict(self.cells)
        sent: dict[str, Any] = {}
        outcomes: dict[str, UpdateReport] = {}
        while (todo or sent) and not self.closing.is_set():
            waited = time.monotonic() - start
            for cell, state in list(todo.items()):
                if state.client.service_is_ready():
                    sent[cell] = state.client.call_async(swap_request(str(report.path)))
                    del todo[cell]
                elif waited > READY_WAIT_S:
                    reason = f"{state.client.srv_name} is not available (the cell is down)"
                    outcomes[cell] = replace(report, status=REFUSED, reason=reason)
                    del todo[cell]
                    self.publish(state, outcomes[cell])
            for cell, future in list(sent.items()):
                if future.done() or waited > self.timeout_s:
                    ok, reason = answer(future) if future.done() else (
                        False, f"no answer from the planner within {self.timeout_s:g} s")
                    if not future.done():
                        self.cells[cell].client.remove_pending_request(future)
                    outcomes[cell] = replace(report, status=SWAPPED if ok else REFUSED,
                                             reason="" if ok else reason)
                    del sent[cell]
                    self.publish(self.cells[cell], outcomes[cell])
                    self.node.get_logger().info(f"task {report.task} of {report.producer}: "
                                                f"{cell} {outcomes[cell].status} {name}")
            time.sleep(0.05)
        return outcomes
