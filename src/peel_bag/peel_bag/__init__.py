"""Bags of peel: the MCAP recorder (``peel record``, the ``peel_recorder`` node), the writer in the
rosbag2 layout, the reader and the repair of a damaged bag.
"""
