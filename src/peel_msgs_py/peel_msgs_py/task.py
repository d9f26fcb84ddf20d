"""One peel task as every package sees it: the seeds of task ``k`` and a measured state sample.

* :func:`task_seed`: the sensor-noise (and, reduced by :func:`mppi_seed`, planner-noise) seed of
  task ``k`` of a seeded run, the one derivation that ``peel experiment``, both plant bridges,
  the controller emulator and the planner node share, so that a graph run and an experiment
  peel the same substrates with the same noise;
* :class:`Sample`: one measured state x_k (section 2) in the paper's units, stamped with its
  ROS time: what a plant bridge publishes on ``/peel/wrench``, ``/peel/twist``, ``/peel/pose``
  and what the planner reassembles from them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
