"""The model input at the end of a measured history: the last h state rows (Eq. 2).

Shared by every planner dynamics (:mod:`.dynamics`, :mod:`.fused_dynamics`); front-padded as the
model was trained (``peel_model.windows.last_history``).
"""

from __future__ import annotations

import numpy as np

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory


def history_window(history: Trajectory, h: int) -> np.ndarray:
    """The last ``h`` state rows [q, v, fx, fz] of ``history`` (Eq. 2), shape (h, 4).

    A history shorter than h (the first control periods of a task) is padded at the front with
    its first row with v = 0: the blade stood still at C before the task started.
    """
    if len(history) == 0:
        raise PeelError("history 't' is empty: the planner needs at least the sample at t=0")
    rows = history.states()[-h:]
    if not np.all(np.isfinite(rows)):
        raise PeelError("history holds non-finite q, v, fx or fz in its last samples")
    if rows.shape[0] < h:
        first = rows[:1].copy()
        first[0, 1] = 0.0
        rows = np.concatenate([np.repeat(first, h - rows.shape[0], axis=0), rows], axis=0)
    return rows
