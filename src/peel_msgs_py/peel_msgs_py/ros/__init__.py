"""The rclpy side of the interface contract: what node code shares (QoS profiles, stamps,
parameter declaration with descriptors, the node ``main``). Only this subpackage and the node
modules of peel import ROS (``rclpy`` and the generated message packages of Jazzy); the rest of
``peel_msgs_py`` is plain Python.
"""
