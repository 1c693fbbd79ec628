"""The prove suite's scoring, shared by every source: the rules, one row per flight, the tables.

A flight's truth (:class:`Truth`, in our effect vocabulary) against ``discover()``'s result
(:func:`score_flight`), a source's numbers (:func:`score`) and its table (:func:`format_table`,
:func:`summary_line`); :func:`map_jobs` runs a source's flights over processes and
:func:`write_result` keeps each flight's result.
"""

from __future__ import annotations

import json
import math
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin_nodes.base import frames
from twin_nodes.twin.simflight import Hidden
from twin_nodes.vehicle.params import VehicleParams


#: parameters that are the components of one vector (a wind velocity, a CoM offset): scored as the length of
#: the vector error over the true vector's length; a component near zero has no relative error of its own
#: (a 3.5 m/s wind blowing 6 degrees off north is not "57 % wrong" because its 0.4 m/s east part is 0.2 m/s off)
VECTOR_PARAMS = {"wind": ("vx", "vy"), "com_offset": ("dx", "dy")}


def _vector_error(name: str, true: dict, found: dict) -> tuple[float, tuple[str, ...]] | None:
    """(|found - true| / |true|, the components) of ``name``'s vector parameters; None when it has none."""
    keys = VECTOR_PARAMS.get(name)
    if not keys or not all(k in true for k in keys):
        return None
    if not all(k in found for k in keys):
        return float("inf"), keys
    t = np.array([true[k] for k in keys], float)
    f = np.array([found[k] for k in keys], float)
    return float(np.linalg.norm(f - t) / max(float(np.linalg.norm(t)), 1e-9)), keys


def _param_error(hidden: Hidden, found: dict, not_identified: frozenset = frozenset()) -> float | None:
    """Largest relative error over the hidden effect's identified parameters (motor index exact; a vector's
    components as one vector, :data:`VECTOR_PARAMS`); ``not_identified``: parameters the finding says it held at
    the model's value because the flight does not show them (its ``held_at_nominal``), not scored; None where
    that leaves none."""
    if hidden.name == "none":
        return None
    errs = []
    vec = _vector_error(hidden.name, hidden.params, found)
    if vec is not None:
        errs.append(vec[0])
    scored = [k for k in hidden.params if k not in not_identified and k != "gust_std"]
    if not scored:
        return None
    for k, true in hidden.params.items():
        if k == "gust_std" or k in not_identified or (vec is not None and k in vec[1]):
            continue  # gust_std: a noise level, not a physical constant: reported, not scored
        if k not in found:
            return float("inf")
        if k == "motor":
            if int(round(found[k])) != int(true):
                return float("inf")
            continue
        errs.append(abs(found[k] - true) / max(abs(true), 1e-9))
    return max(errs) if errs else 0.0


# ------------------------------------------------------------------ scoring, shared by every source
#
# The rules (issue 11, part 5): the true effect is the top `confirmed` or `likely` finding
# (drag names are one class, and mass with thrust coefficient: each pair changes the same force in a
# way one flight may not tell apart); no finding of either grade on a no-effect flight; the parameter
# within 10 % of the truth; the held-out cut >= 50 % in the channel where the effect acts.

#: grades that count as a finding, best first
FINDING_GRADES = ("confirmed", "likely")
EFFECT_CLASS = {"linear_drag": "drag", "body_drag": "drag", "rotor_drag": "drag",
                "mass": "mass/thrust", "thrust_coefficient": "mass/thrust"}


def verdict(effect: dict) -> str:
    """The graded verdict of one effect of ``discover()``'s result (``accepted`` before grading existed)."""
    v = effect.get("verdict")
    if v:
        return str(v)
    return "confirmed" if effect.get("accepted") else "rejected"


def findings(result: dict) -> list[dict]:
    """The effects graded ``confirmed`` or ``likely``, confirmed first (discover's order within a grade);
    a term of stage 9 (``state_term``: what the vocabulary's findings leave) after the vocabulary's findings,
    still a finding (it counts on a no-effect flight)."""
    eff = [e for e in result.get("effects", []) if verdict(e) in FINDING_GRADES]
    return sorted(eff, key=lambda e: (e.get("name") == "state_term", FINDING_GRADES.index(verdict(e))))


def effect_class(name: str) -> str:
    return EFFECT_CLASS.get(name, name)


