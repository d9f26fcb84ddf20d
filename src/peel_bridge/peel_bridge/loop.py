"""The task loop of a plant bridge, ROS-free: which task runs when (docs/graph.md).

Both plant bridges (``peel_sim_node`` on the simulator, ``peel_nachi_bridge`` on the robot
controller) drive one :class:`TaskLoop` from a wall-clock timer: :meth:`TaskLoop.poll` says
which task to start now, :meth:`TaskLoop.task_ended` that the running one ended. Phases:

* ``wait_graph`` (before task 0): wait at most ``node.wait_planner_s`` for the planner's model
  (its ``/peel/model_info``) and for ``node.min_subscribers`` readers of each state topic and
  ``node.min_traj_subscribers`` of ``/peel/trajectory``, so that no sample or trajectory goes out
  before its readers match; then start anyway, with a warning.
* ``running``: the plant runs task k; the bridge reports its end.
* ``between``: wait at most ``node.wait_model_s`` for the outcome of the learner's update of the
  task before, known by its identity (:class:`peel_msgs_py.modelinfo.UpdateWait`: the planner's
  record of that update, or the learner's report that it failed, was refused or skipped), as
  Algorithm 2 line 20 does; a model swapped in by anyone else does not end the wait. A task
  that could not start (the controller refused it, the link was down) is asked for again after
  :data:`RETRY_S` and not counted.
* ``finished``: after ``node.tasks`` tasks (0 = never) and the last update's wait;
  :attr:`TaskLoop.exit_now` with ``node.exit_when_done``.

Task k occupies ROS time ``[k * node.task_slot_s, (k + 1) * node.task_slot_s)``; inside it the
plant's time restarts at 0 (:func:`task_stamp_ns`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from peel_msgs_py import topics
from peel_msgs_py.modelinfo import SWAPPED, UpdateReport

#: Wall s before a task that could not start is asked for again.
RETRY_S = 1.0


def to_ns(t_s: float) -> int:
    """Seconds of ROS time -> integer nanoseconds (exact comparisons of stamps)."""
    return round(t_s * 1e9)


def task_stamp_ns(index: int, slot_ns: int, t_s: float) -> int:
    """ROS time (ns) of the plant's time ``t_s`` (s from the task's start) in task ``index``."""
    return index * slot_ns + to_ns(t_s)


@dataclass(frozen=True)
class LoopParams:
    """The ``node.*`` parameters of the task loop (both bridges declare them)."""

    tasks: int
    wait_planner_s: float
    wait_model_s: float
    min_subscribers: int
    min_traj_subscribers: int
    exit_when_done: bool

    @classmethod
    def from_params(cls, values: Mapping[str, Any]) -> LoopParams:
        """From the node's declared values (``node.tasks``, ``node.wait_planner_s``, ...)."""
        return cls(**{f.name: values[f"node.{f.name}"] for f in fields(cls)})


@dataclass(frozen=True)
class Readiness:
    """What the node sees of the graph at one moment."""

    model_version: int | None
    #: the fewest readers any of the three state topics has
    state_readers: int
    trajectory_readers: int
    #: the outcome of the learner's update after task k (1-based), None while unknown
    update: Callable[[int], UpdateReport | None] = field(default=lambda task: None)


class TaskLoop:
    """Decides, on each :meth:`poll`, whether to start a task and which (module docstring)."""

    def __init__(self, params: LoopParams, log: Callable[[str, str], None]) -> None:
        self.p = params
        self.log = log
        self.next_index = 0
        #: 1-based number of the published task whose update is awaited (None: nothing to await)
        self.awaiting: int | None = None
        self.phase = "wait_graph"
        self.since: float | None = None
        self.retry_at = 0.0

    @property
    def ended_tasks(self) -> int:
        """Tasks that ran and ended (any outcome)."""
        return self.next_index

    @property
    def finished(self) -> bool:
        return self.phase == "finished"

    @property
    def exit_now(self) -> bool:
        """The node should exit (``node.exit_when_done`` and the last update is in)."""
        return self.finished and self.p.exit_when_done

    def poll(self, now: float, seen: Readiness) -> int | None:
        """The index of the task to start now, or None."""
        if self.since is None:
            self.since = now
        if self.phase == "wait_graph":
            return self._wait_graph(now, seen)
        if self.phase == "between" and now >= self.retry_at and self._model_in(now, seen):
            if self.p.tasks > 0 and self.next_index >= self.p.tasks:
                self.log("info", f"all {self.next_index} tasks done")
                self.phase = "finished"
                return None
            return self._begin(now)
        return None

    def task_ended(self, now: float, index: int, *, started: bool = True,
                   published: bool = True) -> None:
        """Task ``index`` ended (``started`` False: it could not start; ``published``: its
        trajectory went out, so the learner updates on it)."""
        self.phase, self.since = "between", now
        if not started:
            self.retry_at = now + RETRY_S
            return
        self.next_index += 1
        self.awaiting = index + 1 if published else None

    # ------------------------------------------------------------------ phases
    def _wait_graph(self, now: float, seen: Readiness) -> int | None:
        p = self.p
        missing = []
        if seen.model_version is None:
            missing.append(f"{topics.MODEL_INFO} from the planner")
        if seen.state_readers < p.min_subscribers:
            missing.append(f"{p.min_subscribers} subscribers of each state topic "
                           f"({topics.WRENCH}, {topics.TWIST}, {topics.POSE})")
        if seen.trajectory_readers < p.min_traj_subscribers:
            missing.append(f"{p.min_traj_subscribers} subscribers of {topics.TRAJECTORY}")
        assert self.since is not None
        if missing and now - self.since < p.wait_planner_s:
            return None
        if missing:
            self.log("warn", f"starting without {', '.join(missing)}")
        return self._begin(now)

    def _model_in(self, now: float, seen: Readiness) -> bool:
        """The outcome of the learner's update of the last published task is known (or the
        wait ran out)."""
        task, wait_s = self.awaiting, self.p.wait_model_s
        if wait_s <= 0 or task is None:
            return True
        outcome = seen.update(task)
        assert self.since is not None
        if outcome is None and now - self.since < wait_s:
            return False
        if outcome is None:
            self.log("warn", f"the learner's update after task {task} did not arrive within "
                             f"{wait_s:g} s; going on with model v{seen.model_version}")
        elif outcome.status != SWAPPED:
            reason = f": {outcome.reason}" if outcome.reason else ""
            self.log("warn", f"the learner's update after task {task} {outcome.status}{reason}; "
                             f"going on with model v{seen.model_version}")
        self.awaiting = None
        return True

    def _begin(self, now: float) -> int:
        self.phase, self.since = "running", now
        return self.next_index
