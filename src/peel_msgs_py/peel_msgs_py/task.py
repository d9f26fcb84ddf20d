"""One peel task as every package sees it: the seeds of task ``k`` and a measured state sample.

* :func:`task_seed`: the sensor-noise (and, reduced by :func:`mppi_seed`, planner-noise) seed of
  task ``k`` of a seeded run, the one derivation that ``peel experiment``, both plant bridges,
  the controller emulator and the planner node share, so that a graph run and an experiment
  peel the same substrates with the same noise;
* :class:`Sample`: one measured state x_k (section 2) in the paper's units, stamped with its
  ROS time: what a plant bridge publishes on ``/peel/wrench``, ``/peel/twist``, ``/peel/pose``
  and what the planner and the learner reassemble from them (:class:`StateAssembler`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: Leftover incomplete samples kept at most (a lost part never completes its sample).
_MAX_PARTIAL = 50
#: ``mppi.seed`` is kept below 2**31 (:func:`mppi_seed`).
MPPI_SEED_RANGE = 2**31


def task_seed(seed: int, k: int, stream: int = 0) -> int:
    """Noise seed of task ``k`` of the run seeded ``seed``; ``stream`` 0 draws the experiment's
    substrates, 1 the sweep's."""
    return int(np.random.SeedSequence([seed, stream, k]).generate_state(1)[0])


def mppi_seed(seed: int, k: int, stream: int = 0) -> int:
    """``mppi.seed`` of task ``k``: :func:`task_seed` reduced to [0, 2**31)."""
    return task_seed(seed, k, stream) % MPPI_SEED_RANGE


@dataclass(frozen=True)
class Sample:
    """One measured state sample in the paper's units (q mm, v mm/s, F N), stamped with its ROS
    time (integer ns) and the index of its task (frame ``peel_task_<task>``)."""

    stamp_ns: int
    task: int
    q_mm: float
    v_mmps: float
    fx_n: float
    fz_n: float


class StateAssembler:
    """Collects the parts of each stamp; returns the sample when its last part arrives."""

    PARTS = frozenset({"fx_n", "fz_n", "v_mmps", "q_mm"})

    def __init__(self) -> None:
        self.partial: dict[int, dict[str, Any]] = {}

    def add(self, stamp_ns: int, task: int, **parts: float) -> Sample | None:
        """Add ``parts`` (some of q_mm, v_mmps, fx_n, fz_n) of the sample ``stamp_ns``."""
        d = self.partial.setdefault(stamp_ns, {"task": task})
        d.update(parts)
        if not d.keys() >= self.PARTS:
            if len(self.partial) > _MAX_PARTIAL:
                for key in sorted(self.partial)[: -_MAX_PARTIAL // 2]:
                    del self.partial[key]
            return None
        del self.partial[stamp_ns]
        return Sample(stamp_ns, d["task"], d["q_mm"], d["v_mmps"], d["fx_n"], d["fz_n"])
