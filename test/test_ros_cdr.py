"""rclpy's CDR is rosbags' CDR: ``rclpy.serialization.serialize_message`` bytes equal
``rosbags``' serializer (Jazzy typestore) for every message type the project publishes (and the
SetParameters result it answers with), with non-default values in the fields we use, and each
decodes the other's bytes.

One difference is allowed, and checked to be only that: Fast CDR (rclpy's serializer) leaves
the alignment padding after a string uninitialised, where rosbags writes zeros; the CDR
specification leaves padding unspecified. Every byte that differs must be one that no decoder
reads: putting rclpy's byte into rosbags' bytes decodes to the same message.
"""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore

from peel_bag.recorder_node import message_class
from peel_msgs_py import codec, topics
from peel_msgs_py.ros.messages import stamp, trajectory_msg
from peel_msgs_py.trajectory import Trajectory

STORE = get_typestore(Stores.ROS2_JAZZY)


def _trajectory_msg():
    traj = Trajectory(t=np.arange(5) * 0.1, q=[0, 1, 2, 3, 4.0], v=[0, 10, 10, 10, 10.0],
                      u=[10.0] * 5, fx=[1, 2, 3, 4, 5.0], fz=[0, -1, -2, -3, -4.0],
                      psi=[np.nan, 0.1, 0.2, 0.3, 0.4], outcome="done", params={"mu": 0.3},
                      meta={"task_index": 2, "note": "äö"})
    return trajectory_msg(traj)


def _stamped(cls, **fields):
    msg = cls(**fields)
    msg.header.stamp = stamp(123_456_789_012)
    msg.header.frame_id = codec.task_frame_id(7)
    return msg


def _examples() -> dict[str, object]:
    from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
    from rcl_interfaces.msg import SetParametersResult
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import Int64, String

    from peel_msgs_py.modelinfo import FAILED, ModelRecord, UpdateReport

    wrench = _stamped(WrenchStamped)
    wrench.wrench.force.x, wrench.wrench.force.z, wrench.wrench.torque.y = 12.5, -3.25, 1e-9
    twist = _stamped(TwistStamped)
    twist.twist.linear.x, twist.twist.angular.z = 0.0042, -1.5
    pose = _stamped(PoseStamped)
    pose.pose.position.x, pose.pose.orientation.w = 0.0251, 0.5
    return {
        "geometry_msgs/msg/WrenchStamped": wrench,
        "geometry_msgs/msg/TwistStamped": twist,
        "geometry_msgs/msg/PoseStamped": pose,
        "std_msgs/msg/Float64MultiArray": _trajectory_msg(),
        "std_msgs/msg/Int64": Int64(data=-(2**40)),
        "std_msgs/msg/String": String(data=ModelRecord(
            3, "ab" * 32, "/tmp/model_v0002.safetensors", "/model_learner_node", 2).to_json()
            + UpdateReport("/model_learner_node", 4, FAILED, "non-finite: äö").to_json()),
        "rosgraph_msgs/msg/Clock": Clock(clock=stamp(5_000_000_001)),
        "rcl_interfaces/msg/SetParametersResult": SetParametersResult(
            successful=False, reason="model swap refused: probe batch"),
    }


def test_every_published_type_is_covered() -> None:
    assert {t.type for t in topics.TOPICS.values()} <= set(_examples())


def _same_decoding(a: bytes, b: bytes, name: str) -> bool:
    return bytes(STORE.serialize_cdr(STORE.deserialize_cdr(a, name), name)) == \
        bytes(STORE.serialize_cdr(STORE.deserialize_cdr(b, name), name))


@pytest.mark.parametrize("name", sorted(_examples()))
def test_rclpy_bytes_equal_rosbags_bytes(name: str) -> None:
    msg = _examples()[name]
    ours = serialize_message(msg)
    assert ours[:4] == b"\x00\x01\x00\x00"  # CDR little endian encapsulation header
    theirs = bytes(STORE.serialize_cdr(STORE.deserialize_cdr(ours, name), name))
    assert len(theirs) == len(ours)
    differ = [i for i in range(len(ours)) if ours[i] != theirs[i]]
    for i in differ:  # padding only: a byte no decoder reads
        assert theirs[i] == 0, (name, i)
        patched = theirs[:i] + ours[i:i + 1] + theirs[i + 1:]
        assert _same_decoding(patched, theirs, name), (name, i)
    back = deserialize_message(theirs, type(msg))  # rclpy reads rosbags' bytes
    if name == "std_msgs/msg/Float64MultiArray":  # NaN != NaN: compare decoded content
        assert codec.trajectory_from_msg(back).meta["note"] == "äö"
        assert serialize_message(back)[4:] == theirs[4:] or _same_decoding(
            serialize_message(back), theirs, name)
    else:
        assert back == msg


def test_recorder_resolves_the_generated_classes() -> None:
    for spec in topics.TOPICS.values():
        cls = message_class(spec.type)
        assert f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}" == spec.type
