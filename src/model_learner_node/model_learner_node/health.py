"""The learner's health for ``/diagnostics`` (ROS-free; :mod:`peel_msgs_py.diagnostics`).

Levels follow the last update's report (:class:`~peel_msgs_py.modelinfo.UpdateReport`): ERROR
when Algorithm 1 failed (or its model predicted non-finite forces), WARN when the planner
refused the model, OK when it was swapped in or there was nothing to learn.
"""

from __future__ import annotations

import threading
from collections import Counter

from peel_msgs_py.diagnostics import ERROR, WARN, Check, DurationWindow, Status, make_status
from peel_msgs_py.modelinfo import FAILED, REFUSED, UpdateReport


class LearnerHealth:
    """What the worker thread reports after each update; read by the node's 1 Hz timer."""

    def __init__(self) -> None:
        self.update_s = DurationWindow()
        self.last: UpdateReport | None = None
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()

    def record(self, report: UpdateReport, update_s: float) -> None:
        """One finished update: its final report and the wall s Algorithm 1 took."""
        self.update_s.add(update_s)
        with self._lock:
            self.last = report
            self.counts[report.status] += 1

    def status(self, waiting: int) -> Status:
        """The status after the last update; ``waiting`` = finished tasks not learned yet."""
        with self._lock:
            last, counts = self.last, dict(self.counts)
        median, worst, _ = self.update_s.summary()
        checks: list[Check] = []
        if last is not None and last.status == FAILED:
            checks.append((ERROR, f"update after task {last.task} failed: {last.reason}"))
        elif last is not None and last.status == REFUSED:
            checks.append((WARN, f"the planner refused the update after task {last.task}: "
                                 f"{last.reason}"))
        values: dict[str, object] = {
            "updates": self.update_s.count, "update time last (s)": self.update_s.last,
            "update time median (s)": median, "update time max (s)": worst,
            "last task": None if last is None else last.task,
            "last result": None if last is None else last.status,
            "last reason": None if last is None else last.reason or None,
            "last model": None if last is None else last.path,
            **{f"{s} updates": counts.get(s, 0) for s in ("swapped", "refused", "failed", "skipped")},
            "tasks waiting": waiting,
        }
        ok = "no update yet" if last is None else f"update after task {last.task}: {last.status}"
        return make_status("model_learner_node: online learning", "model_learner_node", checks,
                           values, ok_message=ok)
