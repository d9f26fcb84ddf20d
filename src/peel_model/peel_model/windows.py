"""Training samples (x_k, v_{k+1}, F_{k+1}) cut from trajectories (Eq. 1-2, 4.3).

A *window* is one sample of the forward model: the history rows k-h+1..k of ``[q, v, fx, fz]``
(Eq. 2), the velocity v_{k+1} applied over the next sample, the forces F_{k+1} and the recorded
indentation psi_{k+1}. Windows never mix two trajectories.

Start of a task: a history that would reach before sample 0 is padded with copies of sample 0
with v = 0 (``pad_front``, default h-1 here). Every task starts at rest at point C, so the padded
rows are what the sensors read before the start; the planner pads the same way
(``peel_planner_node.dynamics.history_window``, :func:`last_history`), so the model is trained on
exactly the inputs it sees at the start of a task.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch
from numpy.lib.stride_tricks import sliding_window_view

from peel_msgs_py.trajectory import Trajectory


@dataclass
class Windows:
    """A batch of model samples (NumPy float64 or torch tensors)."""

    hist: np.ndarray  # [N, h, 4]  q_mm, v_mmps, fx_N, fz_N at k-h+1..k
    v_next: np.ndarray  # [N]      v_{k+1}, mm/s
    f_next: np.ndarray  # [N, 2]   fx_N, fz_N at k+1
    psi_next: np.ndarray  # [N]    psi_{k+1}, mm (NaN where unknown)
    t_next: np.ndarray | None = None  # [N] time of sample k+1 in its task, s (time terms only)

    def __len__(self) -> int:
        return int(self.hist.shape[0])

    def to_torch(self, device: str | torch.device = "cpu") -> Windows:
        """Float32 tensors on ``device``."""
        def conv(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32, device=device)

        return Windows(conv(self.hist), conv(self.v_next), conv(self.f_next), conv(self.psi_next),
                       None if self.t_next is None else conv(self.t_next))

    def subset(self, idx: np.ndarray) -> Windows:
        return Windows(self.hist[idx], self.v_next[idx], self.f_next[idx], self.psi_next[idx],
                       None if self.t_next is None else self.t_next[idx])

    def model_kwargs(self, model: object) -> dict:
        """``{"t_next": ...}`` for a model whose terms need the sample times, else ``{}``."""
        if getattr(model, "needs_time", False):
            if self.t_next is None:
                raise ValueError("the model's terms need sample times; these windows have none")
            return {"t_next": self.t_next}
        return {}


def padded_times(traj: Trajectory, pad_front: int) -> np.ndarray:
    """Sample times ``[T+pad]`` matching :func:`padded_arrays`: the padded rows continue the time
    base backwards from t_0 (one sample period each)."""
    dt = traj.dt if len(traj) > 1 and np.isfinite(traj.dt) else 0.1
    t0 = float(traj.t[0]) if len(traj) else 0.0
    front = t0 - dt * np.arange(pad_front, 0, -1)
    return np.concatenate([front, traj.t])


def padded_arrays(traj: Trajectory, pad_front: int) -> tuple[np.ndarray, np.ndarray]:
    """(states ``[T+pad, 4]``, psi ``[T+pad]``) with ``pad_front`` copies of sample 0 in front."""
    states = traj.states()
    psi = traj.psi.copy()
    if pad_front > 0 and len(traj) > 0:
        first = states[:1].copy()
        first[0, 1] = 0.0  # at rest before the start
        states = np.concatenate([np.repeat(first, pad_front, axis=0), states], axis=0)
        psi = np.concatenate([np.repeat(psi[:1], pad_front), psi])
    return states, psi


def windows_from_slices(states: np.ndarray, psi: np.ndarray, h: int) -> Windows:
    """All windows of a batch of slices ``[n, L, 4]`` (L >= h+1): n*(L-h) samples."""
    length = states.shape[1]
    if length < h + 1:
        raise ValueError(f"slice length {length} is shorter than h + 1 = {h + 1}")
    # [n, L-h+1, 4, h+1] -> windows of h+1 consecutive rows
    win = sliding_window_view(states, h + 1, axis=1)[:, : length - h]
    win = np.moveaxis(win, -1, -2).reshape(-1, h + 1, states.shape[2])
    pwin = sliding_window_view(psi, h + 1, axis=1)[:, : length - h].reshape(-1, h + 1)
    return Windows(
        hist=win[:, :h, :].copy(),
        v_next=win[:, h, 1].copy(),
        f_next=win[:, h, 2:4].copy(),
        psi_next=pwin[:, h].copy(),
    )


def trajectory_windows(traj: Trajectory, h: int, pad_front: int | None = None) -> Windows:
    """Every window of one trajectory (k = 0..T-2 with the default ``pad_front = h-1``)."""
    pad = h - 1 if pad_front is None else pad_front
    states, psi = padded_arrays(traj, pad)
    if states.shape[0] < h + 1:
        return Windows(np.zeros((0, h, 4)), np.zeros(0), np.zeros((0, 2)), np.zeros(0))
    return windows_from_slices(states[None], psi[None], h)


def stack_windows(trajs: Iterable[Trajectory], h: int, pad_front: int | None = None) -> Windows:
    """All windows of several trajectories, concatenated in order."""
    parts = [trajectory_windows(t, h, pad_front) for t in trajs]
    parts = [p for p in parts if len(p)]
    if not parts:
        return Windows(np.zeros((0, h, 4)), np.zeros(0), np.zeros((0, 2)), np.zeros(0))
    return Windows(
        np.concatenate([p.hist for p in parts]),
        np.concatenate([p.v_next for p in parts]),
        np.concatenate([p.f_next for p in parts]),
        np.concatenate([p.psi_next for p in parts]),
    )


def last_history(traj: Trajectory, h: int) -> np.ndarray:
    """The model input for the latest sample of ``traj``: ``[h, 4]``, front-padded with sample 0."""
    if len(traj) == 0:
        raise ValueError("trajectory has no samples")
    states = traj.states()[-h:]
    if states.shape[0] < h:
        first = states[:1].copy()
        first[0, 1] = 0.0
        states = np.concatenate([np.repeat(first, h - states.shape[0], axis=0), states])
    return states
