"""Read peel bags with ``rosbags``: per-topic arrays in the paper's units, and the trajectories.

Used by ``peel train --from-bags`` and the graph tests. Everything here goes through ``rosbags``'
own rosbag2 reader and its Jazzy typestore, so it reads any rosbag2 bag (MCAP or SQLite) that
holds our topics, including bags recorded by ``ros2 bag record`` on a Jazzy machine.

:func:`read_topics` returns, per topic, a dict of equal-length numpy arrays; wire SI values are
converted to the algorithms' units with :mod:`peel_msgs_py.units` (names carry the unit):

==========================  ============================================================
topic                       arrays
==========================  ============================================================
``/peel/wrench``            ``log_ns``, ``t_s`` (header stamp), ``task``, ``fx_n``, ``fz_n``
``/peel/twist``             ``log_ns``, ``t_s``, ``task``, ``v_mmps``
``/peel/pose``              ``log_ns``, ``t_s``, ``task``, ``q_mm``
``/peel/cmd_vel``           ``log_ns``, ``t_s``, ``task``, ``u_mmps``
``/peel/model_version``     ``log_ns``, ``version``
``/clock``                  ``log_ns``, ``t_s``
``/peel/trajectory``        ``log_ns``, ``samples`` (use :func:`read_trajectories`)
==========================  ============================================================

``log_ns`` is the recorder's receive time (ns since the epoch); ``task`` is the task index from
``header.frame_id`` (``peel_task_<k>``), -1 where the frame id is not of that form. A bag whose recorder was killed
has no MCAP summary; opening it raises :class:`PeelError` pointing at ``peel record --repair``
unless ``repair=True`` is passed (which runs :func:`peel_bag.bagrepair.repair_bag` first).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py import topics as T
from peel_msgs_py import units
from peel_msgs_py.codec import join_stamp, task_from_frame_id, trajectory_from_msg
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .bag import mcap_is_complete, mcap_path, typestore
from .bagrepair import repair_bag


def _check(path: Path, repair: bool) -> None:
    if not path.is_dir() or not (path / "metadata.yaml").is_file():
        raise PeelError(f"bag {path}: not a rosbag2 directory with metadata.yaml")
    try:
        mcap = mcap_path(path)
    except PeelError:
        return  # not an MCAP bag (sqlite3): let rosbags read it
    if not mcap_is_complete(mcap):
        if not repair:
            raise PeelError(
                f"bag {path} is incomplete (recorder killed?); run 'peel record --repair {path}'"
            )
        repair_bag(path)


def iter_messages(
    path: str | os.PathLike[str], topics: Iterable[str] | None = None, *, repair: bool = False
) -> Iterator[tuple[str, str, int, Any]]:
    """Yield ``(topic, msgtype, log_time_ns, message)`` in log-time order (rosbags messages)."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    bag = Path(path)
    _check(bag, repair)
    store = typestore()
    wanted = None if topics is None else set(topics)
    try:
        with Reader(bag) as reader:
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
            for conn, t_ns, raw in reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, int(t_ns), store.deserialize_cdr(raw, conn.msgtype)
    except ReaderError as exc:
        raise PeelError(f"bag {bag}: {exc}") from None


def topic_names(path: str | os.PathLike[str], *, repair: bool = False) -> dict[str, int]:
    """``{topic: message count}`` of a bag (same checks as :func:`iter_messages`)."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    bag = Path(path)
    _check(bag, repair)
    try:
        with Reader(bag) as reader:
            counts: dict[str, int] = {}
            for conn in reader.connections:
                counts[conn.topic] = counts.get(conn.topic, 0) + int(conn.msgcount)
            return counts
    except ReaderError as exc:
        raise PeelError(f"bag {bag}: {exc}") from None


def _task(frame_id: str) -> int:
    try:
        return task_from_frame_id(frame_id)
    except PeelError:
        return -1


def _rows(topic: str, msg: Any) -> dict[str, Any]:
    if topic in (T.WRENCH, T.TWIST, T.POSE, T.CMD_VEL):
        row = {"t_s": join_stamp(msg.header.stamp), "task": _task(msg.header.frame_id)}
        if topic == T.WRENCH:
            row.update(fx_n=msg.wrench.force.x, fz_n=msg.wrench.force.z)
        elif topic == T.POSE:
            row["q_mm"] = units.m_to_mm(msg.pose.position.x)
        else:
            key = "v_mmps" if topic == T.TWIST else "u_mmps"
            row[key] = units.mps_to_mmps(msg.twist.linear.x)
        return row
    if topic == T.MODEL_VERSION:
        return {"version": int(msg.data)}
    if topic == T.CLOCK:
        return {"t_s": join_stamp(msg.clock)}
    if topic == T.TRAJECTORY:
        return {"samples": int(msg.layout.dim[0].size) if len(msg.layout.dim) else 0}
    return {}


def read_topics(
    path: str | os.PathLike[str], topics: Iterable[str] | None = None, *, repair: bool = False
) -> dict[str, dict[str, np.ndarray]]:
    """Per-topic arrays (table in the module docstring); unknown topics get ``log_ns`` only."""
    cols: dict[str, dict[str, list[Any]]] = {}
    for topic, _, t_ns, msg in iter_messages(path, topics, repair=repair):
        row = {"log_ns": t_ns, **_rows(topic, msg)}
        dst = cols.setdefault(topic, {k: [] for k in row})
        for k, v in row.items():
            dst[k].append(v)
    out: dict[str, dict[str, np.ndarray]] = {}
    for topic, d in cols.items():
        out[topic] = {
            k: np.asarray(v, dtype=np.int64 if k in ("log_ns", "version", "task", "samples")
                          else np.float64)
            for k, v in d.items()
        }
    return out


def read_trajectories(
    path: str | os.PathLike[str], *, repair: bool = False, topic: str = T.TRAJECTORY
) -> list[Trajectory]:
    """Every ``/peel/trajectory`` message of the bag decoded with :mod:`peel_msgs_py.codec`."""
    return [trajectory_from_msg(msg) for _, _, _, msg in iter_messages(path, [topic], repair=repair)]
