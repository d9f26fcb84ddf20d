"""Experience replay of trajectory slices (paper 3.3.1, Fig. 6).

The pool stores *whole* trajectories; a batch is ``n`` fixed-length slices, each cut at a uniformly
random start of a uniformly random trajectory (among those long enough), so a slice never crosses
the end of a trajectory and never joins two of them. Turn slices into model samples with
:func:`peel_model.windows.windows_from_slices`. Sampling uses only the generator passed in,
so a seed fixes the batch.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from peel_model.windows import Windows, padded_arrays, windows_from_slices
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory


@dataclass
class SliceBatch:
    """``n`` slices: states ``[n, L, 4]`` (q, v, fx, fz), psi ``[n, L]``, and where they came from
    (index into :attr:`ReplayPool.trajectories` and start row in the *padded* arrays)."""

    states: np.ndarray
    psi: np.ndarray
    traj_index: np.ndarray
    start: np.ndarray

    def windows(self, h: int) -> Windows:
        """The (L-h) model samples of every slice."""
        return windows_from_slices(self.states, self.psi, h)


class ReplayPool:
    """Replay buffer of whole trajectories (3.3.1).

    ``capacity``: keep at most this many trajectories (oldest dropped first); ``None`` = unbounded.
    ``pad_front``: rows of sample 0 prepended to each stored trajectory (see
    :mod:`peel_model.windows`); offline training uses h-1, the paper's plain pool 0.
    """

    def __init__(
        self,
        trajectories: Iterable[Trajectory] = (),
        *,
        capacity: int | None = None,
        pad_front: int = 0,
    ):
        if capacity is not None and capacity < 1:
            raise PeelError(f"replay pool capacity must be >= 1, got {capacity}")
        if pad_front < 0:
            raise PeelError(f"replay pool pad_front must be >= 0, got {pad_front}")
        self.capacity = capacity
        self.pad_front = pad_front
        self._trajs: deque[Trajectory] = deque()
        self._arrays: deque[tuple[np.ndarray, np.ndarray]] = deque()
        self.extend(trajectories)

    def add(self, traj: Trajectory) -> None:
        """Store one whole trajectory (drops the oldest beyond ``capacity``)."""
        if not isinstance(traj, Trajectory):
            raise PeelError(f"replay pool stores Trajectory objects, got {type(traj).__name__}")
        self._trajs.append(traj)
        self._arrays.append(padded_arrays(traj, self.pad_front))
        while self.capacity is not None and len(self._trajs) > self.capacity:
            self._trajs.popleft()
            self._arrays.popleft()

    def extend(self, trajs: Iterable[Trajectory]) -> None:
        for t in trajs:
            self.add(t)

    def __len__(self) -> int:
        return len(self._trajs)

    @property
    def trajectories(self) -> list[Trajectory]:
        return list(self._trajs)

    def lengths(self) -> np.ndarray:
        """Stored (padded) length of each trajectory."""
        return np.array([a[0].shape[0] for a in self._arrays], dtype=np.int64)

    def n_slices(self, length: int) -> int:
        """Number of distinct slices of ``length`` in the pool."""
        lens = self.lengths()
        return int(np.clip(lens - length + 1, 0, None).sum())

    def sample_slices(self, n: int, length: int, rng: np.random.Generator) -> SliceBatch:
        """``n`` random slices of ``length`` samples (3.3.1, Fig. 6)."""
        if n < 1 or length < 1:
            raise PeelError(f"sample_slices needs n >= 1 and length >= 1, got {n}, {length}")
        lens = self.lengths()
        eligible = np.flatnonzero(lens >= length)
        if eligible.size == 0:
            raise PeelError(
                f"replay pool has no trajectory with at least {length} samples "
                f"({len(self)} stored)"
            )
        idx = eligible[rng.integers(0, eligible.size, size=n)]
        start = rng.integers(0, lens[idx] - length + 1)
        states = np.empty((n, length, 4))
        psi = np.empty((n, length))
        for j, (i, s) in enumerate(zip(idx, start, strict=True)):
            st, ps = self._arrays[i]
            states[j] = st[s : s + length]
            psi[j] = ps[s : s + length]
        return SliceBatch(states=states, psi=psi, traj_index=idx, start=start)
