"""The samples the residual is computed on: one-step windows and open-loop horizons.

Both are cut from whole tasks exactly as the model sees them in training and in the planner:
the history of the first samples is padded with sample 0 at rest
(:mod:`peel_model.windows`), and the times of the padded rows continue backwards.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from peel_model.windows import padded_arrays, padded_times, trajectory_windows
from peel_msgs_py.trajectory import Trajectory


@dataclass
class Steps:
    """One-step samples (x_k, v_{k+1}) -> F_{k+1} of several tasks (Eq. 1-2).

    ``hist [n, h, 4]`` rows k-h+1..k of (q, v, fx, fz); ``v_next [n]``; ``f_next [n, 2]``;
    ``t_next [n]`` time of sample k+1 in its task (s); ``u [n]`` the command u_k over
    (t_k, t_{k+1}] (NaN where unknown); ``task [n]`` index into the task list; ``k [n]``."""

    hist: np.ndarray
    v_next: np.ndarray
    f_next: np.ndarray
    t_next: np.ndarray
    u: np.ndarray
    task: np.ndarray
    k: np.ndarray

    def __len__(self) -> int:
        return int(self.task.shape[0])

    def subset(self, mask: np.ndarray) -> Steps:
        return Steps(*(getattr(self, f)[mask] for f in
                       ("hist", "v_next", "f_next", "t_next", "u", "task", "k")))


def one_step_samples(tasks: Sequence[Trajectory], h: int) -> Steps:
    """Every one-step sample of every task (k = 0 .. T-2)."""
    parts = []
    for i, tr in enumerate(tasks):
        w = trajectory_windows(tr, h)
        n = len(w)
        t = padded_times(tr, h - 1)
        k = np.arange(n)
        parts.append((w.hist, w.v_next, w.f_next, t[k + h], tr.u[k], np.full(n, i), k))
    cols = [np.concatenate([p[j] for p in parts]) for j in range(7)]
    return Steps(*cols[:5], cols[5].astype(np.int64), cols[6].astype(np.int64))


@dataclass
class Horizons:
    """Open-loop runs of S model steps from every ``stride``-th sample.

    ``rows [n, h+S, 4]``: the measured (q, v, fx, fz) from k-h+1 to k+S (rows past the task's
    end repeat its last row and are masked by ``valid [n, S]``); ``t [n, h+S]`` their times;
    ``u [n, S]`` the commands u_k .. u_{k+S-1}; ``task [n]``, ``k [n]``."""

    rows: np.ndarray
    t: np.ndarray
    u: np.ndarray
    valid: np.ndarray
    task: np.ndarray
    k: np.ndarray

    @property
    def steps(self) -> int:
        return int(self.valid.shape[1])

    def __len__(self) -> int:
        return int(self.task.shape[0])

    def subset(self, mask: np.ndarray) -> Horizons:
        return Horizons(*(getattr(self, f)[mask] for f in
                          ("rows", "t", "u", "valid", "task", "k")))


def horizons(tasks: Sequence[Trajectory], h: int, steps: int, stride: int) -> Horizons:
    """Open-loop runs starting at k = 0, stride, 2 stride, ... (while a next sample exists)."""
    rows, ts, us, valid, task, ks = [], [], [], [], [], []
    for i, tr in enumerate(tasks):
        states, _ = padded_arrays(tr, h - 1)
        times = padded_times(tr, h - 1)
        n_pad = len(states)
        ext = np.concatenate([states, np.repeat(states[-1:], steps, axis=0)])
        t_ext = np.concatenate([times, times[-1] + tr.dt * np.arange(1, steps + 1)])
        u_ext = np.concatenate([tr.u, np.full(steps, np.nan)])
        for k in range(0, len(tr) - 1, stride):
            rows.append(ext[k:k + h + steps])
            ts.append(t_ext[k:k + h + steps])
            us.append(u_ext[k:k + steps])
            valid.append(k + h + np.arange(steps) < n_pad)
            task.append(i)
            ks.append(k)
    return Horizons(np.asarray(rows), np.asarray(ts), np.asarray(us), np.asarray(valid),
                    np.asarray(task, dtype=np.int64), np.asarray(ks, dtype=np.int64))
