"""CDR bytes of the embedded message classes equal rosbags' (typestore ROS2_JAZZY) bytes.

For every registered message and service request/response type, a message with non-default,
alignment-exercising values is built twice -- as our class and as rosbags' class -- from the same
seeded generator driven by rosbags' own field definitions, then both are serialized and compared
byte for byte; rosbags' bytes are also decoded by our deserializer.
"""

from __future__ import annotations

import importlib.util
import os
import random
import subprocess
import sys
from dataclasses import fields

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

os.environ.setdefault("PEEL_RUNTIME", "dds")

from peel_msgs_py.errors import PeelError
from peel_msgs_py.runtime import msg as rmsg
from peel_msgs_py.runtime.embedded.messages import REGISTRY
from peel_msgs_py.runtime.srv import SetParameters, get_service_class

# Service request/response definitions (Jazzy .srv halves); rosbags' store has messages only.
SRV_DEFS = {
    "rcl_interfaces/srv/SetParameters_Request": "rcl_interfaces/Parameter[] parameters",
    "rcl_interfaces/srv/SetParameters_Response": "rcl_interfaces/SetParametersResult[] results",
    "rcl_interfaces/srv/GetParameters_Request": "string[] names",
    "rcl_interfaces/srv/GetParameters_Response": "rcl_interfaces/ParameterValue[] values",
    "rcl_interfaces/srv/ListParameters_Request": (
        "uint64 DEPTH_RECURSIVE=0\nstring[] prefixes\nuint64 depth"
    ),
    "rcl_interfaces/srv/ListParameters_Response": "rcl_interfaces/ListParametersResult result",
    "rcl_interfaces/srv/DescribeParameters_Request": "string[] names",
    "rcl_interfaces/srv/DescribeParameters_Response": (
        "rcl_interfaces/ParameterDescriptor[] descriptors"
    ),
    # rosidl gives an empty message this placeholder member
    "std_srvs/srv/Trigger_Request": "uint8 structure_needs_at_least_one_member",
    "std_srvs/srv/Trigger_Response": "bool success\nstring message",
}

REQUIRED = [
    "builtin_interfaces/msg/Time",
    "std_msgs/msg/Header",
    "std_msgs/msg/String",
    "std_msgs/msg/Int64",
    "std_msgs/msg/MultiArrayDimension",
    "std_msgs/msg/MultiArrayLayout",
    "std_msgs/msg/Float64MultiArray",
    "geometry_msgs/msg/Vector3",
    "geometry_msgs/msg/Wrench",
    "geometry_msgs/msg/WrenchStamped",
    "geometry_msgs/msg/Twist",
    "geometry_msgs/msg/TwistStamped",
    "geometry_msgs/msg/Point",
    "geometry_msgs/msg/Quaternion",
    "geometry_msgs/msg/Pose",
    "geometry_msgs/msg/PoseStamped",
    "rosgraph_msgs/msg/Clock",
    "rcl_interfaces/msg/Parameter",
    "rcl_interfaces/msg/ParameterValue",
    "rcl_interfaces/msg/ParameterType",
    "rcl_interfaces/msg/SetParametersResult",
    "rcl_interfaces/srv/SetParameters_Request",
    "rcl_interfaces/srv/SetParameters_Response",
]

NUMPY = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "uint8": np.uint8,
    "int8": np.int8,
    "uint16": np.uint16,
    "int16": np.int16,
    "uint32": np.uint32,
    "int32": np.int32,
    "uint64": np.uint64,
    "int64": np.int64,
    "float32": np.float32,
    "float64": np.float64,
}


@pytest.fixture(scope="module")
def store():
    ts = get_typestore(Stores.ROS2_JAZZY)
    names = {}
    for name, text in SRV_DEFS.items():
        pkg, _, typ = name.split("/")
        alias = f"{pkg}/msg/{typ}"  # rosbags wants pkg/msg/Type
        ts.register(get_types_from_msg(text, alias))
        names[name] = alias
    return ts, names


def _value(rng: random.Random, base: str):
    if base == "bool":
        return rng.random() < 0.5
    if base == "string":
        return "".join(rng.choice("abcxyz_/é") for _ in range(rng.randint(0, 7)))
    if base.startswith("float"):
        return round(rng.uniform(-1e3, 1e3), 3)
    bits = int(base.lstrip("uint").lstrip("int") or 8) if base not in ("byte", "char") else 8
    if base.startswith("u") or base in ("byte", "char"):
        return rng.randint(0, 2**bits - 1)
    return rng.randint(-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)


