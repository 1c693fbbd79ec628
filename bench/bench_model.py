"""Real-time factor of the physics model, beside RotorPy flying the same commands.

    .venv/bin/python bench/bench_model.py            # about 20 s
    .venv/bin/python bench/bench_model.py --strict   # exit 1 if a target is missed

Real-time factor (RTF) = simulated seconds per wall-clock second.  Every row integrates at a
1 kHz step (dt = 1 ms) the same rotor-speed command sequence: what our PX4-like controller sent
flying the Búho Negro (position jumps with yaw flips), held for 4 steps per 250 Hz command.

Rows:
  ours, step() per 1 ms     one vehicle stepped from Python one control step at a time (as a node does)
  ours, simulate()          one vehicle, the whole command sequence in one call
  ours, batch of K, step()  K vehicles (masses and inertias differ) stepped together from Python,
                            RTF per batch; "vehicle-s/s" = K x RTF
  RotorPy step()            rotorpy.vehicles.multirotor.Multirotor.step per 1 ms, its default
                            solve_ivp RK45 (as RotorPy users run it), aero off

"ratio" = our speed / RotorPy's (for the batch: vehicle-seconds per second against K separate
RotorPy vehicles).  Targets (issue): one vehicle >= 100x real time at 1 kHz, >= 20x RotorPy.
Numba compile time is excluded (reported on its own); timings are the best of --repeat runs.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

from twin_nodes.vehicle.params import VehicleParams, shipped
from twin_nodes.physics.model import Multirotor, MultirotorBatch

DT = 0.001
CMD_HOLD = 4  # 250 Hz controller commands held for 4 physics steps


def vehicle() -> VehicleParams:
    """Búho Negro with a speed-commanded map (omega_min 0, omega_cmd_max = omega_max) and one motor
    time constant, so RotorPy's cmd_motor_speeds = u * omega_max (mapping as in
    tests/test_rotorpy_crosscheck.py)."""
    return (shipped("buho_negro").replace(gravity_m_s2=9.81)
            .replace_rotors(omega_min_rad_s=0.0, omega_cmd_max_rad_s=487.0, omega_max_rad_s=487.0,
                            tau_up_s=0.025, tau_down_s=0.025))


def rotorpy_params(vp: VehicleParams) -> dict:
    r = vp.rotors
    J = vp.inertia
    return {"mass": vp.mass_kg, "Ixx": J[0, 0], "Iyy": J[1, 1], "Izz": J[2, 2], "Ixy": J[0, 1], "Ixz": J[0, 2],
            "Iyz": J[1, 2], "num_rotors": r.count,
            "rotor_pos": {f"r{i + 1}": r.positions_flu_m[i] for i in range(r.count)},
            "rotor_directions": -np.array(r.direction, dtype=float),  # RotorPy: +1 pushes the body +z
            "k_eta": r.kt_n_s2_rad2, "k_m": r.km_m * r.kt_n_s2_rad2, "tau_m": r.tau_up_s,
            "rotor_speed_min": 0.0, "rotor_speed_max": r.omega_max_rad_s, "motor_noise_std": 0.0}


def command_sequence(vp: VehicleParams, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Initial state and 1 kHz commands (T, 4): our controller flying jumps with yaw flips."""
    from twin_nodes.twin.control import setpoint
    from twin_nodes.twin.sim import fly_closed_loop

    t_sp = np.arange(0.0, seconds, 2.0)
    targets = [(0, 0, 50, 0.0), (6, -4, 54, 3.0), (-3, 5, 47, -3.0), (4, 4, 52, 1.0), (0, 0, 50, -2.0)]
    SP = np.array([setpoint(position_enu=targets[i % 5][:3], yaw_enu=targets[i % 5][3]) for i in range(len(t_sp))])
    m = Multirotor(vp)
    x0 = m.initial_state(position_enu=(0.0, 0.0, 50.0), rotor_state="hover")
    rec = fly_closed_loop(vp, t_sp, SP, x0=x0, t_end=seconds)
    return x0, np.repeat(rec.u[:-1], CMD_HOLD, axis=0)


