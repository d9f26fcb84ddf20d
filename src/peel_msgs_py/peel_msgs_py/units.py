"""Unit conversion between the wire (SI, REP-103) and the algorithms (the paper's units).

This is the *only* place where millimetres become metres. On the wire (topics, bags) positions
are in m, velocities in m/s, forces in N and time in s. The algorithms (simulator, model,
planner) work in the paper's units: q in mm, v and u in mm/s, forces in N, time in s
(paper section 4.1: q_ter = 25 mm; Eq. 20 takes v in mm/s).
"""

from __future__ import annotations

import numpy as np

MM_PER_M: float = 1000.0


def mm_to_m(x: float | np.ndarray) -> float | np.ndarray:
    """Position (mm, algorithms) -> position (m, wire)."""
    return x / MM_PER_M


def m_to_mm(x: float | np.ndarray) -> float | np.ndarray:
    """Position (m, wire) -> position (mm, algorithms)."""
    return x * MM_PER_M


def mmps_to_mps(x: float | np.ndarray) -> float | np.ndarray:
    """Velocity (mm/s, algorithms) -> velocity (m/s, wire)."""
    return x / MM_PER_M


def mps_to_mmps(x: float | np.ndarray) -> float | np.ndarray:
    """Velocity (m/s, wire) -> velocity (mm/s, algorithms)."""
    return x * MM_PER_M
