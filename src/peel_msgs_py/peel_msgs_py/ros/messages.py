"""Messages node code builds: the trajectory as ``std_msgs/msg/Float64MultiArray`` (layout of
:mod:`peel_msgs_py.codec`) and ``builtin_interfaces/msg/Time`` stamps from integer nanoseconds.
"""

from __future__ import annotations

import array
from typing import Any

from builtin_interfaces.msg import Time
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, MultiArrayLayout

from ..codec import trajectory_to_layout
from ..trajectory import Trajectory


def trajectory_msg(traj: Trajectory) -> Float64MultiArray:
    """``traj`` on the wire (SI; layout in :mod:`peel_msgs_py.codec`)."""
    dims, offset, data = trajectory_to_layout(traj)
    layout = MultiArrayLayout(
        dim=[MultiArrayDimension(label=lab, size=size, stride=stride) for lab, size, stride in dims],
        data_offset=offset,
    )
    values = array.array("d")
    values.frombytes(data.astype("<f8").tobytes())
    return Float64MultiArray(layout=layout, data=values)


def stamp(ns: int) -> Time:
    """``builtin_interfaces/msg/Time`` of a ROS time in integer nanoseconds."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=int(sec), nanosec=int(nanosec))


def stamp_ns(time_msg: Any) -> int:
    """Integer nanoseconds of a ``Time`` (exact comparisons of stamps)."""
    return int(time_msg.sec) * 1_000_000_000 + int(time_msg.nanosec)