_MOTORS = ("throttle", "roll", "pitch", "yaw")
_FORCE = ("force_x", "force_y", "throttle")
#: the physical modes (residuals.modes) each effect acts in: its held-out cut is read there
EFFECT_CHANNELS = {"mass": ("throttle",), "thrust_coefficient": ("throttle",), "battery_sag": ("throttle",),
                   "ground_effect": ("throttle",), "motor_efficiency": _MOTORS, "motor_time_constant": _MOTORS,
                   "actuator_delay": _MOTORS, "yaw_moment": ("yaw",), "rotor_tilt": ("yaw",),
                   "inertia": ("roll", "pitch", "yaw"), "angular_damping": ("roll", "pitch", "yaw"),
                   "com_offset": ("roll", "pitch"), "linear_drag": _FORCE, "rotor_drag": _FORCE,
                   "body_drag": _FORCE, "wind": _FORCE}


def heldout_cut(effect: dict) -> dict:
    """The held-out cut of a finding in the effect's own channel.

    discover() reports, per residual it judged on (equation error; output error where it has one), the mode
    with the largest held-out drop.  The cut scored is the largest over those residuals whose mode is one the
    effect acts in (:data:`EFFECT_CHANNELS`); when none is, discover's own headline number, flagged."""
    chans = EFFECT_CHANNELS.get(effect["name"])
    per = [(k, r) for k, r in (effect.get("residuals") or {}).items() if isinstance(r, dict)]
    if not per:
        per = [(effect.get("residual", "equation"), effect)]
    own = [(k, r) for k, r in per if chans is None or r.get("heldout_channel") in chans]
    kind, r = max(own, key=lambda kr: kr[1].get("heldout_improvement") or -math.inf) if own else \
        (effect.get("residual", "equation"), effect)
    return {"residual": kind, "channel": r.get("heldout_channel"), "before": r.get("heldout_before"),
            "after": r.get("heldout_after"), "improvement": r.get("heldout_improvement"), "in_channel": bool(own)}


@dataclass(frozen=True)
class DragContext:
    """What a drag comparison needs from the flight: body-frame airspeed and summed rotor speed on the
    airborne samples (wind-free flights: the ground velocity is the airspeed)."""

    v_body: np.ndarray      # (n, 3) FLU m/s
    sum_omega: np.ndarray   # (n,) rad/s, steady state of the logged commands through the nominal

    @classmethod
    def from_log(cls, log, vp: VehicleParams, rate_hz: float = 10.0) -> "DragContext":
        t0, t1 = log.airborne_interval()
        t, d = log.resample(["velocity_enu", "attitude_q", "motors"], rate_hz, t0, t1)
        ok = np.isfinite(d["velocity_enu"]).all(1) & np.isfinite(d["attitude_q"]).all(1) & \
            np.isfinite(d["motors"]).all(1)
        vb = frames.quat_rotate(frames.quat_conjugate(d["attitude_q"][ok]), d["velocity_enu"][ok])
        ref = vp.rotors.reference_from_command(d["motors"][ok])
        if vp.rotors.thrust_model == "omega_squared":
            omega = ref
        else:  # the reported rotor speed of the thrust-factor model: omega_max sqrt(T / T_max)
            omega = vp.rotors.omega_max_rad_s * np.sqrt(np.maximum(vp.rotors.thrust_from_state(ref), 0)
                                                        / vp.rotors.thrust_max_n)
        return cls(vb, omega.sum(1))

    def force(self, name: str, params: dict) -> np.ndarray:
        """Body force (n, 3) [N] of one drag law on this flight's samples."""
        v = self.v_body
        F = np.zeros_like(v)
        if name == "linear_drag":
            F = -params["k_n_s_m"] * v
        elif name == "rotor_drag":
            F[:, :2] = -params["k_d"] * self.sum_omega[:, None] * v[:, :2]
        elif name == "body_drag" and not params.get("norm"):
            c = np.array([params["c_dx"], params["c_dy"], params["c_dz"]])
            F = -c * np.abs(v) * v
        elif name in ("rotorpy_parasitic", "body_drag"):  # RotorPy's D = -|v| C v (our body_drag with norm 1)
            c = np.array([params["c_dx"], params["c_dy"], params["c_dz"]])
            F = -np.linalg.norm(v, axis=1, keepdims=True) * c * v
        else:
            raise ValueError(f"not a drag law: {name}")
        return F

    def linear_equivalent(self, laws: list[tuple[str, dict]]) -> float:
        """The isotropic linear drag coefficient [N/(m/s)] that does the same work on this flight's airspeeds
        as the sum of ``laws``: -sum(F . v) / sum(|v|^2)."""
        F = sum((self.force(n, p) for n, p in laws), np.zeros_like(self.v_body))
        den = float(np.sum(self.v_body ** 2))
        return float(-np.sum(F * self.v_body) / den) if den > 0 else 0.0


