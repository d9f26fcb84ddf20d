"""Simulated time at most a given multiple of wall time (``node.real_time_factor``; docs/graph.md
"Time and lockstep").

In lockstep the simulator steps as soon as the planner answers, so a task of 9 s may pass in
half a second of wall time; whatever runs beside the planner on wall time (the learner's fast
step inside the peel, a person watching the live view) then sees the task over before it has
done anything. :class:`Pace` holds each sample back until its time: sample ``t`` of a task is
due ``t / factor`` wall seconds after the task's first sample (factor 1: real time, as on the
robot). Factor 0 holds nothing back: lockstep alone. The samples and commands are the same at
any factor; only the wall-clock run changes.
"""

from __future__ import annotations

from collections import deque

from peel_msgs_py.task import Sample


class Pace:
    """The samples of a control period waiting for their wall time (module docstring)."""

    def __init__(self, factor: float) -> None:
        if factor < 0.0:
            raise ValueError(f"real-time factor must be >= 0, got {factor!r}")
        self.factor = float(factor)
        self.waiting: deque[Sample] = deque()
        self._wall0 = 0.0
        self._stamp0 = 0

    def start(self, first: Sample, now: float) -> None:
        """A task begins with sample ``first``, sent at wall time ``now``."""
        self.waiting.clear()
        self._wall0, self._stamp0 = now, first.stamp_ns

    def due(self, sample: Sample) -> float:
        """The wall time at which ``sample`` may be published."""
        if self.factor == 0.0:
            return float("-inf")
        return self._wall0 + (sample.stamp_ns - self._stamp0) / 1e9 / self.factor

    def hold(self, samples: list[Sample]) -> None:
        self.waiting.extend(samples)

    def release(self, now: float) -> list[Sample]:
        """The held samples due by ``now``, in order."""
        out = []
        while self.waiting and self.due(self.waiting[0]) <= now:
            out.append(self.waiting.popleft())
        return out

    def clear(self) -> None:
        self.waiting.clear()
