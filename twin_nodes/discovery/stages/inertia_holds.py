"""Holding an ``inertia`` finding's axis at the value PX4's rate loop was flown on, where the rate loop reads
that axis precisely, does not flag it, and disagrees with the finding (more than ``rate_loop.MIN_SE`` of its
standard errors): roll/pitch where it flags neither (:func:`hold_axes_not_borne_out`; beside a flagged axis
:func:`~twin_nodes.discovery.stages.instrument.attach_instrumented` holds the other), yaw always
(:func:`hold_yaw_not_borne_out`)."""

from __future__ import annotations

import math

import numpy as np

from twin_nodes.discovery import rate_loop
from twin_nodes.discovery.output_error import IV_AXIS_PARAM


def _borne_out_at_model(ratio: float, s: float, se: float) -> bool:
    """Whether the rate loop's reading ``s`` +- ``se`` (a scale of the inertia it was flown on) bears out that
    value and not the finding's ``ratio`` to it: x1 within ``MIN_SE`` standard errors, the finding beyond.  PX4
    SIH m013 (SIH_IZZ x1.3 + linear drag, M2): pitch x1.092 +- 0.011 (not flagged: under 10 %) is 7.5 standard
    errors from the finding's Iyy x1.007 and 8.4 from x1, so neither is held."""
    return abs(s - 1.0) <= rate_loop.MIN_SE * se and abs(ratio - s) > rate_loop.MIN_SE * se and abs(ratio - 1.0) > 1e-9


def _hold(entry: dict, k: str, ref: float, axis: str, s: float, se: float, ratio: float) -> None:
    """Hold ``entry``'s parameter ``k`` at ``ref`` (the finding's kept in ``own_params``), saying why: the
    rate loop's ``axis`` reading ``s`` +- ``se``, the finding's ``ratio`` to ``ref``."""
    own = entry.setdefault("own_params", {})[k] = entry["params"][k]
    entry["params"][k] = ref
    entry.setdefault("held_at_nominal", {})[k] = (
        f"PX4's rate loop reads {axis} inertia x{s:.3f} +- {se:.3f} (not flagged): the finding's {k} "
        f"{own:.4g} (x{ratio:.3f}) is not borne out by it")
    entry["verdict_note"] = (entry.get("verdict_note", "") + f"; {k} held at {ref:.4g} (the rate loop "
                             f"reads {axis} x{s:.3f} +- {se:.3f}; the finding's {own:.4g} not borne out)")


def hold_axes_not_borne_out(entry: dict, iv: dict, reference: np.ndarray) -> list[str]:
    """Where PX4's rate loop flags no roll/pitch axis: an ``inertia`` finding's Ixx/Iyy that the rate loop reads
    (``scale`` +- ``scale_se`` of ``reference``, the inertia it was flown on), does not flag and disagrees with
    (:func:`_borne_out_at_model`: x1 within ``MIN_SE`` standard errors of the reading, the finding's ratio to
    ``reference`` beyond) is held at
    ``reference`` (the finding's kept in ``own_params``), as :func:`hold_yaw_not_borne_out` holds Izz and
    :func:`attach_instrumented` an unflagged axis beside a flagged one.  PX4 SIH s023 (SIH_IZZ x1.3 on take-off
    and land, 4 ms): the equation error's Iyy +20 %, the rate loop's pitch x0.96 +- 0.03.  Returns the held."""
    held = []
    if iv.get("method") != "rate_loop" or iv.get("flagged"):
        return held
    for a, d in iv["axes"].items():
        k, j = IV_AXIS_PARAM[a]
        s, se = d.get("scale", math.nan), d.get("scale_se", math.nan)
        if k not in entry.get("params", {}) or not (np.isfinite(s) and np.isfinite(se) and se > 0):
            continue
        ratio = float(entry["params"][k]) / float(reference[j])
        if not _borne_out_at_model(ratio, s, se):
            continue
        _hold(entry, k, float(reference[j]), a, s, se, ratio)
        held.append(k)
    return held


def hold_yaw_not_borne_out(entry: dict, iv: dict, izz_read_on: float | None = None) -> bool:
    """An ``inertia`` finding's Izz that PX4's rate loop neither flags nor agrees with is held at the value the
    rate loop read yaw on (``iv["params"]["izz"]``; the finding's kept in ``own_params``): the rate loop reads
    yaw from the rate setpoint's response (:func:`~twin_nodes.discovery.rate_loop.inertia`, ``yaw_scale``),
    the equation error regresses the motors' yaw mode on the differentiated gyro, whose noise pulls Izz low
    where the flight barely turns in yaw.  PX4 SIH m018 (take-off and land, 4 ms logs, SIH Izz unchanged): the
    equation error's Izz 0.0252 (x0.84, both folds), the rate loop's yaw x0.931 +- 0.019 (not flagged: under 10
    %; 4.8 standard errors from x0.84).  Not flagged: within ``MIN_CHANGE`` or ``MIN_SE`` standard errors of
    x1; disagrees: x1 within ``MIN_SE`` standard errors of the reading, the finding's ratio beyond
    (:func:`_borne_out_at_model`; m018's x1 is 3.6 standard errors from its reading).  ``izz_read_on``:
    the Izz yaw was read on where ``iv`` has no ``params`` (nothing flagged).  Returns whether it held Izz."""
    if iv.get("method") != "rate_loop" or "izz" not in entry.get("params", {}):
        return False
    ref = iv["params"].get("izz", math.nan) if "params" in iv else (izz_read_on or math.nan)
    sy, sey = iv.get("yaw_scale", math.nan), iv.get("yaw_scale_se", math.nan)
    if not (np.isfinite(sy) and np.isfinite(sey) and sey > 0 and np.isfinite(ref) and ref > 0):
        return False
    ratio = float(entry["params"]["izz"]) / ref
    flagged = abs(sy - 1.0) > max(rate_loop.MIN_CHANGE, rate_loop.MIN_SE * sey)
    if flagged or not _borne_out_at_model(ratio, sy, sey):
        return False
    _hold(entry, "izz", float(ref), "yaw", sy, sey, ratio)
    return True


__all__ = ["hold_axes_not_borne_out", "hold_yaw_not_borne_out"]