@dataclass(frozen=True)
class Truth:
    """One flight's truth in our effect vocabulary, with what scoring needs beyond the parameters."""

    hidden: Hidden
    text: str = ""                       # how the source states it (e.g. 'SIH_KDV 1.0 -> 1.8')
    drag_law: tuple | None = None        # (name, params) of the true drag law when its form is not ours


def _drag_laws(vp: VehicleParams) -> list[tuple[str, dict]]:
    return [(n, p) for n, p in vp.effect_dict.items() if effect_class(n) == "drag"]


#: each drag law's coefficients (force per airspeed): what scales with the mass a force per unit mass is read at
DRAG_COEFFICIENTS = {"linear_drag": ("k_n_s_m",), "rotor_drag": ("k_d",), "body_drag": ("c_dx", "c_dy", "c_dz")}


#: parameters of a co-flown effect that a mass <-> thrust-coefficient reading rescales, as the power of
#: ``per_mass`` the finding reads them at: the reading's thrust per command is the real one over ``per_mass``,
#: so a torque per thrust (km) reads x per_mass, an inertia (turn rate per thrust difference) / per_mass (r070:
#: thrust coefficient 0.87 found as mass 1.15 beside a yaw moment: km 0.030 = 0.0345 x 0.87, Ixx x1.15); drags:
#: :data:`DRAG_COEFFICIENTS`.  A CoM offset is read as itself: it only moves the rotors' levers (r_i - d, the
#: weight acts at the CoM), so the trim the flight shows, sum T_i (r_i - d) = 0, i.e. d = sum T_i r_i / sum T_i,
#: is a ratio of thrusts that a common thrust scale leaves alone (o034: mass 1.15 found as kt_scale 0.870, the
#: CoM found at (3.79, -0.79) mm, the truth itself; the earlier x per_mass read it 13 % off)
READING_POWERS = {"yaw_moment": {"km": 1}, "inertia": {"ixx": -1, "iyy": -1, "izz": -1}}


def in_reading(truth: Truth, per_mass: float) -> Truth:
    """``truth`` as a finding made in the flight's other mass/thrust reading reads it (:data:`READING_POWERS`);
    itself where ``per_mass`` is 1 or its effect is not one a reading rescales."""
    powers = READING_POWERS.get(truth.hidden.name)
    if per_mass == 1.0 or not powers:
        return truth
    params = {k: v * per_mass ** powers[k] if k in powers else v for k, v in truth.hidden.params.items()}
    return Truth(Hidden(truth.hidden.name, params), f"{truth.text} (x{per_mass:.3g} reading)", truth.drag_law)


