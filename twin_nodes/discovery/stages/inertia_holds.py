"""Holding an ``inertia`` finding's axis at the value PX4's rate loop was flown on, where the rate loop reads
that axis precisely, does not flag it, and disagrees with the finding (more than ``rate_loop.MIN_SE`` of its
standard errors): roll/pitch where it flags neither (:func:`hold_axes_not_borne_out`; beside a flagged axis
:func:`~twin_nodes.discovery.stages.instrument.attach_instrumented` holds the other), yaw always
(:func:`hold_yaw_not_borne_out`).  Last, each axis of an inertia finding reported with its readings and their span
as its uncertainty; an axis the flight excites weakly takes the midpoint of its readings, or is held at the model's
value as not read where they disagree (:func:`read_weak_axes`, the section below)."""

from __future__ import annotations

import copy
import math
from typing import Callable

import numpy as np

from twin_nodes.discovery import rate_loop
from twin_nodes.discovery.output_error import IV_AXIS_PARAM
from twin_nodes.discovery.visibility import MIN_SNR, STEP


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




# ------------------------------------------------------------------ an axis the flight excites weakly
#
# Measured on the 38 PX4 SIH flights of the judged batches 7-12 with an inertia change (``docs/discovery.md``, "An
# inertia axis the flight excites weakly"): where an axis' visibility is under ``WEAK_SNR`` (the yaw square M3's roll
# 6.4-7.0, the triangle M1's roll 7.0-10.4, take-off and land M5's every axis 2.2-7.6) the output error's roll read
# 9-12 % high on every M3 IXX/IYY flight (j014 x1.416, f014 x1.431, l013 x1.462 for x1.30) while the equation error
# (x1.239-1.284) and PX4's rate loop (x1.286-1.298) read it low or right; at 12 and over (pitch, yaw; roll on M2,
# M4, M6) no axis' readings were more than 10 % apart on a finding of the right effect.

#: an inertia axis is weakly excited under this visibility (:func:`~twin_nodes.discovery.visibility.visibility`: a
#: 30 % change's signal-to-noise over the flight), twice the ``barely excited`` bar: at ``MIN_SNR`` a 30 % change
#: is read to 2 standard errors of 10 %, at this one to 5 %, if nothing but the noise moves the reading
WEAK_SNR = 2.0 * MIN_SNR
#: the readings of a weakly excited axis, each (value -+ 2 standard errors), spanning more than this fraction of
#: their midpoint each way: the axis is not read (the bar a named parameter is held to, ``instrument.AGREE_WITHIN``)
MAX_SPREAD = 0.10
_AXIS = {"ixx": ("roll", 0), "iyy": ("pitch", 1), "izz": ("yaw", 2)}


