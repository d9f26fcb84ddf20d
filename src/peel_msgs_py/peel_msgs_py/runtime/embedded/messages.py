"""ROS 2 Jazzy message definitions as Cyclone DDS IDL structs (the embedded runtime's messages).

Each class mirrors its Jazzy ``.msg`` file field for field, in the same order and with the same
CDR types, so the XCDR1 bytes equal what ``rmw_cyclonedds`` (and ``rosbags``) produce, and node
code reads ``msg.wrench.force.x`` on either runtime. The DDS type name is ROS's
``<pkg>::msg::dds_::<Type>_``; ``__rostype__`` holds the ROS name (``geometry_msgs/msg/Vector3``)
used for lookup and bag schemas. Constructors take keyword arguments with rclpy's defaults
(zeros, empty strings and sequences; ``Quaternion.w`` = 1.0 as in its ``.msg``).

Constants (``ParameterType.PARAMETER_DOUBLE``) are plain class attributes, as in rclpy.
"""


from dataclasses import dataclass, field
from typing import Any

import cyclonedds.idl.types as t
from cyclonedds.idl import IdlStruct

#: ROS type name -> class, filled by :func:`_ros`.
REGISTRY: dict[str, type[Any]] = {}


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/Vector3`` -> ``geometry_msgs::msg::dds_::Vector3_`` (ROS convention)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def _ros(ros_type: str):
    """Class decorator: make an IdlStruct a dataclass and register it under its ROS name."""

    def wrap(cls: type[Any]) -> type[Any]:
        cls = dataclass(cls)
        cls.__rostype__ = ros_type
        REGISTRY[ros_type] = cls
        return cls

    return wrap


def _seq() -> Any:
    return field(default_factory=list)


# --------------------------------------------------------------------------- builtin_interfaces
@_ros("builtin_interfaces/msg/Time")
class Time(IdlStruct, typename=dds_type_name("builtin_interfaces/msg/Time")):
    """builtin_interfaces/msg/Time: seconds and nanoseconds since the epoch of its clock."""

    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@_ros("builtin_interfaces/msg/Duration")
class Duration(IdlStruct, typename=dds_type_name("builtin_interfaces/msg/Duration")):
    """builtin_interfaces/msg/Duration."""

    sec: t.int32 = 0
    nanosec: t.uint32 = 0