def compare(truth: Truth, found_name: str, found: dict, nominal: VehicleParams,
            drag: DragContext | None = None, per_mass: float = 1.0,
            not_identified: frozenset = frozenset()) -> tuple[float | None, str]:
    """Relative parameter error of a finding against the truth, and the comparison as text.

    Same effect: the largest relative error over the truth's parameters (as the ours suite always scored).
    Mass against thrust coefficient: thrust per unit mass (kt_scale against m0/m), shown in the truth's
    parameter.  Drag against drag (any law): the isotropic linear coefficient that does the same work on this
    flight's airspeeds, nominal drag included (the truth's total against the nominal plus the finding).
    Another class: ``(inf, 'wrong effect')``.

    ``per_mass``: the real thrust per command over the finding's reading's, where the flight's mass or thrust
    change was found as the other (``grid_prove._per_mass``: the true mass over the model's, or the true thrust
    coefficient): a drag found beside it is a force per the model's mass, and the IMU fixes only force per unit
    mass, so the found drag is read at the true mass (times ``per_mass``); a yaw moment or inertia is scored
    against the truth in that reading (:func:`in_reading`; a CoM offset, a ratio of thrusts, reads as itself).

    ``not_identified``: the finding's own parameters it held at the model's value as not shown by the flight
    (same effect only): not scored, named in the text (an inertia axis the flight never excites)."""
    if found_name == truth.hidden.name:
        truth = in_reading(truth, per_mass)
    h = truth.hidden
    if per_mass != 1.0 and effect_class(h.name) == "drag" and found_name == h.name and truth.drag_law is None:
        found = {k: v * per_mass if k in DRAG_COEFFICIENTS.get(found_name, ()) else v for k, v in found.items()}
    if h.name == "none":
        return None, "-"
    if effect_class(found_name) != effect_class(h.name):
        return float("inf"), "wrong effect"
    if effect_class(h.name) == "drag" and (found_name != h.name or truth.drag_law is not None):
        if drag is None:
            return None, "no airspeed data"
        nominal_laws = _drag_laws(nominal)
        true_laws = [law for law in nominal_laws if law[0] != h.name]
        true_laws.append(truth.drag_law or (h.name, h.params))
        found_laws = [law for law in nominal_laws if law[0] != found_name] + [(found_name, found)]
        k_true = drag.linear_equivalent(true_laws)
        k_found = drag.linear_equivalent(found_laws) * per_mass
        err = abs(k_found - k_true) / max(abs(k_true), 1e-12)
        return err, f"k_eq {k_found:.4g} vs {k_true:.4g} N/(m/s)"
    if found_name != h.name:  # mass <-> thrust coefficient: thrust per unit mass
        m0 = nominal.mass_kg

        def ratio(name, p):
            return p["kt_scale"] if name == "thrust_coefficient" else m0 / p["mass"]
        r_true, r_found = ratio(h.name, h.params), ratio(found_name, found)
        err = abs(r_found / r_true - 1.0)
        if h.name == "mass":
            return err, f"mass~{m0 / r_found:.4g} vs {h.params['mass']:.4g}"
        return err, f"kt_scale~{r_found:.4g} vs {h.params['kt_scale']:.4g}"
    skip = frozenset(k for k in not_identified if k in h.params)
    held_text = f"; {', '.join(sorted(skip))} not identified (held)" if skip else ""
    err = _param_error(h, found, skip)
    vec = _vector_error(h.name, h.params, found)
    if vec is not None and err is not None and math.isfinite(err) and vec[0] >= err:
        keys = vec[1]
        return err, (f"({', '.join(f'{found[k]:.3g}' for k in keys)}) vs ({', '.join(f'{h.params[k]:.3g}' for k in keys)})"
                     f" |error|/|truth|")
    worst, worst_e = None, -1.0
    for k, true in h.params.items():
        if k in ("gust_std", "motor") or k not in found or k in skip:
            continue
        e = abs(found[k] - true) / max(abs(true), 1e-9)
        if e > worst_e:
            worst, worst_e = k, e
    if err is None or not math.isfinite(err) or worst is None:
        return err, ("motor index wrong" if err is not None and not math.isfinite(err) else "-") + held_text
    return err, f"{worst} {found[worst]:.4g} vs {h.params[worst]:.4g}{held_text}"


def ridge_reading(truth: Truth, found: dict, ground_fit: dict | None) -> tuple[float, str] | None:
    """A ground effect whose finding says the flight pins only its extra thrust near h_ref (discovery's
    ``stages.ground``: a low hover at one height, ``determined`` False) and reads the coefficient and height scale
    along that ridge to a stated range (``ridge``): where both true values lie inside the ranges, scored as the
    one reading the flight gives, c exp(-h_ref/h_s) against the truth's at the same height (as a mass and a thrust
    coefficient are scored as thrust per unit mass); the parameters' own values are named in the text.  None
    where the finding does not say so or a truth lies outside its range (then each parameter is scored)."""
    gf = ground_fit or {}
    ridge, h = gf.get("ridge"), truth.hidden
    if h.name != "ground_effect" or gf.get("determined") is not False or not ridge or "h_ref_m" not in gf:
        return None
    c_t, hs_t = h.params["coefficient"], h.params["height_scale"]
    (c_lo, c_hi), (hs_lo, hs_hi) = ridge["coefficient_range"], ridge["height_scale_range_m"]
    if not (c_lo <= c_t <= c_hi and hs_lo <= hs_t <= hs_hi):
        return None
    from twin_nodes.discovery.stages.ground import gain   # the ground effect's law, in one place

    h_ref = gf["h_ref_m"]
    g_t = float(gain(c_t, hs_t, h_ref)) - 1.0
    g_f = float(gain(found["coefficient"], found["height_scale"], h_ref)) - 1.0
    return abs(g_f / g_t - 1.0), (f"c exp(-{h_ref:.3g}/h_s) {g_f:.4g} vs {g_t:.4g} (not told apart on this flight: "
                                  f"coefficient {found['coefficient']:.3g} vs {c_t:.3g} in {c_lo:.3g}-{c_hi:.3g}, "
                                  f"height_scale {found['height_scale']:.3g} vs {hs_t:.3g} in {hs_lo:.3g}-{hs_hi:.3g})")


