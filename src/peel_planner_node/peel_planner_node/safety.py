"""End-of-task conditions shared by the planner, the node and the experiments (section 4.2).

"When the contact force exceeds the prewarning value [20 N], or the time exceeds t_max, the
experiment will be immediately stopped." :class:`SafetyMonitor` checks the newest sample of a
history; the first trigger latches: the command is zero from then on and the reason is kept
until :meth:`SafetyMonitor.reset`. Reaching q_ter (Algorithm 2, line 2) also ends the task.

Reasons and the trajectory outcome each maps to:

==================  ==============  =====================================================
reason              outcome         condition on the newest sample
==================  ==============  =====================================================
``prewarning_fx``   ``safety_stop`` |F_RX| >= f_prewarn_n
``prewarning_fz``   ``safety_stop`` |F_RZ| >= f_prewarn_n
``timeout``         ``timeout``     t > t_max (and q_ter not reached)
``done``            ``done``        q >= q_ter
==================  ==============  =====================================================

The force check comes first: a sample that both reaches q_ter and breaks the prewarning is a
safety stop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .config import SafetyConfig

OUTCOME_OF: dict[str, str] = {
    "prewarning_fx": "safety_stop",
    "prewarning_fz": "safety_stop",
    "timeout": "timeout",
    "done": "done",
}


@dataclass(frozen=True)
class Stop:
    """Why and when a task ended."""

    reason: str
    outcome: str
    t: float
    value: float

    def as_dict(self) -> dict[str, float | str]:
        return {"reason": self.reason, "outcome": self.outcome, "t": self.t, "value": self.value}


class SafetyMonitor:
    """Latched end-of-task check (section 4.2); see the module docstring."""

    def __init__(self, cfg: SafetyConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else SafetyConfig()
        self.stop: Stop | None = None

    def reset(self) -> None:
        """Forget a previous stop (a new task starts)."""
        self.stop = None

    @property
    def stopped(self) -> bool:
        return self.stop is not None

    @property
    def reason(self) -> str | None:
        return None if self.stop is None else self.stop.reason

    def check_sample(self, t: float, q: float, fx: float, fz: float) -> Stop | None:
        """Check one sample; latches and returns the stop, or None while the task may go on."""
        if self.stop is not None:
            return self.stop
        for name, val in (("t", t), ("q", q), ("fx", fx), ("fz", fz)):
            if not math.isfinite(val):
                raise PeelError(f"sample field '{name}' is not finite ({val!r})")
        c = self.cfg
        stop = None
        if abs(fx) >= c.f_prewarn_n:
            stop = Stop("prewarning_fx", "safety_stop", float(t), float(fx))
        elif abs(fz) >= c.f_prewarn_n:
            stop = Stop("prewarning_fz", "safety_stop", float(t), float(fz))
        elif q >= c.q_ter_mm:
            stop = Stop("done", "done", float(t), float(q))
        elif t > c.t_max_s:
            stop = Stop("timeout", "timeout", float(t), float(t))
        self.stop = stop
        return stop

    def check(self, history: Trajectory) -> Stop | None:
        """Check the newest sample of ``history`` (see :meth:`check_sample`)."""
        if len(history) == 0:
            raise PeelError("history 't' is empty: nothing to check")
        return self.check_sample(float(history.t[-1]), float(history.q[-1]),
                                 float(history.fx[-1]), float(history.fz[-1]))

    def command(self, history: Trajectory, u_mmps: float) -> float:
        """``u_mmps`` while the task may go on, 0.0 once it has ended."""
        return 0.0 if self.check(history) is not None else float(u_mmps)
