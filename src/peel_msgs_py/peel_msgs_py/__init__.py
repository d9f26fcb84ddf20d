"""Interface contract of peel: topic names, QoS, trajectory codec, SI/paper unit conversion,
parameter loading and checking, diagnostics, discovery, atomic writes and the rclpy helpers the
nodes share (``peel_msgs_py.ros``). The recorder and the bags are :mod:`peel_bag`.
"""
