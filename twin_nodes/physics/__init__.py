"""The physics core: rigid body and rotors, the plug-in effect catalogue and kernels, the RK4 model.

May import: base (vehicle only for type hints).

World frame ENU, body frame FLU (ROS REP-103); PX4 data is converted by
:mod:`twin_nodes.base.frames` before it reaches here.
"""

from twin_nodes.physics.core import NX_BODY, POS, QUAT, RATES, ROTORS, VEL  # noqa: F401
from twin_nodes.physics.effects import EFFECTS, Effect, make_effect  # noqa: F401
from twin_nodes.physics.model import Multirotor, MultirotorBatch  # noqa: F401
