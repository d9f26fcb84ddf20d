"""One learner for several peeling cells (docs/fleet.md): the rclpy side of ``node.cells``
(the order and the names without ROS: :mod:`model_learner_node.cells`).

Each cell is a namespace (``/cell_0``) holding a plant bridge and a planner. For every cell the
learner subscribes the cell's ``peel/trajectory`` and its planner's transient-local ``peel/model_info``,
publishes on the cell's ``peel/model_update`` and calls the planner's standard
``<cell>/peel_planner_node/set_parameters`` service (``model.path``), the same swap as one
cell's (docs/graph.md, "The model swap"). The node's worker takes its trajectories from
:meth:`Cells.get` and hands every update to :meth:`Cells.deliver`.

* The finished peels of all cells go into one replay pool and Algorithm 1 learns them in the
  order of :class:`~model_learner_node.cells.TaskOrder` (deterministic for a seed; what it
  depends on is said there). An update learned from task k of cell c is named
  ``<learner>@<c>`` in its checkpoint meta and reports (:func:`cell_producer`), so that cell
  c's bridge, whose ``node.learner_node`` is that name, waits for exactly its own update and
  takes every other cell's as a model swapped in "by anyone else".
* Every update goes to every cell: the swaps are requested at once and each cell's outcome is
  published on that cell's ``peel/model_update`` when its planner answers, the cell named
  (``UpdateReport.cell``). The worker waits only for the cell the task came from, and for it
  no longer than :data:`READY_WAIT_S` once another cell's peel is waiting (its answer is
  reported when it comes), so a cell that is down holds nobody up: one whose planner service is not there within
  :data:`READY_WAIT_S` is reported ``refused`` at once, a request left unanswered (a cell
  killed before DDS noticed) is taken back and reported ``refused`` after
  ``node.swap_timeout_s``.
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
    latest: UpdateReport | None = None  # the last update offered
    inflight: dict[str, tuple[Any, UpdateReport, float]] = field(default_factory=dict)
    outcomes: dict[tuple[str, str, int], UpdateReport] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

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
        if traj is None:
            return
        state = self.cells[cell]
        state.tasks_seen += 1
        task = task_number(traj, state.tasks_seen)
        if self.learner.has_learned(traj):  # the bridge's history, after a restart
            self.order.learned(cell, task)
            self.node.get_logger().info(f"{cell}: task {task}: learned before the restart; "
                                        f"dropped")
        else:
            self.order.add(cell, task, traj)

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
        cell's outcome on its own topic as it comes; returns the outcome at the cell the task
        came from once it is known (``offered`` when stopped before)."""
        origin = report.producer.rpartition("@")[2]
        if report.status != OFFERED:
            for state in self.cells.values():
                self.publish(state, report)
            return replace(report, cell=origin)
        self.sweep()
        self.latest = report
        ready = self.wait_ready()
        for state in self.cells.values():
            if state.name in ready:
                self.offer(state, report)
            else:
                self.publish(state, replace(report, status=REFUSED, reason=(
                    f"{state.client.srv_name} is not available (the cell is down or not "
                    f"started; it gets the current model when its planner announces itself)")))
        start = time.monotonic()
        key = (origin, report.producer, report.task)
        while key not in self.outcomes and origin in ready and not self.closing.wait(0.05):
            waited = time.monotonic() - start
            if waited > self.timeout_s or (waited > READY_WAIT_S and self.order.qsize()):
                break  # another cell's peel waits: the answer is reported when it comes
        self.sweep()
        with self.lock:
            return self.outcomes.pop(key, replace(report, cell=origin))

    def wait_ready(self) -> set[str]:
        """The cells whose planner service is there, each waited for up to READY_WAIT_S."""
        deadline = time.monotonic() + READY_WAIT_S
        while True:
            ready = {n for n, c in self.cells.items() if c.client.service_is_ready()}
            if len(ready) == len(self.cells) or time.monotonic() > deadline:
                return ready
            time.sleep(0.05)

    def offer(self, state: Cell, report: UpdateReport) -> None:
        """Request the swap; :meth:`answered` reports it when the planner answers."""
        future = state.client.call_async(swap_request(str(report.path)))
        with self.lock:
            self.inflight[state.name] = (future, report, time.monotonic() + self.timeout_s)
        future.add_done_callback(lambda f, c=state.name, r=report: self.answered(c, r, f))

    def answered(self, cell: str, report: UpdateReport, future: Any) -> None:
        """A planner answered: its outcome on its topic (the origin's kept for the worker)."""
        ok, reason = answer(future)
        self.settle(cell, future, replace(report, status=SWAPPED if ok else REFUSED,
                                          reason="" if ok else reason))

    def settle(self, cell: str, future: Any, outcome: UpdateReport) -> None:
        with self.lock:
            if self.inflight.get(cell, (None,))[0] is future:
                del self.inflight[cell]
            if outcome.status == SWAPPED and outcome.sha256 == self.latest.sha256:
                self.current = self.latest
            if cell == outcome.producer.rpartition("@")[2]:
                self.outcomes[(cell, outcome.producer, outcome.task)] = replace(outcome, cell=cell)
        self.publish(self.cells[cell], outcome)
        self.node.get_logger().info(f"{cell}: {outcome.status} the update after task "
                                    f"{outcome.task} of {outcome.producer.rpartition('@')[2]}")

    def sweep(self) -> None:
        """Requests unanswered past their deadline (a cell killed before DDS noticed): taken
        back and reported refused, so nothing waits for them."""
        now = time.monotonic()
        with self.lock:
            late = [(c, f, r) for c, (f, r, d) in self.inflight.items() if d < now]
        for cell, future, report in late:
            self.cells[cell].client.remove_pending_request(future)
            self.settle(cell, future, replace(report, status=REFUSED, reason=(
                f"no answer from the planner within {self.timeout_s:g} s")))
