"""Trajectory <-> ``std_msgs/msg/Float64MultiArray`` (``/peel/trajectory``), and wire helpers.

Wire layout of one trajectory of T samples (SI, REP-103; version ``peel.trajectory/1``)::

    layout.dim[0].label  = 'samples {"format": "peel.trajectory/1", "outcome": ..., "params": {...},
                            "meta": {...}}'          # "samples", a space, then one JSON object
    layout.dim[0].size   = T
    layout.dim[0].stride = 7 * T
    layout.dim[1].label  = "t[s],q[m],v[m/s],u[m/s],fx[N],fz[N],psi[m]"
    layout.dim[1].size   = 7
    layout.dim[1].stride = 7
    layout.data_offset   = 0
    data                 = row-major T x 7: sample k occupies data[7k : 7k + 7]

The columns are the fields of :class:`~peel_msgs_py.trajectory.Trajectory` converted to SI with
:mod:`peel_msgs_py.units` (q and psi mm -> m, v and u mm/s -> m/s; t in s and forces in N are
unchanged); NaN (unknown psi) stays NaN. The header JSON carries the ``outcome`` (one of
``done, timeout, safety_stop, aborted, running``), the per-task physical ``params`` verbatim
(their names carry their units, e.g. ``*_mm``; they are not converted) and the provenance
``meta``. A Jazzy user decodes it from ``ros2 topic echo /peel/trajectory`` (or a bag) with::

    header = json.loads(msg.layout.dim[0].label.split(" ", 1)[1])
    rows = numpy.array(msg.data[msg.layout.data_offset:]).reshape(msg.layout.dim[0].size, 7)

The JSON is written by Python's :mod:`json` (``NaN``/``Infinity`` allowed, as Python reads them).
Decoding accepts any object with the ``layout``/``data`` attributes of the message (rclpy, a
``rosbags`` or an ``mcap-ros2-support`` deserialised message).

Also here: the task frame ids (``header.frame_id = peel_task_<k>`` on the stamped topics) and
``builtin_interfaces/Time`` <-> seconds.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

import numpy as np

from . import units
from .errors import PeelError
from .topics import FRAME_PREFIX
from .trajectory import FIELDS, OUTCOMES, Trajectory

#: Version tag in the header JSON.
FORMAT = "peel.trajectory/1"
#: Label of dim[0]; the header JSON follows after one space.
SAMPLES_LABEL = "samples"
#: Label of dim[1]: the columns with their wire units, in :data:`FIELDS` order.
FIELD_LABEL = "t[s],q[m],v[m/s],u[m/s],fx[N],fz[N],psi[m]"
NCOL = len(FIELDS)
_FRAME_RE = re.compile(re.escape(FRAME_PREFIX) + r"(\d+)")

# paper units -> SI, per column (FIELDS order: t, q, v, u, fx, fz, psi)
_TO_SI = {
    "t": lambda x: x,
    "q": units.mm_to_m,
    "v": units.mmps_to_mps,
    "u": units.mmps_to_mps,
    "fx": lambda x: x,
    "fz": lambda x: x,
    "psi": units.mm_to_m,
}
_FROM_SI = {
    "t": lambda x: x,
    "q": units.m_to_mm,
    "v": units.mps_to_mmps,
    "u": units.mps_to_mmps,
    "fx": lambda x: x,
    "fz": lambda x: x,
    "psi": units.m_to_mm,
}


def trajectory_to_layout(traj: Trajectory) -> tuple[list[tuple[str, int, int]], int, np.ndarray]:
    """Wire form as plain data: ``(dims [(label, size, stride)], data_offset, data float64[7T])``."""
    header = {
        "format": FORMAT,
        "outcome": traj.outcome,
        "params": {str(k): float(v) for k, v in traj.params.items()},
        "meta": traj.meta,
    }
    try:
        text = json.dumps(header, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise PeelError(f"trajectory meta is not JSON-serialisable: {exc}") from None
    cols = [np.asarray(_TO_SI[name](getattr(traj, name)), dtype=np.float64) for name in FIELDS]
    data = np.stack(cols, axis=1).reshape(-1) if len(traj) else np.zeros(0)
    n = len(traj)
    dims = [(f"{SAMPLES_LABEL} {text}", n, NCOL * n), (FIELD_LABEL, NCOL, NCOL)]
    return dims, 0, data


def trajectory_from_msg(msg: Any) -> Trajectory:
    """Inverse of :func:`peel_msgs_py.ros.messages.trajectory_msg` (which builds the rclpy
    message from :func:`trajectory_to_layout`) for any message object with ``layout`` and ``data``
    (rclpy's, ``rosbags``', ``mcap-ros2-support``'s).

    Raises :class:`PeelError` naming the offending field when the layout is not ours.
    """
    try:
        dims = list(msg.layout.dim)
        offset = int(msg.layout.data_offset)
        data = np.asarray(msg.data, dtype=np.float64).reshape(-1)
    except (AttributeError, TypeError, ValueError):
        raise PeelError("trajectory message: not a Float64MultiArray") from None
    if len(dims) != 2:
        raise PeelError(f"trajectory message: layout.dim must have 2 entries, got {len(dims)}")
    label0 = str(dims[0].label)
    name, _, text = label0.partition(" ")
    if name != SAMPLES_LABEL or not text:
        raise PeelError(
            f"trajectory message: layout.dim[0].label must start with '{SAMPLES_LABEL} {{'"
        )
    try:
        header = json.loads(text)
    except json.JSONDecodeError:
        raise PeelError("trajectory message: layout.dim[0].label header is not JSON") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        got = header.get("format") if isinstance(header, dict) else None
        raise PeelError(f"trajectory message: header format must be {FORMAT!r}, got {got!r}")
    if str(dims[1].label) != FIELD_LABEL:
        raise PeelError(
            f"trajectory message: layout.dim[1].label must be {FIELD_LABEL!r}, "
            f"got {dims[1].label!r}"
        )
    n = int(dims[0].size)
    if int(dims[1].size) != NCOL or int(dims[1].stride) != NCOL or int(dims[0].stride) != NCOL * n:
        raise PeelError("trajectory message: layout.dim sizes/strides do not describe T x 7")
    if data.shape[0] != offset + NCOL * n:
        raise PeelError(
            f"trajectory message: data has {data.shape[0]} values, layout needs {offset + NCOL * n}"
        )
    outcome = header.get("outcome")
    if outcome not in OUTCOMES:
        raise PeelError(f"trajectory message: outcome {outcome!r} is not one of {OUTCOMES}")
    params = header.get("params", {})
    meta = header.get("meta", {})
    if not isinstance(params, dict) or not isinstance(meta, dict):
        raise PeelError("trajectory message: header params and meta must be JSON objects")
    rows = data[offset:].reshape(n, NCOL)
    cols = {name: np.asarray(_FROM_SI[name](rows[:, i]), dtype=np.float64)
            for i, name in enumerate(FIELDS)}
    try:
        params = {str(k): float(v) for k, v in params.items()}
    except (TypeError, ValueError):
        raise PeelError("trajectory message: header params must be numbers") from None
    return Trajectory(**cols, outcome=outcome, params=params, meta=meta)


# ------------------------------------------------------------------------------- task frame ids
def task_frame_id(task: int) -> str:
    """``header.frame_id`` of the samples of task ``task``: ``peel_task_<k>`` (k >= 0)."""
    if isinstance(task, bool) or not isinstance(task, (int, np.integer)) or task < 0:
        raise PeelError(f"task index must be a non-negative int, got {task!r}")
    return f"{FRAME_PREFIX}{int(task)}"


def task_from_frame_id(frame_id: str) -> int:
    """Inverse of :func:`task_frame_id`; :class:`PeelError` naming the frame id otherwise."""
    m = _FRAME_RE.fullmatch(str(frame_id))
    if m is None:
        raise PeelError(f"header.frame_id {frame_id!r} is not '{FRAME_PREFIX}<task index>'")
    return int(m.group(1))


# ------------------------------------------------------------------------------------ time stamps
def split_stamp(t_s: float) -> tuple[int, int]:
    """Seconds -> ``(sec, nanosec)`` of ``builtin_interfaces/Time`` (nanosec in [0, 1e9))."""
    if not math.isfinite(t_s):
        raise PeelError(f"time stamp must be finite, got {t_s!r}")
    ns = round(t_s * 1e9)
    sec, nanosec = divmod(ns, 1_000_000_000)
    return int(sec), int(nanosec)


def join_stamp(stamp: Any) -> float:
    """``builtin_interfaces/Time`` (any object with ``sec``/``nanosec``) -> seconds."""
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9
