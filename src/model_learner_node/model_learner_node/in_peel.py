"""The learner node's fast step inside the peel, without ROS (docs/graph.md, "The fast step").

The plant bridge publishes every sample of the running task on ``/peel/wrench``, ``/peel/twist``
and ``/peel/pose``; :class:`InPeel` collects them (:class:`~peel_msgs_py.task.StateAssembler`)
into the running task tau_run, hands a copy of it to the node's fast-step thread whenever a fast
step is due (:meth:`FastStepper.due`), and there runs the step
(:class:`~model_learner_node.fast_step.FastStepper`: Eq. 26 from the prior theta on tau_run's
samples, checked on its newest ones against the model in use). An accepted fast model is written
atomically as ``out_dir/fast_tKKKK_sSS.safetensors`` with its identity in the meta
(:func:`peel_model.versions.fast_meta`: producer, task, step, fitted and checked samples), which
the planner carries into ``/peel/model_info`` and the bridge into the trajectory meta.

A step of a task that has ended (its trajectory arrived, or a sample of a later task) is never
offered: :meth:`InPeel.current` is asked again just before the swap. The prior is the learner's
predictor; the node holds one lock over Algorithm 1 and the fast step, so a fast step never
reads weights that Algorithm 1 is changing, and a fast model never becomes the prior.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from peel_model.checkpoint import save_checkpoint
from peel_model.versions import fast_meta
from peel_msgs_py.task import Sample, StateAssembler
from peel_msgs_py.trajectory import Trajectory

from .fast_step import FastResult, FastStepper


class InPeel:
    """The running task's samples and the fast step on them (module docstring)."""

    def __init__(self, stepper: FastStepper, out_dir: Path, producer: str) -> None:
        self.stepper, self.out_dir, self.producer = stepper, Path(out_dir), producer
        self.parts = StateAssembler()
        self.task: int | None = None  # 0-based index of the running task (frame peel_task_<k>)
        self.t0_ns = 0
        self.rows: list[list[float]] = []
        self.last_n = 0  # samples of the running task at the last hand-over
        self.ended: set[int] = set()

    def add(self, stamp_ns: int, task: int, **parts: float) -> Trajectory | None:
        """One part of a sample (the callback thread); the running task so far when the
        completed sample makes a fast step due, else None."""
        s = self.parts.add(stamp_ns, task, **parts)
        return None if s is None else self.on_sample(s)

    def on_sample(self, s: Sample) -> Trajectory | None:
        if s.task in self.ended:
            return None
        if s.task != self.task:
            if self.task is not None:
                self.ended.add(self.task)
            self.task, self.t0_ns, self.rows, self.last_n = s.task, s.stamp_ns, [], 0
        t = (s.stamp_ns - self.t0_ns) / 1e9
        if self.rows and t <= self.rows[-1][0]:
            return None  # re-sent or out of order: the task's samples stay monotonic
        self.rows.append([t, s.q_mm, s.v_mmps, float("nan"), s.fx_n, s.fz_n, float("nan")])
        if not self.stepper.due(len(self.rows), self.last_n):
            return None
        self.last_n = len(self.rows)
        return self.running()

    def running(self) -> Trajectory:
        """A copy of the running task so far (u and psi are not on the sample topics: NaN)."""
        a = np.asarray(self.rows, dtype=np.float64)
        return Trajectory(t=a[:, 0], q=a[:, 1], v=a[:, 2], u=a[:, 3], fx=a[:, 4], fz=a[:, 5],
                          psi=a[:, 6], meta={"task_index": self.task})

    def end_task(self, index: int) -> None:
        """Task ``index`` (0-based) has finished: nothing of it is offered any more."""
        self.ended.add(index)

    def live(self, task: int) -> bool:
        """Whether task ``task`` (1-based) is still running."""
        return task - 1 not in self.ended and task - 1 == self.task

    def current(self, result: FastResult) -> bool:
        """Whether ``result``'s task is still running."""
        return self.live(result.task)

    def step(self, history: Trajectory) -> tuple[FastResult | None, Path | None]:
        """The fast step on ``history`` (the fast-step thread, under the node's lock: the
        stepper is only touched here); the checkpoint of an accepted fast model, else None."""
        task = int(history.meta["task_index"]) + 1
        if not self.live(task):
            return None, None  # the task ended while this copy waited: nothing to fit for
        if task != self.stepper.task:
            self.stepper.start(task)
        result = self.stepper.observe(history)
        if result is None or not result.accepted or not self.current(result):
            return result, None
        path = self.out_dir / f"fast_t{result.task:04d}_s{result.step:02d}.safetensors"
        meta: dict[str, Any] = fast_meta(self.producer, result.identity(),
                                         fast_result=result.as_dict())
        return result, save_checkpoint(path, self.stepper.model, meta)
