"""Physics: rigid body + rotors (``core``), plug-in effects (``effects``), the model (``model``).

World frame ENU, body frame FLU (ROS REP-103); PX4 data is converted by
:mod:`twin_nodes.frames` before it reaches here.
"""

from twin_nodes.physics.core import NX_BODY, POS, QUAT, RATES, ROTORS, VEL  # noqa: F401
from twin_nodes.physics.effects import EFFECTS, Effect, make_effect  # noqa: F401
from twin_nodes.physics.model import Multirotor, MultirotorBatch  # noqa: F401
