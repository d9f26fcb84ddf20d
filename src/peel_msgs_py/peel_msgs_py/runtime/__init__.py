"""The ROS 2 runtime node code imports: real rclpy where available, else the embedded one.

    from peel_msgs_py.runtime import rclpy, Node, Parameter, SetParametersResult
    from peel_msgs_py.runtime.msg import WrenchStamped
    from peel_msgs_py.runtime.qos import QoSProfile
    from peel_msgs_py.runtime.srv import SetParameters

``BACKEND`` says which one is in use (``"rclpy"`` or ``"dds"``); see :mod:`._select` and
docs/runtime.md for the selection rules (``PEEL_RUNTIME=rclpy|dds``). Everything exported here
has the same name and signature under both backends.
"""

from __future__ import annotations

from ._select import BACKEND, DDS, RCLPY, choose_backend

if BACKEND == RCLPY:  # pragma: no cover - exercised only on a ROS 2 machine
    import rclpy
    from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
    from rclpy.clock import Clock, ClockType
    from rclpy.duration import Duration
    from rclpy.exceptions import (
        InvalidParameterTypeException,
        InvalidParameterValueException,
        ParameterAlreadyDeclaredException,
        ParameterNotDeclaredException,
    )
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.task import Future
    from rclpy.time import Time
    from rclpy.utilities import remove_ros_args
else:
    from .embedded import rclpy_api as rclpy
    from .embedded.args import remove_ros_args
    from .embedded.context import ExternalShutdownException
    from .embedded.executor import SingleThreadedExecutor
    from .embedded.messages import ParameterDescriptor, SetParametersResult
    from .embedded.node import Node
    from .embedded.parameter import (
        InvalidParameterTypeException,
        InvalidParameterValueException,
        Parameter,
        ParameterAlreadyDeclaredException,
        ParameterNotDeclaredException,
    )
    from .embedded.services import Future
    from .embedded.time import Clock, ClockType, Duration, Time

__all__ = [
    "BACKEND",
    "DDS",
    "RCLPY",
    "Clock",
    "ClockType",
    "Duration",
    "ExternalShutdownException",
    "Future",
    "InvalidParameterTypeException",
    "InvalidParameterValueException",
    "Node",
    "Parameter",
    "ParameterAlreadyDeclaredException",
    "ParameterDescriptor",
    "ParameterNotDeclaredException",
    "SetParametersResult",
    "SingleThreadedExecutor",
    "Time",
    "choose_backend",
    "rclpy",
    "remove_ros_args",
]
