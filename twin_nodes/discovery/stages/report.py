"""Stage 8, the report: what even the refitted model leaves (short events), the result with the method,
the baseline and after numbers on the held-out part and the closed-loop twin's metrics before and
after (``ReportInput`` -> ``Report``).  Rendering it (terminal summary, HTML, plans) is
:mod:`twin_nodes.discovery.report`, :mod:`~twin_nodes.discovery.plans` and :mod:`~twin_nodes.discovery.confirm`."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from twin_nodes.discovery import rate_loop
from twin_nodes.discovery.judging import BLOCK_S, MIN_REL_IMPROVEMENT, OE_BLOCK_S, T_CRIT, _mode_rms
from twin_nodes.discovery.locate import events
from twin_nodes.discovery.output_error import HORIZON_S, MIN_AXIS_R2, STRIDE_S, authority_mismatch
from twin_nodes.discovery.residuals import LOWPASS_HZ, residual_channels
from twin_nodes.discovery.stages import closed_loop
from twin_nodes.discovery.stages.candidates import not_excited
from twin_nodes.discovery.stages.closed_loop import Checked
from twin_nodes.discovery.stages.instrument import Instrumented
from twin_nodes.discovery.stages.mismatch import Mismatch
from twin_nodes.discovery.stages.prepare import PreparedFlight
from twin_nodes.discovery.stages.provisional import is_provisional
from twin_nodes.discovery.stages.verdicts import Verdicts
from twin_nodes.discovery.visibility import barely_excited, with_lean


@dataclass
class ReportInput:
    log: object                       # the FlightLog
    flight: PreparedFlight
    mismatch: Mismatch
    checked: Checked                  # the effects kept and the closed-loop twin's metrics so far
    verdicts: Verdicts
    refit: Instrumented               # the final refit vehicle and the instrument's numbers
    closed_loop: bool = True          # the closed-loop twin's metrics before/after
    t_start: float = 0.0              # time.time() at the start of the call (for ``elapsed_s``)


@dataclass
class Report:
    result: dict                      # the JSON-ready result (its ``_series``: the arrays the plots use)


def _not_shown(data, S: PreparedFlight, effects: list[dict], instrumented: dict | None = None) -> list[dict]:
    """What this flight cannot show: no signal at all (``stages.candidates.not_excited``), and the inertia axes
    and yaw moment a 30 % change of which stands out of the noise by less than ``visibility.MIN_SNR`` over the
    flight (issue 26 item 3: PX4 SIH's take-off and land), except a parameter a finding identified; a barely
    excited yaw moment the flight still leans to says so (``visibility.with_lean``, with PX4's rate-loop yaw
    gain from ``instrumented`` where it read the flight)."""
    out = not_excited(data, S.excitation)
    if S.nominal is None:
        return out
    skip = {e.split("(")[1].rstrip(")") for n in out for e in n["effects"] if e.startswith("inertia (")}
    for e in effects:
        if e.get("name") in ("inertia", "yaw_moment") and e.get("verdict") in ("confirmed", "likely"):
            skip |= set(e.get("params") or {}) - set(e.get("held_at_nominal") or {})
    yaw_gain = (instrumented or {}).get("yaw_gain") if (instrumented or {}).get("method") == "rate_loop" else None
    return with_lean(out + barely_excited(data, S.nominal, skip), effects, S.nominal.rotors.km_m, yaw_gain)


def run(inp: ReportInput) -> Report:
    """The result of a discover call."""
    S, vp, current, accepted = inp.flight, inp.flight.nominal, inp.refit.current, inp.checked.accepted
    data, names = S.data, S.names
    R_after = residual_channels(data, current, vp)
    after_held = np.sqrt(np.mean(R_after[S.held_mask] ** 2, axis=0))
    # what even the refitted model leaves: short events no steady effect is made for
    transients = events(data, R_after, vp, names)
    effects_out = inp.verdicts.effects
    likely = [e["name"] for e in effects_out if e["verdict"] == "likely"]
    result = {
        "log": str(inp.log.path),
        "params": vp.source,
        "method": _method(S, inp.refit.instrumented),
        "baseline": {"equation_error_heldout": {k: round(float(v), 5) for k, v in zip(names, inp.mismatch.base_held)}},
        "mismatch": inp.mismatch.windows,
        "events": transients,
        "excitation": S.excitation,
        "not_excited": _not_shown(data, S, inp.verdicts.effects, inp.refit.instrumented),
        "effects": effects_out,
        "accepted": [f.candidate.name for f in accepted if not is_provisional(f)],
        "likely": likely,
        "after": {"equation_error_heldout": {k: round(float(v), 5) for k, v in zip(names, after_held)}},
        "refit_params": current.to_ros_dict() if accepted else None,
    }
    _output_error_part(result, S, inp.mismatch, current, accepted)
    if inp.refit.instrumented is not None:
        result["instrumented"] = inp.refit.instrumented
    if inp.refit.lag is not None:
        result["rate_loop_lag"] = inp.refit.lag
    if inp.refit.joint is not None:
        result["lag_and_inertia"] = inp.refit.joint
    if inp.closed_loop:
        closed_loop._closed_loop(result, inp.log, vp, current, *S.scored, inp.checked.closed)
    closed_loop.reset()
    result["elapsed_s"] = round(time.time() - inp.t_start, 1)
    result["_series"] = {"t": data.t, "valid": data.valid, "held": S.held_mask, "R_before": inp.mismatch.R_base,
                         "R_after": R_after, "names": names}
    return Report(result)


def _method(S: PreparedFlight, instrumented: dict | None) -> dict:
    """The result's ``method``: how the flight was judged."""
    data, t_split = S.data, S.t_split
    return {
        "residual": "equation error (measured specific force and angular acceleration vs the model fed the "
                    "logged motor commands), per motor and horizontal force, low-passed "
                    f"{LOWPASS_HZ} Hz, in fraction of full motor output",
        "output_error": (f"the model flown open loop for {HORIZON_S} s from the logged state (windows every "
                         f"{STRIDE_S} s), driven by the logged motor commands; per window the mean "
                         "acceleration error of body rates and velocity over the horizon as force/moment, "
                         "same channels and units; axes where the nominal prediction's r^2 < "
                         f"{MIN_AXIS_R2} are left out"),
        "fit_interval_s": [round(float(data.t[data.valid][0]), 2), round(float(t_split), 2)],
        "heldout_interval_s": [round(float(t_split), 2), round(S.t_end, 2)],
        "motor_log_interval_s": round(float(data.motor_dt_s), 5),
        "timing": data.info.get("timing", ""),
        "acceptance": f"above the physical resolution floor and inside the physical range; 2-fold "
                      f"cross-validated: held-out block test (t or sign test) > {T_CRIT} over up to "
                      f"{len(S.eq.blocks)} blocks of {BLOCK_S} s (output error: "
                      f"{len(S.oe.blocks if S.oe else [])} "
                      f"blocks of {OE_BLOCK_S:.1f} s), held-out RMS cut >= {int(100 * MIN_REL_IMPROVEMENT)} %",
        "likely": "not significant yet, but held-out cut >= 30 % in its channel, parameter well away from "
                  "nominal and physical, both folds agree, most active blocks improved",
        **({"rate_loop": f"PX4's rate loop (the log's MC_*RATE_* gains, gyro/D-term/yaw-torque filters, rate-loop "
                         f"hold) flown on the model from the logged rate setpoint in {rate_loop.WINDOW_S:g} s "
                         "windows (integrator, motor and rate state free per window), compared on body rates: "
                         "roll/pitch inertia, and the motors' lag where every axis reads slow"}
           if instrumented is not None and instrumented.get("method") == "rate_loop" else {}),
    }


def _output_error_part(result: dict, S: PreparedFlight, mismatch: Mismatch, current, accepted: list) -> None:
    """The output error's baseline and after numbers, its axes and the authority mismatch."""
    oe, vp = S.oe, S.nominal
    if oe is not None:
        r0, mn = _mode_rms(mismatch.oe_base[oe.held_mask], vp)
        result["baseline"]["output_error_heldout"] = {k: round(float(v), 5) for k, v in zip(mn, r0)}
        result["output_error_axes"] = {**oe.windows.describe(), "horizon_s": HORIZON_S}
        result["authority"] = authority_mismatch(oe.windows)
        if accepted:
            r1, _ = _mode_rms(oe.residual(current, oe.held_mask), vp)
            result["after"]["output_error_heldout"] = {k: round(float(v), 5) for k, v in zip(mn, r1)}
    else:
        # no axis usable: the output error is not used, its axes and instrumented gains still shown
        result["output_error_axes"] = ({**S.windows.describe(), "horizon_s": HORIZON_S}
                                       if S.windows is not None else None)
        result["authority"] = authority_mismatch(S.windows) if S.windows is not None else []