def best_of(repeat: int, fn) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 epilog="ROTORTWIN_BENCH_SMOKE=1: a smoke run (1 s, 0.2 s RotorPy, a batch of 4, "
                                        "one repeat; the numbers mean nothing)")
    from _smoke import SMOKE as smoke  # bench/ is on sys.path when a bench runs as a script
    ap.add_argument("--seconds", type=float, default=1.0 if smoke else 20.0,
                    help="simulated seconds for our single-vehicle rows")
    ap.add_argument("--rotorpy-seconds", type=float, default=0.2 if smoke else 3.0,
                    help="simulated seconds for RotorPy")
    ap.add_argument("--batch", type=int, default=4 if smoke else 100, help="vehicles in the batch row")
    ap.add_argument("--batch-seconds", type=float, default=0.2 if smoke else 5.0)
    ap.add_argument("--repeat", type=int, default=1 if smoke else 3)
    ap.add_argument("--strict", action="store_true", help="exit 1 if a target is missed")
    args = ap.parse_args(argv)

    vp = vehicle()
    m = Multirotor(vp)
    t0 = time.perf_counter()
    x0, U = command_sequence(vp, max(args.seconds, args.batch_seconds, args.rotorpy_seconds))
    m.simulate(x0, U[:2], DT)
    m.step(x0, U[0], DT)
    rng = np.random.default_rng(0)
    variants = [vp.replace(mass_kg=vp.mass_kg * rng.uniform(0.9, 1.1),
                           inertia_kg_m2=tuple(map(tuple, vp.inertia * rng.uniform(0.9, 1.1))))
                for _ in range(args.batch)]
    batch = MultirotorBatch([Multirotor(v) for v in variants])
    XB0 = np.tile(x0, (args.batch, 1))
    batch.step(XB0, U[0], DT)
    setup_s = time.perf_counter() - t0

    n = int(round(args.seconds / DT))
    Us = U[:n]

    def per_step():
        x = x0
        for k in range(n):
            x = m.step(x, Us[k], DT)

    rtf_step = args.seconds / best_of(args.repeat, per_step)
    rtf_sim = args.seconds / best_of(args.repeat, lambda: m.simulate(x0, Us, DT))

    nb = int(round(args.batch_seconds / DT))

    def batch_steps():
        X = XB0
        for k in range(nb):
            X = batch.step(X, U[k], DT)

    rtf_batch = args.batch_seconds / best_of(args.repeat, batch_steps)

    from rotorpy.vehicles.multirotor import Multirotor as RotorPyMultirotor

    nr = int(round(args.rotorpy_seconds / DT))
    wmax = vp.rotors.omega_max_rad_s
    rp = RotorPyMultirotor(rotorpy_params(vp), control_abstraction="cmd_motor_speeds", aero=False, enable_ground=False)

    def rotorpy_run():
        s = {"x": x0[0:3].copy(), "v": x0[3:6].copy(), "q": x0[[7, 8, 9, 6]].copy(), "w": x0[10:13].copy(),
             "wind": np.zeros(3), "rotor_speeds": x0[13:17].copy()}
        for k in range(nr):
            s = rp.step(s, {"cmd_motor_speeds": U[k] * wmax}, DT)
        rotorpy_run.final = s

    rtf_rp = args.rotorpy_seconds / best_of(1, rotorpy_run)
    same = np.linalg.norm(rotorpy_run.final["x"] - m.simulate(x0, U[:nr], DT)[-1, 0:3])

    rows = [
        ("ours, step() per 1 ms", rtf_step, rtf_step / rtf_rp),
        ("ours, simulate()", rtf_sim, rtf_sim / rtf_rp),
        (f"ours, batch of {args.batch}, step()", rtf_batch, rtf_batch * args.batch / rtf_rp),
        ("RotorPy step()", rtf_rp, 1.0),
    ]
    print(f"rotortwin physics benchmark: Búho Negro, dt = {DT * 1e3:g} ms, python {platform.python_version()}, "
          f"{platform.machine()}")
    print(f"setup (fly the command sequence, numba cache load/compile): {setup_s:.2f} s")
    print(f"RotorPy vs ours after {args.rotorpy_seconds:g} s of the same commands: |dp| = {same:.2e} m")
    print()
    print(f"{'row':<30} {'RTF (sim s / wall s)':>22} {'vehicle-s/s':>13} {'ratio vs RotorPy':>18}")
    print("-" * 86)
    for name, rtf, ratio in rows:
        veh = rtf * args.batch if "batch" in name else rtf
        print(f"{name:<30} {rtf:>21.1f}x {veh:>13.1f} {ratio:>17.1f}x")
    print()
    checks = [("one vehicle >= 100x real time (step() per 1 ms)", rtf_step >= 100.0),
              ("one vehicle >= 20x RotorPy (step() per 1 ms)", rtf_step / rtf_rp >= 20.0)]
    for text, ok in checks:
        print(f"[{'PASS' if ok else 'MISS'}] {text}")
    return 0 if (all(ok for _, ok in checks) or not args.strict) else 1


if __name__ == "__main__":
    sys.exit(main())
