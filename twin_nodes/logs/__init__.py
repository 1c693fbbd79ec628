"""Flight data in and out: PX4 ULog reading and writing, time alignment, the replay's topic streams, ROS message conversions and MCAP recording.

May import: base, msgs_py.
"""
