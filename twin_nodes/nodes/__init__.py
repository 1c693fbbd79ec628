"""Thin rclpy node shells of the rotortwin graph (each runs as its own process).

=================  ==========================================  =============================================
module             node name                                   role
=================  ==========================================  =============================================
``ulog_replay``    ``ulog_replay``                             a ULog as ``/real/...`` topics and ``/clock``
``twin_node``      ``twin``                                    TwinRunner beside ``/real``; ``/twin/...``
``metrics_node``   ``metrics``                                 ``/twin_error/...`` rolling + whole-flight totals
``recorder_node``  ``recorder``                                every topic into one MCAP (rosbag2 layout)
``px4_bridge``     (PX4 MAVLink bridge, separate owner)        live ``/real/...`` from telemetry
=================  ==========================================  =============================================

Run one with ``python -m twin_nodes.nodes.<module> --ros-args -p name:=value ...``,
``launch_scripts/run_node.sh <module> ...`` or ``rotortwin <replay|twin|metrics|record> ...``.
Topic layouts: :mod:`msgs_py.topics`; protocol: :mod:`twin_nodes.nodes.common`.
"""

#: node module -> default node name
NODES = {"ulog_replay": "ulog_replay", "twin_node": "twin", "metrics_node": "metrics", "recorder_node": "recorder"}
