"""One task as the bridge sees it: the samples, the commands in force, and how it ended.

:class:`TaskRecorder` collects the controller's samples (paper units, as on the line) and the
commands the bridge forwarded; :meth:`TaskRecorder.result` turns them into the finished
:class:`~peel_msgs_py.trajectory.Trajectory` that goes out on ``/peel/trajectory``, exactly as
the simulator bridge's (u_k = the command in force over (t_k, t_{k+1}], psi unknown = NaN).

How a task ends, and the trajectory outcome it gets (docs/nachi.md):

==================  ===============  ==========================================================
reason              outcome          when
==================  ===============  ==========================================================
``reached``         ``done``         ``DONE reached`` (q >= q_ter)
``timeout``         ``timeout``      ``DONE timeout`` (t >= t_max)
``prewarning``      ``safety_stop``  a sample at or above the 20 N prewarning: the bridge sent STOP
``alarm``           ``safety_stop``  ``ALARM 20`` (the controller's force alarm)
``alarm``           ``aborted``      any other ``ALARM`` (``10 watchdog``: the planner fell silent)
``stalled``         ``aborted``      no sample for ``safety.stall_timeout_s``: STOP
``bad_lines``       ``aborted``      ``safety.bad_line_limit`` bad lines in a row: STOP
``connection_lost`` ``aborted``      the link broke during the task
``stopped``         ``aborted``      ``DONE stopped`` that the bridge did not ask for
``shutdown``        ``aborted``      the bridge itself was stopped during the task
``deactivated``     ``aborted``      the bridge was deactivated (lifecycle) during the task: STOP
==================  ===============  ==========================================================
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from peel_msgs_py.trajectory import Trajectory

from . import protocol as p

#: Outcome of each end reason (the ``alarm`` row depends on the code, see :func:`alarm_outcome`).
OUTCOME_OF = {
    "reached": "done", "timeout": "timeout", "prewarning": "safety_stop", "stalled": "aborted",
    "bad_lines": "aborted", "connection_lost": "aborted", "stopped": "aborted",
    "shutdown": "aborted",
}


def alarm_outcome(code: int) -> str:
    """``safety_stop`` for the controller's force alarm, ``aborted`` for any other alarm."""
    return "safety_stop" if code == p.ALARM_FORCE else "aborted"


@dataclass
class TaskResult:
    """A task that ended (``started``) or could not start (``started`` False, no trajectory)."""

    index: int
    started: bool
    outcome: str
    reason: str
    detail: str
    trajectory: Trajectory | None = None
    stop_delay_s: float | None = None


@dataclass
class TaskRecorder:
    """The samples and commands of the running task."""

    index: int
    controller_id: str
    controller_task_id: int
    samples: list[p.Sample] = field(default_factory=list)
    u_after: list[float] = field(default_factory=list)  # command in force after sample k
    u_in_force: float = 0.0
    commands: list[float] = field(default_factory=list)
    bad_lines: dict[str, int] = field(default_factory=lambda: dict.fromkeys(p.BAD_KINDS, 0))
    refused: list[str] = field(default_factory=list)
    alarm: str | None = None
    stop_delay_s: float | None = None
    done_t_s: float | None = None

    def add(self, s: p.Sample) -> bool:
        """Append a sample; False (not added) when its t does not increase."""
        if self.samples and not s.t > self.samples[-1].t:
            return False
        if self.samples:
            self.u_after.append(self.u_in_force)
        self.samples.append(s)
        return True

    def command_sent(self, u: float) -> None:
        self.commands.append(u)
        self.u_in_force = u

    def command_refused(self, err: p.Err) -> None:
        """The controller refused the latest V: the command before it stays in force."""
        self.refused.append(f"{err.code} {err.text}")
        if self.commands:
            self.commands.pop()
        self.u_in_force = self.commands[-1] if self.commands else 0.0

    def result(self, outcome: str, reason: str, detail: str) -> TaskResult:
        meta: dict[str, Any] = {
            "source": "nachi", "controller_id": self.controller_id,
            "controller_task_id": self.controller_task_id, "end_reason": reason,
            "end_detail": detail, "bad_lines": dict(self.bad_lines),
            "refused_v": list(self.refused), "alarm": self.alarm,
            "stop_delay_s": self.stop_delay_s, "done_t_s": self.done_t_s,
        }
        n = len(self.samples)
        rows = np.full((n, 7), np.nan)
        if n:
            rows[:, [0, 1, 2, 4, 5]] = [(s.t, s.q, s.v, s.fx, s.fz) for s in self.samples]
            rows[:, 3] = [*self.u_after, 0.0]  # the last sample: the blade is brought to rest
        traj = Trajectory.from_array(rows, outcome=outcome, meta=meta)
        return TaskResult(self.index, True, outcome, reason, detail, traj, self.stop_delay_s)
