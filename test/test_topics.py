"""The topic table: names, types, QoS data, and the rclpy QoS profiles built from it."""

from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_typestore

from peel_msgs_py import qos as Q
from peel_msgs_py import topics as T
from peel_msgs_py.errors import PeelError


def test_required_topics_types_and_rates() -> None:
    want = {
        "/peel/wrench": ("geometry_msgs/msg/WrenchStamped", 10.0),
        "/peel/twist": ("geometry_msgs/msg/TwistStamped", 10.0),
        "/peel/pose": ("geometry_msgs/msg/PoseStamped", 10.0),
        "/peel/cmd_vel": ("geometry_msgs/msg/TwistStamped", 2.0),
        "/peel/trajectory": ("std_msgs/msg/Float64MultiArray", None),
        "/peel/model_version": ("std_msgs/msg/Int64", None),
        "/clock": ("rosgraph_msgs/msg/Clock", 10.0),
    }
    for name, (msgtype, rate) in want.items():
        spec = T.topic(name)
        assert (spec.type, spec.rate_hz) == (msgtype, rate), name
    assert T.topic(T.MODEL_VERSION).qos.durability == Q.TRANSIENT_LOCAL
    assert set(T.RECORDED_TOPICS) == set(T.TOPICS)
    assert all(n.startswith("/peel/") or n == "/clock" for n in T.TOPICS)


def test_every_type_is_a_jazzy_type() -> None:
    store = get_typestore(Stores.ROS2_JAZZY)
    for spec in T.TOPICS.values():
        assert spec.type in store.types, spec.type


def test_unknown_topic_names_it() -> None:
    with pytest.raises(PeelError, match="'/peel/nope'"):
        T.topic("/peel/nope")


def test_qos_spec_validation_and_bag_form() -> None:
    with pytest.raises(PeelError, match="reliability"):
        Q.QosSpec(reliability="sometimes")
    with pytest.raises(PeelError, match="depth"):
        Q.QosSpec(depth=-1)
    d = T.LATCHED_QOS.to_bag()
    assert (d["history"], d["depth"], d["reliability"], d["durability"]) == (
        "keep_last", 1, "reliable", "transient_local")
    # the recorder subscribes to /clock best effort (matches any publisher), the rest as offered
    assert T.topic(T.CLOCK).sub_qos.reliability == Q.BEST_EFFORT
    assert T.topic(T.WRENCH).sub_qos == T.STREAM_QOS


def test_rclpy_qos_profile() -> None:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    prof = T.qos_profile(T.MODEL_VERSION)
    assert isinstance(prof, QoSProfile)
    assert prof.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert prof.reliability == ReliabilityPolicy.RELIABLE
    assert prof.history == HistoryPolicy.KEEP_LAST and prof.depth == 1
    sub = T.qos_profile(T.CLOCK, subscriber=True)
    assert sub.reliability == ReliabilityPolicy.BEST_EFFORT


def test_markdown_table_lists_every_topic() -> None:
    table = T.markdown_table()
    for name in T.TOPICS:
        assert f"`{name}`" in table
