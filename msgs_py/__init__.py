"""Message mappings of the rotortwin ROS graph (standard ROS 2 types only).

- :mod:`msgs_py.topics`: every topic, its type and field layout, metric topic names.
- :mod:`msgs_py.streams`: which flight-log series become which ``/real`` topic on replay.
"""

from msgs_py.topics import TOPICS, TopicSpec, metric_topic, msg_class  # noqa: F401
