"""ROS 2 message classes for node code, from whichever runtime is selected.

Under rclpy these are the generated Jazzy classes (``geometry_msgs.msg.WrenchStamped`` ...);
under the embedded runtime they are the Cyclone DDS IDL structs of
:mod:`peel_msgs_py.runtime.embedded.messages`, which mirror them field for field. Also here:
:func:`get_message_class` (ROS type name -> class), :func:`serialize` / :func:`deserialize`
(CDR with its 4-byte encapsulation header, as stored in rosbag2 and sent by rmw), and
:func:`ros_type_name` (class or instance -> ``pkg/msg/Type``).
"""

from __future__ import annotations

from typing import Any

from ..errors import PeelError
from ._select import BACKEND, RCLPY

if BACKEND == RCLPY:  # pragma: no cover - exercised only on a ROS 2 machine
    from builtin_interfaces.msg import Duration, Time
    from geometry_msgs.msg import (
        Point,
        Pose,
        PoseStamped,
        Quaternion,
        Twist,
        TwistStamped,
        Vector3,
        Wrench,
        WrenchStamped,
    )
    from rcl_interfaces.msg import (
        FloatingPointRange,
        IntegerRange,
        ListParametersResult,
        Parameter,
        ParameterDescriptor,
        ParameterEvent,
        ParameterType,
        ParameterValue,
        SetParametersResult,
    )
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import (
        Bool,
        Float64,
        Float64MultiArray,
        Header,
        Int64,
        MultiArrayDimension,
        MultiArrayLayout,
        String,
    )
else:
    from .embedded.messages import (
        Bool,
        Clock,
        Duration,
        Float64,
        Float64MultiArray,
        FloatingPointRange,
        Header,
        Int64,
        IntegerRange,
        ListParametersResult,
        MultiArrayDimension,
        MultiArrayLayout,
        Parameter,
        ParameterDescriptor,
        ParameterEvent,
        ParameterType,
        ParameterValue,
        Point,
        Pose,
        PoseStamped,
        Quaternion,
        SetParametersResult,
        String,
        Time,
        Twist,
        TwistStamped,
        Vector3,
        Wrench,
        WrenchStamped,
    )

__all__ = [
    "Bool",
    "Clock",
    "Duration",
    "Float64",
    "Float64MultiArray",
    "FloatingPointRange",
    "Header",
    "Int64",
    "IntegerRange",
    "ListParametersResult",
    "MultiArrayDimension",
    "MultiArrayLayout",
    "Parameter",
    "ParameterDescriptor",
    "ParameterEvent",
    "ParameterType",
    "ParameterValue",
    "Point",
    "Pose",
    "PoseStamped",
    "Quaternion",
    "SetParametersResult",
    "String",
    "Time",
    "Twist",
    "TwistStamped",
    "Vector3",
    "Wrench",
    "WrenchStamped",
    "deserialize",
    "get_message_class",
    "ros_type_name",
    "serialize",
]


def _normalise(name: str) -> str:
    """Accept ``pkg/msg/Type`` and ``pkg/Type``; return ``pkg/msg/Type``."""
    parts = name.strip().split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and all(parts) and parts[1] in ("msg", "srv"):
        return "/".join(parts)
    raise PeelError(f"unknown message type {name!r} (expected 'pkg/msg/Type')")


def get_message_class(name: str) -> type[Any]:
    """The message class for a ROS type name such as ``geometry_msgs/msg/WrenchStamped``.

    Raises :class:`PeelError` ``unknown message type ...`` for a name that is not provided.
    """
    full = _normalise(name)
    if BACKEND == RCLPY:  # pragma: no cover
        try:
            from rosidl_runtime_py.utilities import get_message

            return get_message(full)
        except (AttributeError, ModuleNotFoundError, ValueError):
            raise PeelError(f"unknown message type {name!r}") from None
    from .embedded.messages import REGISTRY

    try:
        return REGISTRY[full]
    except KeyError:
        raise PeelError(f"unknown message type {name!r}") from None


def ros_type_name(msg_or_cls: Any) -> str:
    """``pkg/msg/Type`` of a message class or instance (either runtime)."""
    cls = msg_or_cls if isinstance(msg_or_cls, type) else type(msg_or_cls)
    name = getattr(cls, "__rostype__", None)
    if name:
        return name
    mod = cls.__module__.split(".")  # rclpy: geometry_msgs.msg._wrench_stamped
    if len(mod) >= 2 and mod[1] in ("msg", "srv"):
        return f"{mod[0]}/{mod[1]}/{cls.__name__}"
    raise PeelError(f"{cls.__name__} is not a ROS message class")


def serialize(msg: Any) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header ``00 01 00 00``)."""
    if BACKEND == RCLPY:  # pragma: no cover
        from rclpy.serialization import serialize_message

        return serialize_message(msg)
    from .embedded.cdr import serialize as _ser

    return _ser(msg)


def deserialize(data: bytes | bytearray | memoryview, msg_type: type[Any] | str) -> Any:
    """Inverse of :func:`serialize`; ``msg_type`` is a class or a ROS type name.

    Raises :class:`PeelError` when the bytes are not a valid CDR message of that type.
    """
    cls = get_message_class(msg_type) if isinstance(msg_type, str) else msg_type
    if BACKEND == RCLPY:  # pragma: no cover
        from rclpy.serialization import deserialize_message

        try:
            return deserialize_message(bytes(data), cls)
        except Exception as exc:
            raise PeelError(f"cannot deserialize {ros_type_name(cls)}: {exc}") from None
    from .embedded.cdr import deserialize as _de

    return _de(data, cls)
