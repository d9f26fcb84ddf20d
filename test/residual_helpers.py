"""Data for the ``peel residual`` tests: small task sets from PeelEnv, written to real bags."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import ros_msgs as M

from peel_bag.bag import BagWriter
from peel_msgs_py import codec
from peel_msgs_py import topics as T
from peel_msgs_py.ros.messages import trajectory_msg
from peel_msgs_py.trajectory import Trajectory
from peel_msgs_py.units import mm_to_m, mmps_to_mps
from peel_sim_node.config import load_sim_config
from peel_sim_node.episode import exploratory_tasks

T0_NS = 1_700_000_000_000_000_000


def generate_tasks(source: str, effects: Sequence[Callable] = (), n: int = 24, seed: int = 0,
                   u_max: float = 6.0) -> list[Trajectory]:
    """``n`` tasks under exploratory command profiles (0.5 .. u_max mm/s), seeded."""
    return exploratory_tasks(load_sim_config(), source=source, effects=effects, n=n, seed=seed,
                             u_max=u_max)


def _stamped(msg, t_ns: int, task: int):
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
    msg.header.frame_id = codec.task_frame_id(task)
    return msg


def write_bag(path: Path, trajs: Sequence[Trajectory], *, trajectory: bool = True,
              streams: bool = False, slot_s: float = 100.0) -> Path:
    """A rosbag2 MCAP bag written with the project's BagWriter: the tasks as /peel/trajectory
    messages and/or as the 10 Hz state streams (+ /peel/cmd_vel at the control instants)."""
    with BagWriter(path) as bag:
        if trajectory:
            bag.add_topic(T.TRAJECTORY, T.topic(T.TRAJECTORY).type, [T.topic(T.TRAJECTORY).qos])
        if streams:
            for name in (T.WRENCH, T.TWIST, T.POSE, T.CMD_VEL):
                bag.add_topic(name, T.topic(name).type, [T.topic(name).qos])
        log = T0_NS
        for i, tr in enumerate(trajs):
            base = T0_NS + int(i * slot_s * 1e9)
            if streams:
                for k in range(len(tr)):
                    t_ns = base + round(float(tr.t[k]) * 1e9)
                    w = _stamped(M.WrenchStamped(), t_ns, i)
                    w.wrench.force.x, w.wrench.force.z = float(tr.fx[k]), float(tr.fz[k])
                    tw = _stamped(M.TwistStamped(), t_ns, i)
                    tw.twist.linear.x = float(mmps_to_mps(float(tr.v[k])))
                    po = _stamped(M.PoseStamped(), t_ns, i)
                    po.pose.position.x = float(mm_to_m(float(tr.q[k])))
                    log = max(log + 1, t_ns)
                    for name, m in ((T.WRENCH, w), (T.TWIST, tw), (T.POSE, po)):
                        bag.write(name, M.serialize(m), log)
                    if k % 5 == 0 and k < len(tr) - 1:
                        c = _stamped(M.TwistStamped(), t_ns, i)
                        c.twist.linear.x = float(mmps_to_mps(float(tr.u[k])))
                        bag.write(T.CMD_VEL, M.serialize(c), log)
            if trajectory:
                log = max(log + 1, base + round(float(tr.t[-1]) * 1e9) + 1)
                bag.write(T.TRAJECTORY, M.serialize(trajectory_msg(tr)), log)
    return Path(path)


def peel(*args: str, timeout: float = 900) -> subprocess.CompletedProcess[str]:
    """Run the ``peel`` command in a subprocess."""
    return subprocess.run([sys.executable, "-m", "peel_bringup.cli", *args],
                          capture_output=True, text=True, timeout=timeout)
