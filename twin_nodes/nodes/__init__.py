"""Thin rclpy node shells of the graph, each its own process: parameters in, topics out.

May import: base, vehicle, logs, twin, mavlink, msgs_py.

=================  ==========================================  =============================================
module             node name                                   role
=================  ==========================================  =============================================
``ulog_replay``    ``ulog_replay``                             a ULog as ``/real/...`` topics and ``/clock``
``twin_node``      ``twin``                                    TwinRunner beside ``/real``; ``/twin/...``
``metrics_node``   ``metrics``                                 ``/twin_error/...`` rolling + whole-flight totals
``recorder_node``  ``recorder``                                every topic into one MCAP (rosbag2 layout)
``px4_bridge``     (PX4 MAVLink bridge, separate owner)        live ``/real/...`` from telemetry
``engine``         (no node: pure, no rclpy)                   the twin's and the metrics' cores, also run
                                                               in-process by ``rotortwin regress --offline``
=================  ==========================================  =============================================

Run one with ``python -m twin_nodes.nodes.<module> --ros-args -p name:=value ...``,
``launch_scripts/run_node.sh <module> ...`` or ``rotortwin <replay|twin|metrics|record> ...``.
Topic layouts: :mod:`msgs_py.topics`; protocol: :mod:`twin_nodes.nodes.common`.  Nodes started by
the graph orchestrator stop when it dies (``PR_SET_PDEATHSIG`` and the ``ROTORTWIN_PARENT_PID``
watchdog in :func:`twin_nodes.nodes.common.run_node`).
"""

#: node module -> default node name
NODES = {"ulog_replay": "ulog_replay", "twin_node": "twin", "metrics_node": "metrics", "recorder_node": "recorder"}