def _build(ts, ros_name: str, store_name: str, rng: random.Random):
    """Return (ours, theirs) for one type, with the same random field values."""
    ours_cls = REGISTRY[ros_name]
    _, defs = ts.fielddefs[store_name]
    ours_kw, theirs_kw = {}, {}
    for fname, (ntype, desc) in defs:
        if ntype == Nodetype.BASE:
            v = _value(rng, desc[0])
            ours_kw[fname] = theirs_kw[fname] = v
        elif ntype == Nodetype.NAME:
            ours_kw[fname], theirs_kw[fname] = _build(ts, desc, desc, rng)
        else:  # sequence or array
            (sub_t, sub_d), bound = desc
            n = rng.randint(0, bound if bound else 3) if ntype == Nodetype.SEQUENCE else bound
            if sub_t == Nodetype.NAME:
                pairs = [_build(ts, sub_d, sub_d, rng) for _ in range(n)]
                ours_kw[fname] = [p[0] for p in pairs]
                theirs_kw[fname] = [p[1] for p in pairs]
            elif sub_d[0] == "string":
                vals = [_value(rng, "string") for _ in range(n)]
                ours_kw[fname], theirs_kw[fname] = vals, list(vals)
            else:
                vals = [_value(rng, sub_d[0]) for _ in range(n)]
                # fixed octet arrays (Gid.data) come back from Cyclone as bytes
                octets = ntype == Nodetype.ARRAY and sub_d[0] in ("char", "byte", "uint8")
                ours_kw[fname] = bytes(vals) if octets else vals
                theirs_kw[fname] = np.array(vals, dtype=NUMPY[sub_d[0]])
    # our field order and names must be rosbags' (= the Jazzy .msg) exactly
    assert [f.name for f in fields(ours_cls)] == [d[0] for d in defs], ros_name
    return ours_cls(**ours_kw), ts.types[store_name](**theirs_kw)


def test_every_required_type_is_provided():
    for name in REQUIRED:
        cls = rmsg.get_message_class(name)
        assert cls.__rostype__ == name
        assert rmsg.ros_type_name(cls()) == name


@pytest.mark.parametrize("ros_name", sorted(REGISTRY))
def test_cdr_bytes_equal_rosbags(store, ros_name):
    ts, srv_alias = store
    store_name = srv_alias.get(ros_name, ros_name)
    rng = random.Random(ros_name)
    for _ in range(4):
        ours, theirs = _build(ts, ros_name, store_name, rng)
        ours_bytes = rmsg.serialize(ours)
        theirs_bytes = bytes(ts.serialize_cdr(theirs, store_name))
        assert ours_bytes == theirs_bytes
        assert ours_bytes[:4] == b"\x00\x01\x00\x00"
        assert rmsg.deserialize(theirs_bytes, ros_name) == ours
    # defaults serialize like rosbags' zero message too (Quaternion.w = 1)
    default = REGISTRY[ros_name]()
    back = ts.deserialize_cdr(rmsg.serialize(default), store_name)
    if ros_name == "geometry_msgs/msg/Quaternion":
        assert back.w == 1.0


def test_nested_defaults_and_field_access():
    w = rmsg.WrenchStamped()
    assert (w.wrench.force.x, w.wrench.torque.z, w.header.frame_id) == (0.0, 0.0, "")
    w.wrench.force.x = 2.5
    assert rmsg.WrenchStamped().wrench.force.x == 0.0  # defaults are not shared
    assert rmsg.PoseStamped().pose.orientation.w == 1.0
    assert rmsg.WrenchStamped.__idl_typename__ == "geometry_msgs::msg::dds_::WrenchStamped_"
    assert SetParameters.__rostype__ == "rcl_interfaces/srv/SetParameters"
    assert SetParameters.Request.__idl_typename__ == (
        "rcl_interfaces::srv::dds_::SetParameters_Request_"
    )


def test_unknown_and_bad_input():
    with pytest.raises(PeelError, match="unknown message type 'geometry_msgs/msg/Nope'"):
        rmsg.get_message_class("geometry_msgs/msg/Nope")
    with pytest.raises(PeelError, match="unknown message type"):
        rmsg.get_message_class("not a type")
    assert rmsg.get_message_class("std_msgs/String") is rmsg.String
    with pytest.raises(PeelError, match="unknown service type"):
        get_service_class("std_srvs/srv/Nope")
    with pytest.raises(PeelError, match="cannot deserialize geometry_msgs/msg/Vector3"):
        rmsg.deserialize(b"\x00\x01\x00\x00\x01", "geometry_msgs/msg/Vector3")
    with pytest.raises(PeelError, match="encapsulation header"):
        rmsg.deserialize(b"", rmsg.Vector3)


def test_backend_selection_in_fresh_processes():
    code = "import peel_msgs_py.runtime as r; print(r.BACKEND)"
    env = dict(os.environ, PEEL_RUNTIME="dds")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.strip() == "dds"
    env["PEEL_RUNTIME"] = "rclpy"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if importlib.util.find_spec("rclpy") is None:
        assert out.returncode != 0
        assert "PEEL_RUNTIME=rclpy but rclpy is not importable" in out.stderr
    else:  # Jazzy's rclpy wheels are installed (requirements.txt)
        assert out.stdout.strip() == "rclpy"
    # automatic: the embedded runtime unless a ROS 2 install is sourced (ROS_DISTRO)
    auto = {k: v for k, v in os.environ.items() if k not in ("PEEL_RUNTIME", "ROS_DISTRO")}
    out = subprocess.run([sys.executable, "-c", code], env=auto, capture_output=True, text=True)
    assert out.stdout.strip() == "dds"
    env["PEEL_RUNTIME"] = "bogus"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert "PEEL_RUNTIME must be 'rclpy' or 'dds'" in out.stderr