def score_flight(flight: str, truth: Truth, result: dict, nominal: VehicleParams,
                 drag: DragContext | None = None, **facts) -> dict:
    """One row of a prove table from a discover() result (see the rules above)."""
    h = truth.hidden
    found = findings(result)
    top = found[0] if found else None
    right = top is not None and h.name != "none" and effect_class(top["name"]) == effect_class(h.name)
    # not scored: the true effect is the top finding's alternative, one the flight cannot tell apart
    # from it (e.g. a motor lag and a pure delay on a 50 Hz log); shown beside the score
    tied = bool(top is not None and not right and h.name != "none" and any(
        effect_class(a.get("name", "")) == effect_class(h.name) for a in top.get("alternatives") or []))
    err, text = (compare(truth, top["name"], top["params"], nominal, drag) if right else (None, "-"))
    ho = heldout_cut(top) if top else {}
    cut = ho.get("improvement")
    if h.name == "none":
        passed = not found
    else:
        passed = bool(right and err is not None and err <= 0.10 and cut is not None and cut >= 0.5)
    return {"flight": flight, "true_effect": h.label, "true_params": h.params, "truth_text": truth.text,
            "top_finding": top["name"] if top else "none", "top_verdict": verdict(top) if top else "-",
            "findings": [f"{e['name']} ({verdict(e)})" for e in found], "n_findings": len(found),
            "right_class": right, "true_is_alternative": tied, "found_params": top["params"] if top else {},
            "param_error": err, "param_text": text,
            "heldout_channel": ho.get("channel"), "heldout_residual": ho.get("residual"),
            "heldout_before": ho.get("before"), "heldout_after": ho.get("after"),
            "heldout_improvement": cut, "passed": passed,
            # the names the ours suite has always used (tests and older summaries read them)
            "top_accepted": top["name"] if top else "none", "n_accepted": len(found),
            # what discovery ranked first when nothing was found (a rejected candidate): shown, never scored
            "first_candidate": (result.get("effects") or [{}])[0].get("name") if not top else None,
            "elapsed_s": result.get("elapsed_s"), **facts}


def write_result(path: Path, res: dict) -> None:
    from twin_nodes.base.io import atomic_write_text

    atomic_write_text(path, json.dumps(res, indent=1, default=_json_default))


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return float(o)


def map_jobs(fn, jobs: list, workers: int, desc: str, progress: bool = True) -> list:
    """``[fn(j) for j in jobs]``, over ``workers`` processes when more than one, with a progress bar."""
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as ex:
            it = ex.map(fn, jobs)
            if progress:
                from tqdm import tqdm
                it = tqdm(it, total=len(jobs), desc=desc, unit="flight")
            return list(it)
    it = jobs
    if progress:
        from tqdm import tqdm
        it = tqdm(jobs, desc=desc, unit="flight")
    return [fn(j) for j in it]


def score(rows: list[dict], source: str = "ours") -> dict:
    """Per-source accuracy: the issue's four numbers and the flights that pass every rule."""
    with_eff = [r for r in rows if r["true_effect"] != "none"]
    none = [r for r in rows if r["true_effect"] == "none"]
    right = [r for r in with_eff if r.get("right_class", r["top_accepted"] == r["true_effect"])]
    false_acc = [r for r in none if r["n_accepted"] > 0]
    improved = [r for r in right if (r["heldout_improvement"] or 0) >= 0.5]
    within = [r for r in right if r["param_error"] is not None and r["param_error"] <= 0.10]
    passed = [r for r in rows if r.get("passed")]
    tied = [r for r in with_eff if r.get("true_is_alternative")]
    return {
        "source": source,
        "rows": rows,
        "n_effect_flights": len(with_eff),
        "n_no_effect_flights": len(none),
        "n_right_top": len(right),
        "right_top_fraction": len(right) / max(len(with_eff), 1),
        "false_accepts_on_no_effect": len(false_acc),
        "heldout_improved_50pct_fraction": len(improved) / max(len(right), 1),
        "params_within_10pct_fraction": len(within) / max(len(right), 1),
        "n_heldout_50pct": len(improved),
        "n_params_within_10pct": len(within),
        "n_passed": len(passed),
        "n_true_is_alternative": len(tied),
        "n_flights": len(rows),
    }


