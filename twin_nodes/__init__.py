"""rotortwin: a physics twin of a multirotor beside its real counterpart.

Subpackages, lowest layer first (each ``__init__`` says what it owns and what it may import;
``tests/test_layout.py`` enforces it):

- ``base``       one-line errors; the only NED/FRD <-> ENU/FLU conversion
- ``physics``    rigid body + rotors + plug-in effects, RK4 model (numba, ENU/FLU)
- ``vehicle``    parameter files, the paper's derivations, PX4/Gazebo export, rotor geometry
- ``logs``       ULog read/write, time alignment, replay streams, ROS conversions, MCAP
- ``twin``       controller, simulator, simulated PX4-like flights, the twin beside a flight, comparison, metrics, report
- ``identify``   the second reference's identification methods
- ``discovery``  missing-physics discovery (the method)
- ``prove``      the evidence: flights with one known change each (ours, PX4 SIH, RotorPy), found blind, scored
- ``fleet``      discovery over many flights on Dask, the Parquet flight catalog, trends and alarms
- ``mavlink``    PX4 over MAVLink: simulator link, telemetry, missions
- ``nodes``      thin rclpy shells, one process each
- ``graph``      the process orchestrator (``run_graph``) and bag regression
- ``live``       the graph in Foxglove (WebSocket server, layout) and ``rotortwin live`` (twin beside telemetry)
- ``cli``        the ``rotortwin`` command: argument parsing and output only
"""

__version__ = "0.1.0"
