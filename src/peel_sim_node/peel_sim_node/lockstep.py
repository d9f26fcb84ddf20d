"""Consecutive peeling tasks on one :class:`~peel_sim_node.env.PeelEnv`, in lockstep with a
planner: the ROS-free core of ``peel_sim_node`` (docs/graph.md, "Time and lockstep").

Task ``i`` occupies ROS time ``[i * task_slot_s, (i + 1) * task_slot_s)``; inside its trajectory
the time restarts at 0 (``t_k = k * dt``, section 4.2). Per control period (5 samples of 0.1 s):

1. the sample at the control instant is published and waits for its command
   (:attr:`TaskSequence.awaiting` holds its stamp);
2. :meth:`TaskSequence.apply` takes the command that answers exactly that stamp, steps the env
   for one control period and returns the new samples, the last of which is the next control
   instant (unless the task ended); each sample's speed is the command after the slowdown zone
   of Eq. M6 (:mod:`peel_bridge.slowdown`), as in ``peel experiment``;
3. :meth:`TaskSequence.finish` closes the task: the trajectory with its provenance ``meta``.

Task ``k``'s physical parameters and noise seed derive from ``(seed, k)`` exactly as in
``peel experiment`` (:func:`peel_msgs_py.task.task_seed`, :func:`task_params`), so both peel
the same substrates.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from peel_bridge.loop import task_stamp_ns, to_ns
from peel_msgs_py.errors import PeelError
from peel_msgs_py.task import Sample, task_seed
from peel_msgs_py.trajectory import Trajectory

from .effects import Effect
from .env import PeelEnv, sample_params


def task_params(cfg: Any, seed: int, k: int, source: str) -> dict[str, float]:
    """Physical parameters of task ``k`` (3.2.1 intervals), as ``peel_experiments.experiment``."""
    return dict(sample_params(cfg, np.random.default_rng([seed, 0, k]), source))


class TaskSequence:
    """The task loop of the simulator bridge, without ROS (module docstring)."""

    def __init__(self, cfg: Any, *, source: str, seed: int, task_slot_s: float,
                 effects: Sequence[Effect] = ()) -> None:
        if task_slot_s <= cfg.task.t_max_s:
            raise PeelError(f"node.task_slot_s = {task_slot_s} must exceed task.t_max_s = "
                            f"{cfg.task.t_max_s}")
        self.cfg, self.source, self.seed = cfg, source, int(seed)
        self.slot_ns = to_ns(task_slot_s)
        self.steps = int(cfg.samples_per_control)
        self.env = PeelEnv(cfg, source=source, seed=task_seed(seed, 0), effects=effects)
        self.zone = cfg.slowdown_zone()  # Eq. M6 on every sample, as run_episode
        self.index = -1  # task running or last finished
        self.awaiting: int | None = None  # stamp (ns) of the sample waiting for its command
        self.running = False

    def sample(self, k: int) -> Sample:
        """Sample ``k`` of the current task."""
        h = self.env.history
        return Sample(task_stamp_ns(self.index, self.slot_ns, float(h.t[k])), self.index,
                      float(h.q[k]), float(h.v[k]), float(h.fx[k]), float(h.fz[k]))

    def last(self) -> Sample:
        return self.sample(len(self.env.history) - 1)

    def start(self, index: int) -> Sample:
        """Reset the env for task ``index``; returns its first sample (a control instant)."""
        self.index = int(index)
        self.env.reset(seed=task_seed(self.seed, index),
                       params=task_params(self.cfg, self.seed, index, self.source))
        self.running = True
        self.zone.reset()
        first = self.last()
        self.awaiting = first.stamp_ns
        return first

    def apply(self, stamp_ns: int, u_mmps: float) -> list[Sample] | None:
        """The command ``u_mmps`` answering the sample ``stamp_ns``: one control period.

        Returns the samples of the period (None for a command that answers no waiting sample,
        e.g. a repeated answer to a re-sent sample). The task may end inside the period.
        """
        if not self.running or stamp_ns != self.awaiting:
            return None
        out = []
        for _ in range(self.steps):
            self.zone.measured(*self.env.last_forces)
            self.env.step(self.zone.speed(u_mmps))
            out.append(self.last())
            if self.env.done:
                break
        self.awaiting = None if self.env.done else out[-1].stamp_ns
        return out

    @property
    def ended(self) -> bool:
        """The running task reached done, timeout or safety_stop."""
        return self.running and self.env.done

    def finish(self, meta: dict[str, Any], outcome: str | None = None) -> Trajectory:
        """Close the task; its trajectory with ``meta`` (``outcome`` overrides, e.g. aborted)."""
        traj = self.env.history
        if outcome is not None:
            traj = traj.slice(0, len(traj))
            traj.outcome = outcome
        traj.meta.update({"source": self.source, "seed": self.seed, "task_index": self.index,
                          "slowdown": self.zone.as_dict(),
                          "task_seed": task_seed(self.seed, self.index),
                          "t0_ros_s": self.index * self.slot_ns / 1e9, **meta})
        self.running = False
        self.awaiting = None
        return traj

    def close(self) -> None:
        self.env.close()
