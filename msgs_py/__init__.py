"""Message mappings of the rotortwin ROS graph (standard ROS 2 types only).

- :mod:`msgs_py.topics`: every topic, its type and field layout, metric topic names.

Which flight-log series become which ``/real`` topic on replay is decided where flight logs
are read (:mod:`twin_nodes.logs.streams`); this package imports nothing from ``twin_nodes``.
"""

from msgs_py.topics import TOPICS, TopicSpec, metric_topic, msg_class  # noqa: F401
