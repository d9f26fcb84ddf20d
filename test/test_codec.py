"""Trajectory <-> Float64MultiArray codec: round trip, SI on the wire, byte-level agreement."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import Float64MultiArray

from peel_msgs_py import codec
from peel_msgs_py.errors import PeelError
from peel_msgs_py.ros.messages import trajectory_msg
from peel_msgs_py.trajectory import Trajectory


def _traj(n: int = 40, seed: int = 3) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    q = np.linspace(0.0, 25.0, n)
    v = np.r_[0.0, np.diff(q) / 0.1]
    psi = rng.uniform(0.0, 0.3, n)
    psi[:3] = np.nan
    return Trajectory(t=t, q=q, v=v, u=rng.uniform(0, 10, n), fx=rng.normal(5, 1, n),
                      fz=rng.normal(-2, 1, n), psi=psi, outcome="done",
                      params={"k_pad_n_per_mm": 1.25, "mu": 0.3},
                      meta={"source": "sim", "seed": seed, "ids": [1, 2]})


def _same(a: Trajectory, b: Trajectory) -> None:
    for name in ("t", "q", "v", "u", "fx", "fz", "psi"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-15, atol=0,
                                   equal_nan=True, err_msg=name)
    assert (a.outcome, a.params, a.meta) == (b.outcome, b.params, b.meta)


def test_round_trip_through_rclpy_message_and_cdr() -> None:
    traj = _traj()
    msg = trajectory_msg(traj)
    assert isinstance(msg, Float64MultiArray)
    _same(codec.trajectory_from_msg(msg), traj)
    back = deserialize_message(serialize_message(msg), Float64MultiArray)
    _same(codec.trajectory_from_msg(back), traj)


def test_si_on_the_wire() -> None:
    traj = _traj()
    dims, offset, data = codec.trajectory_to_layout(traj)
    rows = data[offset:].reshape(dims[0][1], 7)
    assert rows[-1, 1] == 0.025  # q = 25 mm -> 0.025 m
    np.testing.assert_allclose(rows[:, 2], traj.v / 1000.0, rtol=1e-15)  # mm/s -> m/s
    np.testing.assert_array_equal(rows[:, 4], traj.fx)  # N stays N
    np.testing.assert_array_equal(rows[:, 0], traj.t)  # s stays s
    assert dims[1] == ("t[s],q[m],v[m/s],u[m/s],fx[N],fz[N],psi[m]", 7, 7)


def test_jazzy_user_decoding_recipe_on_rosbags_message() -> None:
    """A rosbags-deserialised message decodes with the documented two-line recipe and ours."""
    traj = _traj(12)
    raw = serialize_message(trajectory_msg(traj))
    store = get_typestore(Stores.ROS2_JAZZY)
    msg = store.deserialize_cdr(raw, "std_msgs/msg/Float64MultiArray")
    header = json.loads(msg.layout.dim[0].label.split(" ", 1)[1])
    rows = np.array(msg.data[msg.layout.data_offset:]).reshape(msg.layout.dim[0].size, 7)
    assert header["outcome"] == "done" and header["params"]["mu"] == 0.3
    assert rows.shape == (12, 7) and rows[-1, 1] == 0.025
    _same(codec.trajectory_from_msg(msg), traj)


def test_empty_trajectory_round_trips() -> None:
    empty = Trajectory(*(np.zeros(0) for _ in range(7)), outcome="aborted")
    back = codec.trajectory_from_msg(trajectory_msg(empty))
    assert len(back) == 0 and back.outcome == "aborted"


def test_bad_messages_name_the_field() -> None:
    msg = trajectory_msg(_traj(5))
    msg.layout.dim[1].label = "t,q"
    with pytest.raises(PeelError, match=r"dim\[1\]\.label"):
        codec.trajectory_from_msg(msg)
    msg = trajectory_msg(_traj(5))
    msg.data = msg.data[:-1]
    with pytest.raises(PeelError, match="data has 34 values"):
        codec.trajectory_from_msg(msg)
    msg = trajectory_msg(_traj(5))
    msg.layout.dim[0].label = "samples {not json"
    with pytest.raises(PeelError, match=r"dim\[0\]\.label header is not JSON"):
        codec.trajectory_from_msg(msg)
    with pytest.raises(PeelError, match="not JSON-serialisable"):
        codec.trajectory_to_layout(Trajectory(*(np.zeros(1) for _ in range(7)),
                                              meta={"x": object()}))


def test_task_frame_ids_and_stamps() -> None:
    assert codec.task_frame_id(7) == "peel_task_7"
    assert codec.task_from_frame_id(codec.task_frame_id(12)) == 12
    for bad in ("peel_c", "peel_task_", "peel_task_-1", "peel_task_3x"):
        with pytest.raises(PeelError, match="frame_id"):
            codec.task_from_frame_id(bad)
    with pytest.raises(PeelError, match="task index"):
        codec.task_frame_id(-1)
    assert codec.split_stamp(12.3) == (12, 300_000_000)
    assert codec.split_stamp(-0.5) == (-1, 500_000_000)

    class Stamp:
        sec, nanosec = 12, 300_000_000

    assert codec.join_stamp(Stamp()) == pytest.approx(12.3, abs=1e-12)
