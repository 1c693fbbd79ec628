"""Which control law a twin flies: PX4's cascade (:mod:`twin_nodes.twin.control`) or the geometric SE(3) law
(:mod:`twin_nodes.twin.control_se3`, the controller RotorPy flies), as the params' ``controller.law`` says."""

from __future__ import annotations

from twin_nodes.twin.control import Controller
from twin_nodes.twin.control_se3 import SE3Controller
from twin_nodes.vehicle.params import VehicleParams

#: the control laws a twin can fly (``controller.law``)
LAWS = ("px4", "se3")


def controller_law(vp: VehicleParams) -> str:
    """The params' ``controller.law`` (default ``px4``)."""
    return str((vp.controller or {}).get("law", "px4"))


def make_controller(vp: VehicleParams, believed: VehicleParams | None = None) -> Controller | SE3Controller:
    """The controller the params' ``controller.law`` names, for the vehicle ``vp`` (the SE(3) law's mass and
    inertia: ``believed``, the vehicle its controller was written for; default ``vp``)."""
    if controller_law(vp) == "se3":
        return SE3Controller(vp, believed)
    return Controller(vp)
