"""Interface contract of peel: topic names, QoS, trajectory codec, SI/paper unit conversion,
parameter loading and checking, the rclpy helpers the nodes share (``peel_msgs_py.ros``) and the
MCAP recorder.
"""
