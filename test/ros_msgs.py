"""The Jazzy message classes the tests build messages with (rclpy's generated ones), and
rclpy's CDR serializer, under short names: ``import ros_msgs as M; M.serialize(M.Int64(data=1))``.
"""

from builtin_interfaces.msg import Time
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
from rclpy.serialization import deserialize_message as deserialize
from rclpy.serialization import serialize_message as serialize
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray, Header, Int64, MultiArrayDimension, MultiArrayLayout

__all__ = [
    "Clock", "Float64MultiArray", "Header", "Int64", "MultiArrayDimension", "MultiArrayLayout",
    "Point", "Pose", "PoseStamped", "Quaternion", "Time", "Twist", "TwistStamped", "Vector3",
    "Wrench", "WrenchStamped", "deserialize", "serialize",
]
