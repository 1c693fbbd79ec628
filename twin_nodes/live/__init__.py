"""Watching the twin live: the Foxglove WebSocket server of the graph, its shipped layout, and ``rotortwin live`` (the twin shadowing a vehicle's MAVLink telemetry: bridge -> twin -> metrics -> recorder, link-loss flag).

May import: base, vehicle, logs, twin, identify, mavlink, nodes, graph, msgs_py.

- :mod:`.scene` pure helpers: vehicle outlines from the params, decimated paths, the JSON records
  of the derived channels (no rclpy, no foxglove at import time).
- :mod:`.foxglove_node` the rclpy node that republishes the graph's ``/real``, ``/twin``,
  ``/twin_error``, ``/clock`` (and ``/diagnostics``) topics on a Foxglove WebSocket server
  (foxglove-sdk), unchanged (CDR with their ``ros2msg`` schemas, the channel names of the bag), plus
  ``/viz/...`` channels in Foxglove schemas (FrameTransforms, SceneUpdate) and JSON.
- :mod:`.layout` the Foxglove layout (``layouts/rotortwin.json``) and the topics it names.
- :mod:`.link_node` the link watchdog of a live run: ``/twin_error/link_lost``.
- :mod:`.shadow` ``rotortwin live --url``: the processes of a live run, started, watched, stopped.
- :mod:`.offline` the same computation offline on a recorded telemetry stream (``rotortwin live tlog``).
- :mod:`.attach` ``--foxglove [PORT]`` for other commands: the server as a child process beside them.
"""
