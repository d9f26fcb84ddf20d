"""The tasks of recorded bags, as trajectories in the paper's units (docs/interfaces.md).

A bag from the simulator bridge or ``peel graph --record`` holds one ``/peel/trajectory`` message
per finished task: those are used as they are. A bag without it (a bridge to the real robot that
publishes only the streams) is rebuilt from ``/peel/wrench``, ``/peel/twist`` and ``/peel/pose``:
samples are joined on their ``header.stamp`` within each task (``header.frame_id`` =
``peel_task_<k>``), t restarts at the task's first sample, and the command u_k is the last
``/peel/cmd_vel`` stamped at or before sample k (NaN before the first, or without the topic).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from peel_bag import bagread
from peel_msgs_py import topics as T
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

STREAMS: tuple[str, ...] = (T.WRENCH, T.TWIST, T.POSE)


def _ns(t_s: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(t_s) * 1e9).astype(np.int64)


def _by_stamp(arr: dict[str, np.ndarray], task: int, key: str) -> dict[int, float]:
    sel = arr["task"] == task
    return dict(zip(_ns(arr["t_s"][sel]).tolist(), arr[key][sel].tolist(), strict=True))


def tasks_from_streams(path: str | os.PathLike[str]) -> list[Trajectory]:
    """Rebuild the tasks of a bag from its state streams (module docstring)."""
    arrays = bagread.read_topics(path, [*STREAMS, T.CMD_VEL])
    missing = [t for t in STREAMS if t not in arrays]
    if missing:
        raise PeelError(f"bag {path}: no messages on {', '.join(missing)}")
    wrench, twist, pose = (arrays[t] for t in STREAMS)
    cmd = arrays.get(T.CMD_VEL)
    out = []
    for task in sorted(set(wrench["task"].tolist()) - {-1}):
        fx = _by_stamp(wrench, task, "fx_n")
        fz = _by_stamp(wrench, task, "fz_n")
        v = _by_stamp(twist, task, "v_mmps")
        q = _by_stamp(pose, task, "q_mm")
        stamps = np.array(sorted(set(fx) & set(v) & set(q)), dtype=np.int64)
        if stamps.size < 2:
            continue
        u = np.full(stamps.size, np.nan)
        if cmd is not None:
            sel = cmd["task"] == task
            c_ns, c_u = _ns(cmd["t_s"][sel]), cmd["u_mmps"][sel]
            order = np.argsort(c_ns, kind="stable")
            c_ns, c_u = c_ns[order], c_u[order]
            idx = np.searchsorted(c_ns, stamps, side="right") - 1
            u[idx >= 0] = c_u[idx[idx >= 0]]
        out.append(Trajectory(
            t=(stamps - stamps[0]) / 1e9, q=[q[s] for s in stamps], v=[v[s] for s in stamps],
            u=u, fx=[fx[s] for s in stamps], fz=[fz[s] for s in stamps],
            psi=np.full(stamps.size, np.nan), outcome="running",
            meta={"task_index": int(task), "rebuilt_from": "streams"}))
    return out


def tasks_from_bag(path: str | os.PathLike[str]) -> list[Trajectory]:
    """The tasks of one bag: its ``/peel/trajectory`` messages, else its rebuilt streams."""
    counts = bagread.topic_names(path)
    if counts.get(T.TRAJECTORY, 0) > 0:
        trajs = bagread.read_trajectories(path)
    elif all(counts.get(t, 0) > 0 for t in STREAMS):
        trajs = tasks_from_streams(path)
    else:
        have = ", ".join(sorted(t for t, n in counts.items() if n > 0)) or "no messages"
        raise PeelError(f"bag {path} has neither {T.TRAJECTORY} nor all of "
                        f"{', '.join(STREAMS)} (it has: {have})")
    for i, tr in enumerate(trajs):
        tr.meta = {**tr.meta, "bag": str(path), "bag_task": i}
    return trajs


def load_tasks(paths: Sequence[str | os.PathLike[str]], *, h: int, dt_s: float,
               min_tasks: int = 4) -> list[Trajectory]:
    """Every usable task of the bags; refuses data the model cannot be run on (PeelError).

    Usable: at least h + 2 samples, finite q, v, F. The sample period must be the model's
    ``dt_s`` (1 % tolerance) in every task."""
    if not paths:
        raise PeelError("no bag given")
    tasks: list[Trajectory] = []
    for path in paths:
        if not Path(path).exists():
            raise PeelError(f"bag {path} does not exist")
        for tr in tasks_from_bag(path):
            if len(tr) < h + 2:
                continue
            if not np.all(np.isfinite(tr.states())):
                raise PeelError(f"bag {path}, task {tr.meta['bag_task']}: non-finite q, v or F")
            if abs(tr.dt - dt_s) > 0.01 * dt_s:
                raise PeelError(f"bag {path}, task {tr.meta['bag_task']}: sampled every "
                                f"{tr.dt:g} s, but the model's inputs are {dt_s:g} s apart")
            tasks.append(tr)
    if len(tasks) < min_tasks:
        raise PeelError(f"the bags hold {len(tasks)} usable task(s) (at least {h + 2} samples "
                        f"each); peel residual needs at least {min_tasks}")
    return tasks
