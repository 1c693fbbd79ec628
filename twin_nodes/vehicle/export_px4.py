"""Export a vehicle to the Gazebo / PX4 side: what the Búho Negro paper fills in by hand.

- :func:`sdf_motor_plugins`: one gz-sim ``MulticopterMotorModel`` plugin block
  per rotor for the model SDF;
- :func:`px4_airframe_params`: the PX4 parameters that must agree with it
  (``SIM_GZ_EC_*`` output range, ``CA_ROTOR*`` geometry, ``MPC_THR_HOVER``),
  written by :func:`px4_airframe_script` as ``param set-default`` lines for an
  airframe file and by :func:`qgc_params_table` as a QGroundControl
  ``.params`` file.

How the pieces fit (PX4 ``gz_bridge`` with the gz-sim plugin): PX4 sends per
ESC channel ``i`` the speed ``ω_ref = SIM_GZ_EC_MINi + u (SIM_GZ_EC_MAXi −
SIM_GZ_EC_MINi)`` [rad/s] for actuator command u in [0, 1], in the order of
``SIM_GZ_EC_FUNCi`` (101 = Motor1); the plugin with ``motorNumber i−1`` reads
entry i−1, clamps it to ``maxRotVelocity``, lags it with
``timeConstantUp/Down`` and applies ``T = motorConstant ω²`` and the reaction
torque ``momentConstant T``.  That is exactly rotortwin's ``omega_squared``
model, so these files make a Gazebo vehicle that matches the twin.

Parameter names were checked against the plugin source
(gazebosim/gz-sim ``src/systems/multicopter_motor_model/MulticopterMotorModel.cc``,
which reads ``jointName, linkName, motorNumber, turningDirection, motorType,
commandSubTopic, rotorDragCoefficient, rollingMomentCoefficient,
maxRotVelocity, motorConstant, momentConstant, timeConstantUp,
timeConstantDown, rotorVelocitySlowdownSim`` and optionally
``robotNamespace``) and PX4's ``4001_gz_x500`` airframe and x500 model.  The
plugin reads the channel index from ``motorNumber`` (some third-party models
write ``actuator_number``, which gz-sim ignores).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from twin_nodes.base.errors import ParamsError
from twin_nodes.base.frames import flu_to_frd
from twin_nodes.vehicle.params import VehicleParams

#: MAVLink MAV_PARAM_TYPE used in QGC .params files.
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9

#: PX4's range of MPC_THR_HOVER (conventions.md §2).
MPC_THR_HOVER_RANGE = (0.1, 0.8)


def _require_omega_squared(vp: VehicleParams) -> None:
    if vp.rotors.thrust_model != "omega_squared":
        raise ParamsError(vp.source, "rotors.thrust_model",
                          "export needs thrust_model omega_squared (Gazebo MulticopterMotorModel: "
                          f"T = kt omega^2), got {vp.rotors.thrust_model}")


def _fmt(x: float) -> str:
    return f"{float(x):.9g}"


def sdf_motor_plugins(vp: VehicleParams, *, command_sub_topic: str = "command/motor_speed",
                      joint_name: str = "rotor_{i}_joint", link_name: str = "rotor_{i}",
                      robot_namespace: str | None = None,
                      rotor_drag_coefficient: float | None = None,
                      rolling_moment_coefficient: float = 0.0,
                      rotor_velocity_slowdown_sim: float = 10.0) -> str:
    """The ``<plugin>`` blocks (one per rotor, PX4 motor order) for the model SDF.

    ``joint_name`` / ``link_name`` are patterns with ``{i}`` = 0-based rotor
    index (PX4's x500 names).  ``turningDirection`` is ``ccw`` for direction
    +1, ``cw`` for −1.  ``rotorDragCoefficient`` [N/((rad/s)(m/s))] defaults to
    the ``k_d`` of an enabled ``rotor_drag`` effect (the same law: each rotor
    adds ``−|ω| k v_perp``), else 0, so that Gazebo has no physics the twin
    lacks; ``rollingMomentCoefficient`` defaults to 0 for the same reason
    (x500 uses 8.06428e-05 and 1e-06).
    """
    _require_omega_squared(vp)
    r = vp.rotors
    if rotor_drag_coefficient is None:
        rotor_drag_coefficient = vp.effect_dict.get("rotor_drag", {}).get("k_d", 0.0)
    blocks = []
    for i in range(r.count):
        turning = "ccw" if r.direction[i] > 0 else "cw"
        x, y, z = r.x_flu_m[i], r.y_flu_m[i], r.z_flu_m[i]
        ns = f"\n  <robotNamespace>{robot_namespace}</robotNamespace>" if robot_namespace else ""
        blocks.append(
            f"<!-- Motor{i + 1} (SIM_GZ_EC_FUNC{i + 1} = {101 + i}): rotor at FLU "
            f"({_fmt(x)}, {_fmt(y)}, {_fmt(z)}) m, {turning.upper()} -->\n"
            f'<plugin filename="gz-sim-multicopter-motor-model-system" '
            f'name="gz::sim::systems::MulticopterMotorModel">{ns}\n'
            f"  <jointName>{joint_name.format(i=i)}</jointName>\n"
            f"  <linkName>{link_name.format(i=i)}</linkName>\n"
            f"  <turningDirection>{turning}</turningDirection>\n"
            f"  <timeConstantUp>{_fmt(r.tau_up_s)}</timeConstantUp>\n"
            f"  <timeConstantDown>{_fmt(r.tau_down_s)}</timeConstantDown>\n"
            f"  <maxRotVelocity>{_fmt(r.omega_max_rad_s)}</maxRotVelocity>\n"
            f"  <motorConstant>{_fmt(r.kt_n_s2_rad2)}</motorConstant>\n"
            f"  <momentConstant>{_fmt(r.km_m)}</momentConstant>\n"
            f"  <commandSubTopic>{command_sub_topic}</commandSubTopic>\n"
            f"  <motorNumber>{i}</motorNumber>\n"
            f"  <rotorDragCoefficient>{_fmt(rotor_drag_coefficient)}</rotorDragCoefficient>\n"
            f"  <rollingMomentCoefficient>{_fmt(rolling_moment_coefficient)}</rollingMomentCoefficient>\n"
            f"  <rotorVelocitySlowdownSim>{_fmt(rotor_velocity_slowdown_sim)}</rotorVelocitySlowdownSim>\n"
            f"  <motorType>velocity</motorType>\n"
            f"</plugin>"
        )
    head = (f"<!-- MulticopterMotorModel plugins for {vp.name}, generated by rotortwin from {vp.source}.\n"
            f"     Paste inside <model>; PX4 needs the matching SIM_GZ_EC_* / CA_ROTOR* parameters. -->")
    return head + "\n" + "\n".join(blocks) + "\n"


def rotor_positions_frd_m(vp: VehicleParams) -> np.ndarray:
    """Rotor positions (N, 3) in body **FRD** [m], as PX4's CA_ROTORn_PX/PY/PZ.

    The params store body FLU (ROS); FLU -> FRD keeps x and flips y and z.
    """
    return flu_to_frd(vp.rotors.positions_flu_m)


def px4_airframe_params(vp: VehicleParams) -> dict[str, int | float]:
    """PX4 parameters for a Gazebo (gz_bridge) airframe matching ``vp``, in airframe-file order.

    - ``SIM_GZ_EN`` 1 (Gazebo bridge on), ``CA_AIRFRAME`` 0 (multicopter), ``CA_ROTOR_COUNT`` N;
    - ``CA_ROTOR{i}_PX/PY/PZ`` [m, body FRD] (i = 0..N−1);
    - ``CA_ROTOR{i}_KM`` = +km for a CCW rotor, −km for CW (PX4: "> 0 = CCW");
    - ``CA_ROTOR{i}_CT`` [N] = kt ω_cmd_max², the thrust at full command (PX4's
      "Thrust = CT u²"; the allocator uses it only as a relative scale);
    - ``SIM_GZ_EC_FUNC{j}`` = 100 + j (Motor j), ``SIM_GZ_EC_MIN{j}`` = ω_min and
      ``SIM_GZ_EC_MAX{j}`` = ω_cmd_max [rad/s] for j = 1..N.  These are integer
      parameters in PX4 (output-module channel limits), so the speeds are
      rounded to whole rad/s (the twin keeps the exact values);
    - ``THR_MDL_FAC`` 0: PX4 must output commands linear in ω_ref, as the
      twin's command map assumes;
    - ``MPC_THR_HOVER`` = hover command on that linear map, clipped to PX4's
      range 0.1..0.8 and rounded to 3 decimals.
    """
    _require_omega_squared(vp)
    r = vp.rotors
    frd = rotor_positions_frd_m(vp)
    out: dict[str, int | float] = {"SIM_GZ_EN": 1, "CA_AIRFRAME": 0, "CA_ROTOR_COUNT": r.count}
    for i in range(r.count):
        # "+ 0.0" turns a -0.0 (z = 0 flipped) into 0.0 so the files read "0", not "-0".
        out[f"CA_ROTOR{i}_PX"] = round(float(frd[i, 0]), 6) + 0.0
        out[f"CA_ROTOR{i}_PY"] = round(float(frd[i, 1]), 6) + 0.0
        out[f"CA_ROTOR{i}_PZ"] = round(float(frd[i, 2]), 6) + 0.0
        out[f"CA_ROTOR{i}_KM"] = round(float(r.direction[i] * r.km_m), 6)
        out[f"CA_ROTOR{i}_CT"] = round(float(r.thrust_at_full_command_n), 4)
    for j in range(1, r.count + 1):
        out[f"SIM_GZ_EC_FUNC{j}"] = 100 + j
    for j in range(1, r.count + 1):
        out[f"SIM_GZ_EC_MIN{j}"] = int(round(r.omega_min_rad_s))
    for j in range(1, r.count + 1):
        out[f"SIM_GZ_EC_MAX{j}"] = int(round(r.omega_cmd_max_rad_s))
    out["THR_MDL_FAC"] = 0.0
    lo, hi = MPC_THR_HOVER_RANGE
    out["MPC_THR_HOVER"] = round(min(max(vp.hover_command, lo), hi), 3)
    return out


def simulated_log_params(vp: VehicleParams) -> dict[str, int | float]:
    """The PX4 parameters a ULog of a flight simulated with ``vp`` carries, as PX4 would log them:
    ``SYS_AUTOSTART`` 0 (no PX4 airframe), ``CA_ROTOR_COUNT``, ``CA_ROTOR{i}_PX/PY/PZ`` [m, body FRD],
    ``CA_ROTOR{i}_KM`` (spin in the sign, PX4's "> 0 = CCW"), ``MPC_THR_HOVER`` (hover command) and
    ``THR_MDL_FAC`` (0 unless the thrust model is PX4's thrust factor); unrounded, unlike the airframe file."""
    r = vp.rotors
    frd = rotor_positions_frd_m(vp)
    out: dict[str, int | float] = {
        "SYS_AUTOSTART": 0, "CA_ROTOR_COUNT": int(r.count), "MPC_THR_HOVER": float(vp.hover_command),
        "THR_MDL_FAC": float(r.thr_mdl_fac) if r.thrust_model == "thrust_factor" else 0.0}
    for i in range(r.count):
        out.update({f"CA_ROTOR{i}_PX": float(frd[i, 0]), f"CA_ROTOR{i}_PY": float(frd[i, 1]),
                    f"CA_ROTOR{i}_PZ": float(frd[i, 2]), f"CA_ROTOR{i}_KM": float(r.direction[i]) * r.km_m})
    return out


def px4_airframe_script(vp: VehicleParams) -> str:
    """``param set-default NAME VALUE`` lines for a PX4 airframe file (ROMFS init.d-posix)."""
    params = px4_airframe_params(vp)
    lines = [f"# PX4 parameters for {vp.name}, generated by rotortwin from {vp.source}",
             "# CA_ROTORn_P* in body FRD [m]; SIM_GZ_EC_MIN/MAX in rad/s (integers in PX4);",
             f"# hover: {vp.hover_omega_rad_s:.1f} rad/s, command {vp.hover_command:.3f}"]
    lines += [f"param set-default {k} {_value(v)}" for k, v in params.items()]
    return "\n".join(lines) + "\n"


def qgc_params_table(vp: VehicleParams, system_id: int = 1, component_id: int = 1) -> str:
    """The parameters as a QGroundControl ``.params`` file (tab-separated
    ``Vehicle-Id Component-Id Name Value Type``; type 6 = INT32, 9 = REAL32)."""
    params = px4_airframe_params(vp)
    lines = [f"# Onboard parameters for {vp.name} (generated by rotortwin from {vp.source})",
             "#",
             "# Vehicle-Id Component-Id Name Value Type"]
    for k, v in params.items():
        t = MAV_PARAM_TYPE_INT32 if isinstance(v, int) else MAV_PARAM_TYPE_REAL32
        lines.append(f"{system_id}\t{component_id}\t{k}\t{_value(v)}\t{t}")
    return "\n".join(lines) + "\n"


def _value(v: Any) -> str:
    if isinstance(v, int):
        return str(v)
    return _fmt(v)


__all__ = ["px4_airframe_params", "px4_airframe_script", "qgc_params_table",
           "rotor_positions_frd_m", "sdf_motor_plugins", "simulated_log_params"]