def axis_readings(entry: dict, nominal_inertia: np.ndarray, iv: dict | None) -> dict[str, dict[str, tuple[float, float]]]:
    """Per inertia axis of ``entry``, each reading's (value, standard error): the output error's and the equation
    error's fits where they moved the axis (a fit that held it leaves it at the model's value exactly), PX4's rate
    loop for roll and pitch where its reading is attached (``residuals.rate_loop``; its standard error the
    reading's ``scale_se`` in ``iv``).  The fits' own standard errors are not computed: 0."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    res = entry.get("residuals") or {}
    for k, (axis, j) in _AXIS.items():
        if k not in (entry.get("params") or {}):
            continue
        got = {}
        for kind in ("output", "equation", "rate_loop"):
            v = ((res.get(kind) or {}).get("params") or {}).get(k)
            if v is None or not np.isfinite(v) or abs(v - nominal_inertia[j]) <= 1e-9 * nominal_inertia[j] or \
                    (kind == "rate_loop" and k == "izz"):     # the rate loop reads roll and pitch; its izz is the model's
                continue
            d = ((iv or {}).get("axes") or {}).get(axis) or {}
            s, se = d.get("scale", math.nan), d.get("scale_se", math.nan)
            got[kind] = (float(v), float(v) * se / s if kind == "rate_loop" and np.isfinite(se) and s > 0 else 0.0)
        out[k] = got
    return out


def weak_axis(value: float, readings: dict[str, tuple[float, float]], vis: float, nominal: float,
              dropped: str | None = None) -> dict:
    """An axis' report from its readings (:func:`axis_readings`), ``vis`` its visibility and ``nominal`` the model's
    value: ``value``, ``uncertainty`` (kg m^2: the half width about the value that holds every reading +- 2 of its
    standard errors; a fit's, which has none of its own, the flight's: ``(STEP - 1) / vis`` of the reading, a 30 %
    change standing out of the noise by ``vis``) and ``read``.  Where the axis is weakly excited (``vis`` < ``WEAK_SNR``) and read more than
    once, the value is the midpoint of the readings: no one of them is known better there (the module's
    measurements).  Not read (``read`` False, the value the model's) where the readings themselves lie more than
    ``MAX_SPREAD`` of their midpoint either side of it, or where a barely excited axis (< ``MIN_SNR``) has no
    reading of its own (the finding carries the model's value).  Elsewhere the value stands.  ``dropped``: the
    kind of the reading the finding's ``value`` is, where that reading was set aside as no reading on this axis
    (:func:`read_weak_axes`' weakly excited yaw): the value is not the finding's to keep, a weakly excited axis
    takes its one remaining reading, or is not read where none remains (m517)."""
    vals = [v for v, _ in readings.values()]
    out = {"visibility": round(float(vis), 2), "readings": {k: round(v, 6) for k, (v, _) in readings.items()},
           "value": float(value), "read": True}
    weak = bool(np.isfinite(vis) and vis < WEAK_SNR)
    if dropped is not None:
        out["set_aside"] = f"{dropped} {value:.6g}"
    if weak:
        out["weakly_excited"] = True
        if len(vals) >= 2:
            out["value"] = float(0.5 * (min(vals) + max(vals)))
        elif dropped is not None and vals:
            out["value"] = float(vals[0])
        elif dropped is not None:
            out.update(value=float(nominal), read=False, why=(
                f"its one reading, the {dropped} error's {value:.4g}, is no reading here and none other remains"))
        elif not vals and vis < MIN_SNR and abs(value - nominal) <= 1e-9 * nominal:
            out.update(read=False, why="no reading of its own (the finding carries the model's value)")
    mid = out["value"]
    # a fit's reading carries no standard error of its own: the flight's, a 30 % change standing out by ``vis``
    floor = (STEP - 1.0) / vis if np.isfinite(vis) and vis > 0 else 0.0
    out["uncertainty"] = round(float(max([abs(v - mid) + 2 * (s if s > 0 else floor * v) for v, s in readings.values()],
                                         default=0.0)), 6)
    if weak and len(vals) >= 2 and 0.5 * (max(vals) - min(vals)) > MAX_SPREAD * mid:
        out.update(value=float(nominal), read=False, why=(
            f"its readings ({', '.join(f'{k} {v:.4g}' for k, v in sorted(out['readings'].items()))}) lie up to "
            f"{100 * 0.5 * (max(vals) - min(vals)) / mid:.0f} % either side of {mid:.4g} (> {100 * MAX_SPREAD:.0f} %)"))
    return out


def read_weak_axes(data, nominal, effects_out: list[dict], current, iv: dict | None,
                   guard: Callable[[object], str | None]):
    """Each axis of an ``inertia`` finding with its readings and uncertainty (``axis_readings``: per axis
    :func:`weak_axis`'s numbers); a weakly excited axis takes the midpoint of its readings, or, where they
    disagree or it has none, is held at the model's value as not read (``held_at_nominal`` says why, the
    finding's own value kept in ``own_params``), as an axis the flight never excites is (``not_excited`` then
    names it where it is barely excited).  A confirmed finding's refit vehicle follows unless ``guard`` objects
    (then the entry stays as it was, the numbers kept).  ``data``/``nominal``: the flight's equation data and
    model (:func:`~twin_nodes.discovery.visibility.visibility`).  Returns the new refit vehicle (None: unchanged)."""
    from twin_nodes.discovery.visibility import visibility

    entry = next((e for e in effects_out if e["name"] == "inertia" and e["verdict"] in ("confirmed", "likely")), None)
    if entry is None or nominal is None:
        return None
    before = copy.deepcopy(entry)
    vis = visibility(data, nominal)
    I0 = np.diag(nominal.inertia)
    reads = axis_readings(entry, I0, iv)
    held = entry.get("held_at_nominal") or {}
    numbers = {}
    for k, readings in reads.items():
        if k in held:
            continue
        axis, j = _AXIS[k]
        if k == "izz" and not vis.get(k, math.nan) >= WEAK_SNR:
            # the equation error's Izz where the flight barely turns in yaw is pulled low by the differentiated gyro's
            # noise (PX4 SIH M5, Izz unchanged: m004 x0.82, m018 x0.84, f008 x0.52; :func:`hold_yaw_not_borne_out`)
            # m517: and where the finding's Izz is that reading (an equation-error finding), the value goes with it
            # (PX4 SIH sa008, M5, SIH_L_PITCH 0.15: Izz 0.01804, x0.60, kept with no reading, 39.9 % off)
            eq = readings.get("equation")
            dropped = "equation" if eq is not None and abs(eq[0] - entry["params"][k]) <= 1e-9 * I0[j] else None
            readings = {kind: r for kind, r in readings.items() if kind != "equation"}
        else:
            dropped = None
        r = numbers[k] = weak_axis(float(entry["params"][k]), readings, vis.get(k, math.nan), float(I0[j]), dropped)
        moved = abs(r["value"] - entry["params"][k]) > 1e-12 * I0[j]
        if r["read"] and not moved:
            continue
        if moved:
            entry.setdefault("own_params", {}).setdefault(k, entry["params"][k])
            entry["params"][k] = r["value"]
        if r["read"]:
            entry["verdict_note"] = (entry.get("verdict_note", "") + f"; {k} {r['value']:.4g} +- {r['uncertainty']:.2g}"
                                     f", the midpoint of its readings ({axis} weakly excited: visibility "
                                     f"{r['visibility']:.1f} < {WEAK_SNR:g})")
        else:
            entry.setdefault("held_at_nominal", {})[k] = (
                f"not read: {axis} is weakly excited (visibility {r['visibility']:.1f} < {WEAK_SNR:g}) and {r['why']}")
            entry["verdict_note"] = entry.get("verdict_note", "") + f"; {k} not read ({axis} weakly excited)"
    if numbers:
        entry["axis_readings"] = numbers
    if entry["params"] == before["params"] or entry["verdict"] != "confirmed" or "inertia" not in current.effect_dict:
        return None
    trial = current.with_effect("inertia", **{k: float(v) for k, v in entry["params"].items()})
    against = guard(trial)
    if against:
        entry.clear()
        entry.update(before)
        entry["axis_readings"] = {**numbers, "not_applied": against}
        return None
    return trial


__all__ = ["MAX_SPREAD", "WEAK_SNR", "axis_readings", "hold_axes_not_borne_out", "hold_yaw_not_borne_out",
           "read_weak_axes", "weak_axis"]