# ----------------------------------------------------------------------------------- std_msgs
@_ros("std_msgs/msg/Header")
class Header(IdlStruct, typename=dds_type_name("std_msgs/msg/Header")):
    """std_msgs/msg/Header: stamp and frame id."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@_ros("std_msgs/msg/String")
class String(IdlStruct, typename=dds_type_name("std_msgs/msg/String")):
    """std_msgs/msg/String."""

    data: str = ""


@_ros("std_msgs/msg/Int64")
class Int64(IdlStruct, typename=dds_type_name("std_msgs/msg/Int64")):
    """std_msgs/msg/Int64."""

    data: t.int64 = 0


@_ros("std_msgs/msg/Float64")
class Float64(IdlStruct, typename=dds_type_name("std_msgs/msg/Float64")):
    """std_msgs/msg/Float64."""

    data: t.float64 = 0.0


@_ros("std_msgs/msg/Bool")
class Bool(IdlStruct, typename=dds_type_name("std_msgs/msg/Bool")):
    """std_msgs/msg/Bool."""

    data: bool = False


@_ros("std_msgs/msg/MultiArrayDimension")
class MultiArrayDimension(IdlStruct, typename=dds_type_name("std_msgs/msg/MultiArrayDimension")):
    """std_msgs/msg/MultiArrayDimension: label, size and stride of one dimension."""

    label: str = ""
    size: t.uint32 = 0
    stride: t.uint32 = 0


@_ros("std_msgs/msg/MultiArrayLayout")
class MultiArrayLayout(IdlStruct, typename=dds_type_name("std_msgs/msg/MultiArrayLayout")):
    """std_msgs/msg/MultiArrayLayout."""

    dim: t.sequence[MultiArrayDimension] = _seq()
    data_offset: t.uint32 = 0


@_ros("std_msgs/msg/Float64MultiArray")
class Float64MultiArray(IdlStruct, typename=dds_type_name("std_msgs/msg/Float64MultiArray")):
    """std_msgs/msg/Float64MultiArray."""

    layout: MultiArrayLayout = field(default_factory=MultiArrayLayout)
    data: t.sequence[t.float64] = _seq()


# ------------------------------------------------------------------------------ geometry_msgs
@_ros("geometry_msgs/msg/Vector3")
class Vector3(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Vector3")):
    """geometry_msgs/msg/Vector3."""

    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@_ros("geometry_msgs/msg/Point")
class Point(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Point")):
    """geometry_msgs/msg/Point."""

    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@_ros("geometry_msgs/msg/Quaternion")
class Quaternion(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Quaternion")):
    """geometry_msgs/msg/Quaternion (``w`` defaults to 1, as in the Jazzy ``.msg``)."""

    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@_ros("geometry_msgs/msg/Pose")
class Pose(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Pose")):
    """geometry_msgs/msg/Pose."""

    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@_ros("geometry_msgs/msg/PoseStamped")
class PoseStamped(IdlStruct, typename=dds_type_name("geometry_msgs/msg/PoseStamped")):
    """geometry_msgs/msg/PoseStamped."""

    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@_ros("geometry_msgs/msg/Wrench")
class Wrench(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Wrench")):
    """geometry_msgs/msg/Wrench."""

    force: Vector3 = field(default_factory=Vector3)
    torque: Vector3 = field(default_factory=Vector3)


@_ros("geometry_msgs/msg/WrenchStamped")
class WrenchStamped(IdlStruct, typename=dds_type_name("geometry_msgs/msg/WrenchStamped")):
    """geometry_msgs/msg/WrenchStamped."""

    header: Header = field(default_factory=Header)
    wrench: Wrench = field(default_factory=Wrench)


@_ros("geometry_msgs/msg/Twist")
class Twist(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Twist")):
    """geometry_msgs/msg/Twist."""

    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@_ros("geometry_msgs/msg/TwistStamped")
class TwistStamped(IdlStruct, typename=dds_type_name("geometry_msgs/msg/TwistStamped")):
    """geometry_msgs/msg/TwistStamped."""

    header: Header = field(default_factory=Header)
    twist: Twist = field(default_factory=Twist)


# ------------------------------------------------------------------------------ rosgraph_msgs
@_ros("rosgraph_msgs/msg/Clock")
class Clock(IdlStruct, typename=dds_type_name("rosgraph_msgs/msg/Clock")):
    """rosgraph_msgs/msg/Clock: the simulated time published on ``/clock``."""

    clock: Time = field(default_factory=Time)


# ----------------------------------------------------------------------------- rcl_interfaces
@_ros("rcl_interfaces/msg/ParameterType")
class ParameterType(IdlStruct, typename=dds_type_name("rcl_interfaces/msg/ParameterType")):
    """rcl_interfaces/msg/ParameterType: constants only (plus ROS's placeholder member)."""

    structure_needs_at_least_one_member: t.uint8 = 0


ParameterType.PARAMETER_NOT_SET = 0
ParameterType.PARAMETER_BOOL = 1
ParameterType.PARAMETER_INTEGER = 2
ParameterType.PARAMETER_DOUBLE = 3
ParameterType.PARAMETER_STRING = 4
ParameterType.PARAMETER_BYTE_ARRAY = 5
ParameterType.PARAMETER_BOOL_ARRAY = 6
ParameterType.PARAMETER_INTEGER_ARRAY = 7
ParameterType.PARAMETER_DOUBLE_ARRAY = 8
ParameterType.PARAMETER_STRING_ARRAY = 9


@_ros("rcl_interfaces/msg/ParameterValue")
class ParameterValue(IdlStruct, typename=dds_type_name("rcl_interfaces/msg/ParameterValue")):
    """rcl_interfaces/msg/ParameterValue: a tagged union, ``type`` picks the valid field."""

    type: t.uint8 = 0
    bool_value: bool = False
    integer_value: t.int64 = 0
    double_value: t.float64 = 0.0
    string_value: str = ""
    byte_array_value: t.sequence[t.uint8] = _seq()
    bool_array_value: t.sequence[bool] = _seq()
    integer_array_value: t.sequence[t.int64] = _seq()
    double_array_value: t.sequence[t.float64] = _seq()
    string_array_value: t.sequence[str] = _seq()


@_ros("rcl_interfaces/msg/Parameter")
class Parameter(IdlStruct, typename=dds_type_name("rcl_interfaces/msg/Parameter")):
    """rcl_interfaces/msg/Parameter (the message; the node-side class is runtime.Parameter)."""

    name: str = ""
    value: ParameterValue = field(default_factory=ParameterValue)


@_ros("rcl_interfaces/msg/SetParametersResult")
class SetParametersResult(
    IdlStruct, typename=dds_type_name("rcl_interfaces/msg/SetParametersResult")
):
    """rcl_interfaces/msg/SetParametersResult: accepted or refused, with the reason."""

    successful: bool = False
    reason: str = ""


@_ros("rcl_interfaces/msg/FloatingPointRange")
class FloatingPointRange(IdlStruct, typename=dds_type_name("rcl_interfaces/msg/FloatingPointRange")):
    """rcl_interfaces/msg/FloatingPointRange (inclusive bounds; step 0 = continuous)."""

    from_value: t.float64 = 0.0
    to_value: t.float64 = 0.0
    step: t.float64 = 0.0


@_ros("rcl_interfaces/msg/IntegerRange")
class IntegerRange(IdlStruct, typename=dds_type_name("rcl_interfaces/msg/IntegerRange")):
    """rcl_interfaces/msg/IntegerRange (inclusive bounds; step 0 = any integer)."""

    from_value: t.int64 = 0
    to_value: t.int64 = 0
    step: t.uint64 = 0


@_ros("rcl_interfaces/msg/ParameterDescriptor")
class ParameterDescriptor(
    IdlStruct, typename=dds_type_name("rcl_interfaces/msg/ParameterDescriptor")
):
    """rcl_interfaces/msg/ParameterDescriptor (ranges are bounded sequences of at most 1)."""

    name: str = ""
    type: t.uint8 = 0
    description: str = ""
    additional_constraints: str = ""
    read_only: bool = False
    dynamic_typing: bool = False
    floating_point_range: t.sequence[FloatingPointRange, 1] = _seq()
    integer_range: t.sequence[IntegerRange, 1] = _seq()


@_ros("rcl_interfaces/msg/ListParametersResult")
class ListParametersResult(
    IdlStruct, typename=dds_type_name("rcl_interfaces/msg/ListParametersResult")
):
    """rcl_interfaces/msg/ListParametersResult."""

    names: t.sequence[str] = _seq()
    prefixes: t.sequence[str] = _seq()


@_ros("rcl_interfaces/msg/ParameterEvent")
class ParameterEvent(IdlStruct, typename=dds_type_name("rcl_interfaces/msg/ParameterEvent")):
    """rcl_interfaces/msg/ParameterEvent: published on ``/parameter_events``."""

    stamp: Time = field(default_factory=Time)
    node: str = ""
    new_parameters: t.sequence[Parameter] = _seq()
    changed_parameters: t.sequence[Parameter] = _seq()
    deleted_parameters: t.sequence[Parameter] = _seq()


# ----------------------------------------------------------------------------- rmw_dds_common
@_ros("rmw_dds_common/msg/Gid")
class Gid(IdlStruct, typename=dds_type_name("rmw_dds_common/msg/Gid")):
    """rmw_dds_common/msg/Gid (Jazzy: ``char[16] data``, the entity's DDS GUID)."""

    data: t.array[t.uint8, 16] = bytes(16)


@_ros("rmw_dds_common/msg/NodeEntitiesInfo")
class NodeEntitiesInfo(IdlStruct, typename=dds_type_name("rmw_dds_common/msg/NodeEntitiesInfo")):
    """rmw_dds_common/msg/NodeEntitiesInfo: a node and the GUIDs of its readers and writers."""

    node_namespace: str = ""
    node_name: str = ""
    reader_gid_seq: t.sequence[Gid] = _seq()
    writer_gid_seq: t.sequence[Gid] = _seq()


@_ros("rmw_dds_common/msg/ParticipantEntitiesInfo")
class ParticipantEntitiesInfo(
    IdlStruct, typename=dds_type_name("rmw_dds_common/msg/ParticipantEntitiesInfo")
):
    """rmw_dds_common/msg/ParticipantEntitiesInfo, published on ``ros_discovery_info``."""

    gid: Gid = field(default_factory=Gid)
    node_entities_info_seq: t.sequence[NodeEntitiesInfo] = _seq()


# ----------------------------------------------------------------------- service req/response
@_ros("rcl_interfaces/srv/SetParameters_Request")
class SetParameters_Request(
    IdlStruct, typename=dds_type_name("rcl_interfaces/srv/SetParameters_Request")
):
    """rcl_interfaces/srv/SetParameters request."""

    parameters: t.sequence[Parameter] = _seq()


@_ros("rcl_interfaces/srv/SetParameters_Response")
class SetParameters_Response(
    IdlStruct, typename=dds_type_name("rcl_interfaces/srv/SetParameters_Response")
):
    """rcl_interfaces/srv/SetParameters response: one result per requested parameter."""

    results: t.sequence[SetParametersResult] = _seq()


@_ros("rcl_interfaces/srv/GetParameters_Request")
class GetParameters_Request(
    IdlStruct, typename=dds_type_name("rcl_interfaces/srv/GetParameters_Request")
):
    """rcl_interfaces/srv/GetParameters request."""

    names: t.sequence[str] = _seq()


@_ros("rcl_interfaces/srv/GetParameters_Response")
class GetParameters_Response(
    IdlStruct, typename=dds_type_name("rcl_interfaces/srv/GetParameters_Response")
):
    """rcl_interfaces/srv/GetParameters response (PARAMETER_NOT_SET for unknown names)."""

    values: t.sequence[ParameterValue] = _seq()


@_ros("rcl_interfaces/srv/ListParameters_Request")
class ListParameters_Request(
    IdlStruct, typename=dds_type_name("rcl_interfaces/srv/ListParameters_Request")
):
    """rcl_interfaces/srv/ListParameters request."""

    prefixes: t.sequence[str] = _seq()
    depth: t.uint64 = 0


ListParameters_Request.DEPTH_RECURSIVE = 0


@_ros("rcl_interfaces/srv/ListParameters_Response")
class ListParameters_Response(
    IdlStruct, typename=dds_type_name("rcl_interfaces/srv/ListParameters_Response")
):
    """rcl_interfaces/srv/ListParameters response."""

    result: ListParametersResult = field(default_factory=ListParametersResult)


@_ros("rcl_interfaces/srv/DescribeParameters_Request")
class DescribeParameters_Request(
    IdlStruct, typename=dds_type_name("rcl_interfaces/srv/DescribeParameters_Request")
):
    """rcl_interfaces/srv/DescribeParameters request."""

    names: t.sequence[str] = _seq()


@_ros("rcl_interfaces/srv/DescribeParameters_Response")
class DescribeParameters_Response(
    IdlStruct, typename=dds_type_name("rcl_interfaces/srv/DescribeParameters_Response")
):
    """rcl_interfaces/srv/DescribeParameters response."""

    descriptors: t.sequence[ParameterDescriptor] = _seq()


@_ros("std_srvs/srv/Trigger_Request")
class Trigger_Request(
    IdlStruct, typename=dds_type_name("std_srvs/srv/Trigger_Request")
):
    """std_srvs/srv/Trigger request (empty: ROS's placeholder member)."""

    structure_needs_at_least_one_member: t.uint8 = 0


@_ros("std_srvs/srv/Trigger_Response")
class Trigger_Response(
    IdlStruct, typename=dds_type_name("std_srvs/srv/Trigger_Response")
):
    """std_srvs/srv/Trigger response."""

    success: bool = False
    message: str = ""


# ----------------------------------------------------------------------------- service classes
class _ServiceType:
    """A service type as rclpy exposes it: ``Srv.Request``, ``Srv.Response``, ``__rostype__``."""

    Request: type[Any]
    Response: type[Any]
    __rostype__: str


#: ROS service name -> service class.
SERVICE_REGISTRY: dict[str, type[_ServiceType]] = {}


def _service(ros_type: str) -> type[_ServiceType]:
    name = ros_type.rsplit("/", 1)[1]
    cls = type(
        name,
        (_ServiceType,),
        {
            "Request": REGISTRY[f"{ros_type}_Request"],
            "Response": REGISTRY[f"{ros_type}_Response"],
            "__rostype__": ros_type,
            "__doc__": f"{ros_type}: ``Request`` and ``Response`` message classes.",
            "__module__": __name__,
        },
    )
    SERVICE_REGISTRY[ros_type] = cls
    return cls


SetParameters = _service("rcl_interfaces/srv/SetParameters")
GetParameters = _service("rcl_interfaces/srv/GetParameters")
ListParameters = _service("rcl_interfaces/srv/ListParameters")
DescribeParameters = _service("rcl_interfaces/srv/DescribeParameters")
Trigger = _service("std_srvs/srv/Trigger")
