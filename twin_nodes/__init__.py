"""rotortwin: a physics twin of a multirotor beside its real counterpart.

Package map (one home per concern):

- ``params``       vehicle parameter files: schema, validation, YAML I/O
- ``physics``      rigid body + rotors + plug-in effects (pure numpy/numba, ENU/FLU)
- ``frames``       the only place that converts PX4 NED/FRD <-> ROS ENU/FLU
- ``cli``          the ``rotortwin`` command; one module per subcommand group
- ``nodes``        thin rclpy shells
"""

__version__ = "0.1.0"