def breakdown(summary: dict, key: str) -> list[str]:
    """The summary line of each group of rows that share ``row[key]`` (e.g. the PX4 SIH flights'
    ``logging`` profile or ``sih_change``); nothing when no row has ``key`` or there is one group."""
    groups: dict[str, list[dict]] = {}
    for r in summary["rows"]:
        if key in r:
            groups.setdefault(str(r[key]), []).append(r)
    if len(groups) < 2:
        return []
    return [summary_line(score(rows, source=f"{summary.get('source', 'ours')} [{key} {name}]"))
            for name, rows in sorted(groups.items())]


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


def format_table(summary: dict) -> str:
    """One source's table: flight, true effect, top finding + verdict, parameter vs truth, held-out cut,
    pass/fail; then the summary line."""
    rows = summary["rows"]
    track = any("xy_tracking_rmse_m" in r for r in rows)
    fw = max([len("flight")] + [len(r["flight"]) for r in rows])
    head = (f"{'flight':<{fw}}  {'true effect':<20} {'top finding (verdict)':<32} {'parameter vs truth':<36} "
            f"{'param err':>9} {'held-out':>15} {'cut':>5} {'in':<14} {'result':<6}")
    if track:
        head += f" {'XY trk':>7} {'Z trk':>6}"
    lines = [head]
    for r in rows:
        top = "none" if r["top_accepted"] == "none" else f"{r['top_accepted']} ({r.get('top_verdict', 'confirmed')})"
        if top == "none" and r["true_effect"] != "none" and r.get("first_candidate"):
            top = f"none [1st: {r['first_candidate']}]"
        if r.get("n_findings", r["n_accepted"]) > 1:
            top += f" +{r.get('n_findings', r['n_accepted']) - 1}"
        pe = r["param_error"]
        pe_s = "-" if pe is None else ("wrong" if not math.isfinite(pe) else f"{100 * pe:.1f} %")
        ho = "-" if r["heldout_before"] is None else f"{r['heldout_before']:.3f}->{r['heldout_after']:.3f}"
        ok = "pass" if r.get("passed") else "FAIL"
        where = "-" if not r.get("heldout_channel") else \
            f"{r['heldout_channel']} ({str(r.get('heldout_residual') or 'equation')[:3]})"
        line = (f"{r['flight']:<{fw}}  {r['true_effect']:<20} {top:<32} {r.get('param_text', '-'):<36} {pe_s:>9} "
                f"{ho:>15} {_pct(r['heldout_improvement']):>5} {where:<14} {ok:<6}")
        if track:
            line += f" {r.get('xy_tracking_rmse_m', math.nan):>6.2f}m {r.get('z_tracking_rmse_m', math.nan):>5.2f}m"
        lines.append(line.rstrip())
    lines.append(summary_line(summary))
    lines += breakdown(summary, "logging") + breakdown(summary, "sih_change")
    return "\n".join(lines)


def summary_line(summary: dict) -> str:
    s = summary
    return (f"{s.get('source', 'ours')}: right effect on top {s['n_right_top']}/{s['n_effect_flights']} "
            f"({_pct(s['right_top_fraction'])}); findings on no-effect flights "
            f"{s['false_accepts_on_no_effect']}/{s['n_no_effect_flights']}; params within 10 % "
            f"{s['n_params_within_10pct']}/{s['n_right_top']}; held-out cut >= 50 % "
            f"{s['n_heldout_50pct']}/{s['n_right_top']}; flights passing every rule {s['n_passed']}/{s['n_flights']}"
            + (f" (not scored: on {s['n_true_is_alternative']} more the true effect is the top finding's "
               "not-told-apart alternative)" if s.get("n_true_is_alternative") else ""))
