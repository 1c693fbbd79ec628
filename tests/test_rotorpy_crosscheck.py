"""Cross-check against RotorPy's ``Multirotor`` (an independent implementation, scipy solve_ivp).

Mapping (RotorPy 3.x ``rotorpy/vehicles/multirotor.py``; both worlds are z-up, both bodies are
x-forward/y-left/z-up, so positions, velocities and body rates carry over unchanged):

- quaternion: RotorPy ``q`` is ``[x, y, z, w]`` (scipy, body -> world); ours ``[w, x, y, z]``.
- thrust: ``k_eta omega^2`` = our ``kt omega^2``; yaw moment ``rotor_dir k_m omega^2`` on +z, so
  ``k_m = km kt`` and ``rotor_dir = -direction`` (our CCW rotor, direction +1, pushes the body -z;
  RotorPy's own PX4 SIH preset lists ``[-1, -1, 1, 1]`` for PX4 order, "+ CW, - CCW").
- motor: one first-order lag ``tau_m`` on rotor speed -> our ``tau_up = tau_down = tau_m``; the
  command is a rotor speed -> our ``omega_min = 0``, ``omega_cmd_max = omega_max = rotor_speed_max``,
  so ``u = omega_cmd / rotor_speed_max``.
- gravity: RotorPy uses 9.81 m/s^2; aerodynamics off (``aero=False``), no ground, no motor noise.

The commands are those our controller sent flying an aggressive schedule (position jumps, +-170 deg
yaw flips), replayed open loop into RotorPy at the same 4 ms step.  RotorPy integrates each step
with its own solve_ivp RK45, at rtol 1e-7 (its default rtol 1e-3 drifts 0.4 m in 10 s on the agile
Hummingbird, tau_m = 5 ms); ours runs its fixed 1 ms RK4 as shipped.
"""

from __future__ import annotations

import numpy as np
import pytest
from rotorpy.vehicles.hummingbird_params import quad_params as hummingbird
from rotorpy.vehicles.multirotor import Multirotor as RotorPyMultirotor

from twin_nodes.twin.control import setpoint
from twin_nodes.base.frames import quat_angle_between
from twin_nodes.vehicle.params import RotorParams, VehicleParams, shipped
from twin_nodes.physics.model import Multirotor
from twin_nodes.twin.sim import fly_closed_loop

DT = 0.004
T_END = 10.0
RK45_TIGHT = {"method": "RK45", "rtol": 1e-7, "atol": 1e-9}


def ours_from_rotorpy(qp: dict) -> VehicleParams:
    """Our parameters for a RotorPy vehicle (the Hummingbird preset, non-PX4 rotor order)."""
    pos = np.array(list(qp["rotor_pos"].values()))
    inertia = np.array([[qp["Ixx"], qp["Ixy"], qp["Ixz"]], [qp["Ixy"], qp["Iyy"], qp["Iyz"]],
                        [qp["Ixz"], qp["Iyz"], qp["Izz"]]])
    rotors = RotorParams(
        x_flu_m=tuple(pos[:, 0]), y_flu_m=tuple(pos[:, 1]), z_flu_m=tuple(pos[:, 2]),
        direction=tuple(int(-d) for d in qp["rotor_directions"]), thrust_model="omega_squared",
        kt_n_s2_rad2=qp["k_eta"], km_m=qp["k_m"] / qp["k_eta"], omega_min_rad_s=0.0,
        omega_cmd_max_rad_s=float(qp["rotor_speed_max"]), omega_max_rad_s=float(qp["rotor_speed_max"]),
        tau_up_s=qp["tau_m"], tau_down_s=qp["tau_m"], thrust_max_n=qp["k_eta"] * qp["rotor_speed_max"] ** 2,
        thr_mdl_fac=0.0)
    # the rest (controller gains, dt) from a shipped file; every physical value is replaced
    return shipped("buho_negro").replace(name="hummingbird", mass_kg=qp["mass"], gravity_m_s2=9.81,
                                         inertia_kg_m2=tuple(map(tuple, inertia)), rotors=rotors)


def buho_for_rotorpy() -> VehicleParams:
    """Búho Negro with cross inertia terms, one motor time constant, speed-commanded, g = 9.81."""
    J = np.array([[0.179, 0.004, -0.006], [0.004, 0.180, 0.003], [-0.006, 0.003, 0.303]])
    return (shipped("buho_negro").replace(gravity_m_s2=9.81, inertia_kg_m2=tuple(map(tuple, J)))
            .replace_rotors(omega_min_rad_s=0.0, omega_cmd_max_rad_s=487.0, omega_max_rad_s=487.0,
                            tau_up_s=0.025, tau_down_s=0.025))


