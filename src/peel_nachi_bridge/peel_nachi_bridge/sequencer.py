"""Which task the bridge node runs next: the simulator bridge's task loop (docs/graph.md), ROS-free.

* Before task 0: wait (at most ``node.wait_planner_s``) for the planner's ``/peel/model_version``
  and for ``node.min_subscribers`` readers of each state topic (``/peel/wrench``, ``/peel/twist``,
  ``/peel/pose``) and ``node.min_traj_subscribers`` of ``/peel/trajectory``, so that no sample
  or trajectory goes out before its readers match.
* Between tasks: wait (at most ``node.wait_model_s``) for the outcome of the learner's update of
  the task before, known by its identity (:class:`peel_msgs_py.modelinfo.UpdateWait`: the
  planner's record of that update, or the learner's report that it failed, was refused or
  skipped), as Algorithm 2 line 20 does; a model swapped in by anyone else does not end the wait.
* A task that could not start (no ``OK START``, link lost before it) is requested again after
  ``RETRY_S``; it is not counted.
* After ``node.tasks`` tasks (0 = never): :attr:`TaskSequencer.finished`; with
  ``node.exit_when_done`` the node exits once the last model update arrived (or the wait ran out).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from .config import NodeParams
from .task import TaskResult

#: Wall s before a task that could not start is requested again.
RETRY_S = 1.0


@dataclass(frozen=True)
class Readiness:
    """What the node sees of the graph at one moment."""

    model_version: int | None
    #: the fewest readers any of the three state topics has
    state_readers: int
    trajectory_readers: int
    #: whether the outcome of the learner's update after task k (1-based) is known
    update_known: Callable[[int], bool] = field(default=lambda task: False)


class TaskSequencer:
    """Decides, on each :meth:`poll`, whether to request a task and which."""

    def __init__(self, params: NodeParams, log: Callable[[str, str], None]) -> None:
        self.p = params
        self.log = log
        self.next_index = 0
        self.published = 0
        #: 1-based number of the published task whose update is awaited (None: nothing to await)
        self.awaiting: int | None = None
        self.phase = "ready"  # ready -> between -> running -> ... -> finished / exit
        self.since: float | None = None
        self.retry_at = 0.0

    @property
    def finished(self) -> bool:
        return self.phase in ("finished", "exit")

    @property
    def exit_now(self) -> bool:
        """The node should exit (``node.exit_when_done`` and the last update is in)."""
        return self.phase == "exit"

    def poll(self, now: float, seen: Readiness) -> int | None:
        """The index of the task to request now, or None."""
        if self.since is None:
            self.since = now
        if self.phase == "ready":
            return self._ready(now, seen)
        if self.phase == "between" and now >= self.retry_at and self._model_in(now, seen):
            return self._begin(now)
        if self.phase == "finished" and self.p.exit_when_done and self._model_in(now, seen):
            self.phase = "exit"
        return None

    def task_ended(self, now: float, result: TaskResult, published: bool) -> None:
        """The bridge reports a task's end (or that it could not start)."""
        self.since = now
        if not result.started:
            self.phase, self.retry_at = "between", now + RETRY_S
            return
        self.next_index += 1
        self.published += int(published)
        # the learner updates on published trajectories only (meta task_index = result.index)
        self.awaiting = result.index + 1 if published else None
        done = self.p.tasks > 0 and self.next_index >= self.p.tasks
        self.phase = "finished" if done else "between"

    # ------------------------------------------------------------------ phases
    def _ready(self, now: float, seen: Readiness) -> int | None:
        p = self.p
        missing = []
        if p.wait_planner_s > 0 and seen.model_version is None:
            missing.append("the planner's /peel/model_version")
        if seen.state_readers < p.min_subscribers:
            missing.append(f"{p.min_subscribers} readers of each state topic")
        if seen.trajectory_readers < p.min_traj_subscribers:
            missing.append(f"{p.min_traj_subscribers} readers of /peel/trajectory")
        assert self.since is not None
        if missing and now - self.since < p.wait_planner_s:
            return None
        if missing:
            self.log("warn", f"still waiting for {', '.join(missing)} after "
                             f"{p.wait_planner_s:g} s; starting anyway")
        return self._begin(now)

    def _model_in(self, now: float, seen: Readiness) -> bool:
        """The outcome of the learner's update of the last published task is known (or the
        wait ran out)."""
        if self.p.wait_model_s <= 0 or self.awaiting is None:
            return True
        if seen.update_known(self.awaiting):
            self.awaiting = None
            return True
        assert self.since is not None
        if now - self.since >= self.p.wait_model_s:
            self.log("warn", f"the learner's update after task {self.awaiting} did not arrive "
                             f"within {self.p.wait_model_s:g} s; going on with "
                             f"v{seen.model_version}")
            self.awaiting = None  # wait no more
            return True
        return False

    def _begin(self, now: float) -> int:
        self.phase, self.since = "running", now
        return self.next_index
