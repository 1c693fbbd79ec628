"""Flying the model: a stateful simulator, closed-loop flights and open-loop prediction.

- :class:`Simulator` — one vehicle with a command delay line and exogenous inputs,
  advanced by wall-clock-free steps (used by the ROS model node and the PX4 bridge).
- :func:`fly_closed_loop` — the PX4-like controller flies a setpoint history
  (the paper's method: compare the twin's throttle/motors with the real ones).
- open loop with re-sync (the second reference's method) lives in
  :class:`twin_nodes.twin.runner.TwinRunner`, the one engine the node and offline runs share.

World ENU, body FLU throughout; times in seconds.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from twin_nodes.twin.control import Controller
from twin_nodes.vehicle.params import VehicleParams
from twin_nodes.physics.effects import Effect, effective_params
from twin_nodes.physics.model import Multirotor


class DelayLine:
    """Pure delay on a command stream (zero-order hold), exact to the step size."""

    def __init__(self, delay_s: float, dt_s: float, initial):
        self.n = int(round(max(delay_s, 0.0) / dt_s))
        self.buf: deque = deque([np.array(initial, float)] * self.n, maxlen=max(self.n, 1))

    def push(self, u: np.ndarray) -> np.ndarray:
        if self.n == 0:
            return u
        out = self.buf[0]
        self.buf.append(np.array(u, float))
        return out


class Simulator:
    """One vehicle stepped in time: ``sim.advance(u, 0.004)``; ``sim.state``; ``sim.t``."""

    def __init__(self, vp: VehicleParams, dt_s: float | None = None, extra_effects: Sequence[Effect] = (),
                 rng: np.random.Generator | None = None):
        self.model = Multirotor(vp, extra_effects)
        self.dt = float(dt_s or vp.dt_s)
        self.rng = rng or np.random.default_rng(0)
        # steady exogenous inputs from the params' effects (e.g. a wind effect); gusts need fly_closed_loop
        self.ext = self.model.exogenous(np.zeros(1), self.rng)[0]
        self.t = 0.0
        self.state = self.model.initial_state()
        self._delay = DelayLine(self.model.command_delay_s, self.dt, np.full(self.model.n_rotors, np.nan))
        self.last_u = np.full(self.model.n_rotors, np.nan)

    def reset(self, state: np.ndarray | None = None, t: float = 0.0) -> None:
        self.state = self.model.initial_state() if state is None else np.array(state, float)
        self.t = float(t)

    def set_battery_voltage(self, volts: float) -> None:
        self.ext[0] = volts

    def set_wind(self, wind_enu) -> None:
        self.ext[1:4] = wind_enu

    def advance(self, u, duration_s: float) -> np.ndarray:
        """Hold command ``u`` (N,) for ``duration_s`` (rounded to whole steps); returns the state."""
        u = np.asarray(u, float)
        self.last_u = u
        nsteps = max(int(round(duration_s / self.dt)), 1)
        if self._delay.n == 0:
            self.state = self.model.step(self.state, u, self.dt, self.ext, nsteps)
        else:
            for _ in range(nsteps):
                self.state = self.model.step(self.state, self._delay.push(u), self.dt, self.ext, 1)
        self.t += nsteps * self.dt
        return self.state

    def specific_force_flu(self) -> np.ndarray:
        return self.model.specific_force_flu(self.state, np.nan_to_num(self.last_u, nan=np.nan), self.ext)


@dataclass
class FlightRecord:
    """A simulated flight sampled at the controller rate (all ENU/FLU)."""

    t: np.ndarray            # (T,) s
    x: np.ndarray            # (T, nx) true state
    u: np.ndarray            # (T, N) motor commands sent (before any delay)
    throttle: np.ndarray     # (T,) collective throttle command (PX4 thrust setpoint convention)
    sp: np.ndarray           # (T, 11) setpoint flown
    specific_force: np.ndarray  # (T, 3) true accelerometer reading, FLU
    ext: np.ndarray          # (T, 4) battery voltage, wind
    x_est: np.ndarray        # (T, 13) what the controller saw
    info: dict = field(default_factory=dict)


def fly_closed_loop(plant: VehicleParams, t_sp: np.ndarray, SP: np.ndarray, *,
                    controller_params: VehicleParams | None = None,
                    extra_effects: Sequence[Effect] = (), x0: np.ndarray | None = None,
                    t_start: float | None = None, t_end: float | None = None,
                    battery_v: Callable[[np.ndarray], np.ndarray] | None = None,
                    estimate_noise: Callable[[np.ndarray, np.random.Generator], np.ndarray] | None = None,
                    armed: Callable[[np.ndarray], np.ndarray] | None = None,
                    rng: np.random.Generator | None = None, progress: bool = False) -> FlightRecord:
    """Fly the setpoint history (t_sp (S,), SP (S, 11), zero-order hold) with the PX4-like controller.

    ``plant`` is the vehicle that flies (hidden effects included); ``controller_params``
    what the controller believes (defaults to ``plant``).  ``estimate_noise(x13, rng)``
    returns a noisy copy of the state for the controller (estimator-like noise).
    ``armed(t)`` -> bool array: when False the motors are stopped (NaN commands).
    """
    rng = rng or np.random.default_rng(0)
    # by default the controller knows the plant as it is (parameter-type effects applied)
    cparams = controller_params or effective_params(plant)
    ctrl = Controller(cparams)
    model = Multirotor(plant, extra_effects)
    rate = ctrl.gains.rate_hz
    dt_c = 1.0 / rate
    nsub = max(int(round(dt_c / plant.dt_s)), 1)
    dt = dt_c / nsub
    t0 = float(t_sp[0] if t_start is None else t_start)
    t1 = float(t_sp[-1] if t_end is None else t_end)
    t = t0 + np.arange(int(np.floor((t1 - t0) / dt_c)) + 1) * dt_c
    idx = np.clip(np.searchsorted(t_sp, t, side="right") - 1, 0, len(t_sp) - 1)
    sp_t = SP[idx]
    ext = model.exogenous(t, rng, battery_v(t) if battery_v is not None else None)
    arm = armed(t) if armed is not None else np.ones(len(t), bool)
    n = model.n_rotors
    x = model.initial_state() if x0 is None else np.array(x0, float)
    X = np.empty((len(t), model.nx))
    U = np.empty((len(t), n))
    THR = np.empty(len(t))
    SF = np.empty((len(t), 3))
    XE = np.empty((len(t), 13))
    delay = DelayLine(model.command_delay_s, dt_c, np.full(n, np.nan))
    u_applied = np.full(n, np.nan)
    iterator = range(len(t))
    if progress:
        from tqdm import tqdm
        iterator = tqdm(iterator, desc="flying", unit="step", mininterval=0.5, leave=False)
    for k in iterator:
        X[k] = x
        SF[k] = model.specific_force_flu(x, u_applied, ext[k])
        xe = x[:13] if estimate_noise is None else estimate_noise(x[:13], rng)
        XE[k] = xe
        if arm[k]:
            u, info = ctrl.update(xe, sp_t[k], dt_c)
            THR[k] = info[0]
        else:
            ctrl.reset()
            u = np.full(n, np.nan)
            THR[k] = np.nan
        U[k] = u
        u_applied = delay.push(u)
        x = model.step(x, u_applied, dt, ext[k], nsub)
    return FlightRecord(t=t, x=X, u=U, throttle=THR, sp=sp_t, specific_force=SF, ext=ext, x_est=XE,
                        info={"rate_hz": rate, "model_terms": model.term_names})