def rotorpy_from_ours(vp: VehicleParams) -> dict:
    r = vp.rotors
    J = vp.inertia
    return {
        "mass": vp.mass_kg, "Ixx": J[0, 0], "Iyy": J[1, 1], "Izz": J[2, 2],
        "Ixy": J[0, 1], "Ixz": J[0, 2], "Iyz": J[1, 2],
        "num_rotors": r.count,
        "rotor_pos": {f"r{i + 1}": r.positions_flu_m[i] for i in range(r.count)},
        "rotor_directions": -np.array(r.direction, dtype=float),
        "k_eta": r.kt_n_s2_rad2, "k_m": r.km_m * r.kt_n_s2_rad2,
        "tau_m": r.tau_up_s, "rotor_speed_min": 0.0, "rotor_speed_max": r.omega_max_rad_s,
        "motor_noise_std": 0.0,
    }


def aggressive_flight(vp: VehicleParams):
    """Our controller flying position jumps with +-170 deg yaw flips every 2 s (our model)."""
    t_sp = np.arange(0.0, T_END, 2.0)
    targets = [(0.0, 0.0, 50.0, 0.0), (6.0, -4.0, 54.0, np.radians(170)), (-3.0, 5.0, 47.0, -np.radians(170)),
               (4.0, 4.0, 52.0, np.radians(60)), (0.0, 0.0, 50.0, -np.radians(120))]
    SP = np.array([setpoint(position_enu=p[:3], yaw_enu=p[3]) for p in targets])
    m = Multirotor(vp)
    x0 = m.initial_state(position_enu=(0.0, 0.0, 50.0), rotor_state="hover")
    return fly_closed_loop(vp, t_sp, SP, x0=x0, t_end=T_END)


@pytest.mark.parametrize("case", ["buho_negro_cross_inertia", "rotorpy_hummingbird"])
def test_same_rotor_speed_commands_give_the_same_flight_as_rotorpy(case):
    if case == "rotorpy_hummingbird":
        qp = dict(hummingbird)
        qp.update(c_Dx=0.0, c_Dy=0.0, c_Dz=0.0, k_d=0.0, k_z=0.0, k_h=0.0, k_flap=0.0, motor_noise_std=0.0)
        vp = ours_from_rotorpy(qp)
    else:
        vp = buho_for_rotorpy()
        qp = rotorpy_from_ours(vp)
    rec = aggressive_flight(vp)
    X, U = rec.x, rec.u
    assert np.all(np.isfinite(U)) and np.all((U >= 0) & (U <= 1))
    # it is an aggressive manoeuvre: large differential commands, fast yaw, large tilt
    assert np.max(np.ptp(U, axis=1)) > 0.4
    assert np.max(np.abs(X[:, 12])) > 3.0
    assert np.max(np.degrees(np.arccos(1 - 2 * (X[:, 7] ** 2 + X[:, 8] ** 2)))) > 30.0

    omega_max = vp.rotors.omega_max_rad_s
    state = {"x": X[0, 0:3].copy(), "v": X[0, 3:6].copy(), "q": X[0, [7, 8, 9, 6]].copy(),
             "w": X[0, 10:13].copy(), "wind": np.zeros(3), "rotor_speeds": X[0, 13:17].copy()}
    rp = RotorPyMultirotor(qp, initial_state=state, control_abstraction="cmd_motor_speeds", aero=False,
                           enable_ground=False, integrator_kwargs=RK45_TIGHT)
    n = len(rec.t) - 1
    P = np.empty((n + 1, 3))
    Q = np.empty((n + 1, 4))
    W = np.empty((n + 1, 4))
    P[0], Q[0], W[0] = X[0, 0:3], X[0, 6:10], X[0, 13:17]
    for k in range(n):
        state = rp.step(state, {"cmd_motor_speeds": U[k] * omega_max}, DT)
        P[k + 1] = state["x"]
        Q[k + 1] = state["q"][[3, 0, 1, 2]]
        W[k + 1] = state["rotor_speeds"]

    pos_err = np.linalg.norm(P - X[:, 0:3], axis=1)
    att_err = np.degrees(quat_angle_between(Q, X[:, 6:10]))
    assert np.max(pos_err) < 0.01, f"max position difference {np.max(pos_err):.3g} m"
    assert np.max(att_err) < 0.5, f"max attitude difference {np.max(att_err):.3g} deg"
    np.testing.assert_allclose(W, X[:, 13:17], atol=1e-3 * omega_max)
