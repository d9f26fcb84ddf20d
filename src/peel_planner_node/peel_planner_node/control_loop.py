"""The planner node's work without ROS: assemble state samples from the three state topics and
run one OL-MPPI cycle at every control instant (docs/graph.md, "Time and lockstep").

* :class:`~peel_msgs_py.task.StateAssembler` (shared with the learner's fast step):
  ``/peel/wrench``, ``/peel/twist`` and ``/peel/pose`` arrive as separate messages in any order;
  a sample is complete when all three parts with the same stamp are in.
* :class:`ControlLoop`: per task (a new ``peel_task_<k>`` frame) a fresh
  :class:`~peel_planner_node.mppi.Planner` with ``mppi.seed`` from ``(seed, k)`` as
  ``peel experiment`` does; at every 5th sample (2 Hz of simulated time) one
  :meth:`Planner.plan` (Algorithm 2) on the task's history; between control instants only the
  20 N prewarning and t_max (:class:`~peel_planner_node.safety.SafetyMonitor`), answered at
  once with a zero command. A re-sent sample (same stamp) gets the answer already computed.

The guard of the force limit (:mod:`~peel_planner_node.guard`, Eq. M1-M5) is the planner's; the
loop keeps what a node reports of it as plain fields: ``margin_n`` (the larger axis margin in
use at the last plan, N), ``margins_n`` (RX, RZ) and ``guard`` (the task's
:meth:`~peel_planner_node.guard.GuardStats.as_dict`), and :meth:`ControlLoop.safety_report` is
its JSON for ``/peel/planner_safety`` (what the plant bridges put into the trajectory's meta); a
fallback and a slowdown (Eq. M5) are each a line of their own, and the line that ends a task
carries the task's guard summary.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from peel_msgs_py.diagnostics import DurationWindow
from peel_msgs_py.task import Sample, StateAssembler, mppi_seed
from peel_msgs_py.trajectory import Trajectory

from .config import PlannerConfig
from .cost import Cost
from .mppi import Planner

__all__ = ["Answer", "ControlLoop", "StateAssembler"]

@dataclass(frozen=True)
class Answer:
    """A command for the sample ``stamp_ns``; ``note`` is a line worth logging, if any."""

    stamp_ns: int
    task: int
    u_mmps: float
    note: str | None = None


class ControlLoop:
    """OL-MPPI on assembled samples (module docstring). ``dynamics`` may be swapped any time
    between two calls (:meth:`set_dynamics`); ``cfg`` changes apply from the next task."""

    def __init__(self, cfg: PlannerConfig, dynamics: Any, seed: int) -> None:
        self.cfg, self.seed = cfg, int(seed)
        self.dt_ns = round(cfg.cost.dt_s * 1e9)
        self.steps = cfg.mppi.steps_per_horizon_step
        self.planner = Planner(dynamics, Cost(cfg.cost), cfg)
        self.task = -1
        self.t0_ns = 0
        self.last_ns: int | None = None
        self.rows: list[list[float]] = []  # t, q, v, u, fx, fz, psi of the current task
        self.answered: dict[int, float] = {}
        self.u_hold = 0.0
        self.cycles = 0
        #: wall s of each plan() against the control period (steps * dt, 0.5 s): /diagnostics
        self.latency = DurationWindow(budget_s=self.steps * cfg.cost.dt_s)
        self.margin_n = 0.0
        self.margins_n: tuple[float, float] = (0.0, 0.0)
        self.guard: dict[str, Any] = {}

    def set_dynamics(self, dynamics: Any) -> None:
        self.planner.set_dynamics(dynamics)

    def warm_up(self, samples: int) -> float:
        """One throwaway plan (Algorithm 2) on a resting history of ``samples`` samples, by a
        planner of its own (its own generator: the tasks' plans are unchanged), so that torch's
        first-call costs are paid before the first task and not inside its first control
        period, where a robot controller's watchdog may be waiting. Returns its seconds."""
        rows = np.zeros((max(int(samples), 1), 7))
        rows[:, 0] = np.arange(len(rows)) * self.cfg.cost.dt_s
        rows[:, 6] = float("nan")
        planner = Planner(self.planner.dynamics, Cost(self.cfg.cost), self.cfg)
        planner.reset()
        t0 = time.perf_counter()
        planner.plan(Trajectory.from_array(rows))
        return time.perf_counter() - t0

    def probe_rows(self) -> np.ndarray | None:
        """Measured (q_mm, v_mmps, fx_N, fz_N) rows of the current task, for a probe batch."""
        if not self.rows:
            return None
        rows = np.asarray(self.rows, dtype=np.float64)
        return np.stack([rows[:, 1], rows[:, 2], rows[:, 4], rows[:, 5]], axis=1)

    def on_sample(self, s: Sample) -> Answer | None:
        """Extend the history with ``s``; plan at a control instant (module docstring)."""
        if self.last_ns is not None and s.stamp_ns <= self.last_ns:
            u = self.answered.get(s.stamp_ns)  # a re-sent sample: repeat the answer
            return None if u is None else Answer(s.stamp_ns, self.task, u)
        note = self.new_task(s) if s.task != self.task else None
        self.last_ns = s.stamp_ns
        t = (s.stamp_ns - self.t0_ns) / 1e9
        self.rows.append([t, s.q_mm, s.v_mmps, self.u_hold, s.fx_n, s.fz_n, float("nan")])
        if round((s.stamp_ns - self.t0_ns) / self.dt_ns) % self.steps == 0:
            return self.plan(s, note)
        if self.planner.stop is not None:
            return None
        stop = self.planner.safety.check_sample(t, s.q_mm, s.fx_n, s.fz_n)
        if stop is None or stop.reason == "done":
            return None
        self.answered[s.stamp_ns] = 0.0
        return Answer(s.stamp_ns, self.task, 0.0, f"task {self.task + 1}: blade stopped "
                      f"({stop.reason} at t={stop.t:.1f} s, between control instants); "
                      f"{guard_line(self.guard)}")

    def new_task(self, s: Sample) -> str:
        """A fresh planner for task ``s.task`` with the current model and configuration."""
        cfg = self.cfg.replace(**{"mppi.seed": mppi_seed(self.seed, s.task)})
        previous = self.planner if self.task >= 0 else None
        self.planner = Planner(self.planner.dynamics, Cost(cfg.cost), cfg)
        self.planner.reset()
        self.planner.carry_from(previous)
        self.task, self.t0_ns = s.task, s.stamp_ns
        self.rows, self.answered, self.u_hold = [], {}, 0.0
        self.guard = {}
        return f"task {s.task + 1} starts at ROS time {s.stamp_ns / 1e9:.1f} s"

    def plan(self, s: Sample, note: str | None) -> Answer:
        """One OL-MPPI cycle (Algorithm 2) on the history up to ``s``."""
        history = Trajectory.from_array(np.asarray(self.rows, dtype=np.float64))
        was_stopped = self.planner.stop is not None
        t0 = time.perf_counter()
        u = float(self.planner.plan(history))
        self.latency.add(time.perf_counter() - t0)
        self.cycles += 1
        self.u_hold = u
        self.rows[-1][3] = u
        self.answered[s.stamp_ns] = u
        stop = self.planner.stop
        if stop is not None and not was_stopped:
            note = (f"task {self.task + 1}: blade stopped ({stop.reason} at t={stop.t:.1f} s); "
                    f"{guard_line(self.guard)}")
        elif stop is None:
            note = self.read_guard(history, note)
        return Answer(s.stamp_ns, self.task, u, note)

    def safety_report(self) -> str | None:
        """The JSON of ``/peel/planner_safety``: ``task`` and the task's guard counts (None
        before the task's first plan)."""
        if not self.guard:
            return None
        return json.dumps({"task": self.task, **self.guard})

    def read_guard(self, history: Trajectory, note: str | None) -> str | None:
        """Copy the guard's state after a plan into the plain fields; a fallback's line."""
        last = self.planner.last
        self.margins_n = (float(last["margin"][0]), float(last["margin"][1]))
        self.margin_n = max(self.margins_n)
        self.guard = self.planner.guard.as_dict()
        if last.get("slowed"):
            slow = (f"task {self.task + 1}: slowdown at t={float(history.t[-1]):.1f} s: measured "
                    f"|F| >= {self.cfg.safety.slowdown.start_n:g} N; sent {last['u_out']:.2f} mm/s")
            note = slow if note is None else f"{note}; {slow}"
        if not last.get("fallback"):
            return note
        line = (f"task {self.task + 1}: guard fallback at t={float(history.t[-1]):.1f} s: "
                f"u* = {last['u_star']:.2f} mm/s and even u_min predicted over "
                f"{self.cfg.safety.f_prewarn_n:g} N - margin ({self.margins_n[0]:.2f}, "
                f"{self.margins_n[1]:.2f}) N; sent {last['u_out']:.2f} mm/s")
        return line if note is None else f"{note}; {line}"


def guard_line(g: dict[str, Any]) -> str:
    """One log line of a task's guard summary (:meth:`GuardStats.as_dict`)."""
    if not g:
        return "guard: no plan"
    horizon = (f", set by the horizon error in {g['margin_from_horizon']} plans"
               if g.get("margin_from_horizon") else "")
    return (f"guard: {g['commands_reduced']} of {g['plans']} commands reduced (at most "
            f"{g['reduced_max_mmps']:.2f} mm/s), {g['fallbacks']} fallbacks, "
            f"{g['commands_slowed']} slowed by the measured force, margin max "
            f"({g['margin_max_n'][0]:.2f}, {g['margin_max_n'][1]:.2f}) N{horizon}")
