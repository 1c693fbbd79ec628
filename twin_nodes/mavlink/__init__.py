"""PX4 over MAVLink: the lockstep simulator link, sensor models, live telemetry and missions.

May import: base, vehicle, twin.

- :mod:`twin_nodes.mavlink.sensors` — IMU / magnetometer / barometer / GPS models
  (true value + bias + white noise per axis) and the geodesy they need.
- :mod:`twin_nodes.mavlink.simlink` — :class:`~twin_nodes.mavlink.simlink.SimLinkServer`,
  the TCP server PX4 SITL's ``simulator_mavlink`` connects to (HIL_SENSOR /
  HIL_GPS / HIL_STATE_QUATERNION out, HIL_ACTUATOR_CONTROLS in, lockstep).
- :mod:`twin_nodes.mavlink.telemetry` — a client for a real vehicle's telemetry
  stream, parsed into ROS-frame numbers.
- :mod:`twin_nodes.mavlink.mission` — YAML plan files (per-item yaw) and MAVSDK upload/start.
- :mod:`twin_nodes.mavlink.sih_flight` — PX4 SIH flights with SIH parameters changed, the log
  scrubbed of SIH_* and the truth beside it (``launch_scripts/fly_sih.sh``).

None of these import ``rclpy``; the ROS shell is :mod:`twin_nodes.nodes.px4_bridge`.

MAVLink 2 is used throughout (PX4 speaks it; HIL_SENSOR's ``id`` is a MAVLink 2
extension field).  pymavlink's ``mavutil`` picks its wire protocol from the
``MAVLINK20`` environment variable when it loads a dialect, so importing this
package sets ``MAVLINK20=1`` if it is unset; the client also passes
``dialect="common"`` so that an earlier MAVLink 1 load is replaced.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")
