"""Missing-physics discovery: locate the mismatch, name the physics left out, grade it, refit, show it on held-out data.

Two residuals judge the candidates:

- the **equation error** (:mod:`twin_nodes.discovery.residuals`): measured specific force and
  angular acceleration minus what the model predicts from the logged motor commands, per motor and
  horizontal force, low-passed at 2 Hz.  Forces that act at every sample (mass, thrust, drag,
  wind, ground effect, a weak motor...) show here.
- the **output error** (:mod:`twin_nodes.discovery.output_error`): the model flown open loop for
  0.4 s from the logged state at the start of each window, driven by the logged motor commands,
  compared on body rates and velocity.  What acts through the dynamics (rotor lag, delay, inertia,
  the reaction torque of a yaw manoeuvre) shows here; the equation error's 2 Hz low-pass hides it.

Method:

1. **Locate** (:mod:`twin_nodes.discovery.locate`): every channel (collective, roll, pitch and yaw
   moments, each motor, horizontal force): 2-s windows whose equation error is above 3x the
   channel's noise floor, by flight regime; and per channel its *excitation*, the number of
   held-out blocks that carry signal and the manoeuvres they come from.
2. **Name.**  Every candidate effect (:mod:`twin_nodes.discovery.candidates`) is fitted on 65 % of
   the flight and judged on the rest, both ways round (2-fold cross-validation), on the equation
   error; the dynamic ones (``OUTPUT_ERROR_EFFECTS``) also on the output error, on the axes the
   nominal model predicts credibly there.  Accepted (``confirmed``) only if its size is above the
   physical resolution floor, it is inside the physical range, it lowers the held-out residual in
   a block test (t, sign or sign-flip test > 3 over independent blocks) and explains >= 10 % of
   the held-out residual.  Greedy forward selection: accept the best, refit the others on top.
3. **Grade** (:mod:`twin_nodes.discovery.verdicts`): ``confirmed``, ``likely`` (a large held-out cut
   and a clear parameter, but too few excited blocks for the test: how many are missing and which
   manoeuvre supplies them) or ``rejected``.
4. **Refit** all accepted effects jointly; report before/after on the held-out part.
"""

from __future__ import annotations

import time

from twin_nodes.discovery.blocktest import N_FLIPS, _block_stats, _block_test, _flip_sums
from twin_nodes.discovery.judging import (ALT_FRACTION, BLOCK_S, HELDOUT_FRACTION, JOINT_STARTS, JOINT_STARTS_LEAN,
                                          MAX_EFFECTS, MIN_REL_IMPROVEMENT, MOTOR_DYNAMICS, OE_BLOCK_S, OE_FIT_WINDOWS,
                                          OE_MIN_CHANGE, OUTPUT_ERROR_EFFECTS, PRUNE_GAIN, T_CHOICE, T_CRIT, Fit, Judge,
                                          _affine_form, _blocks, _equation_judge, _fold_fit, _fold_fits, _mode_rms,
                                          _output_judge, _restrict_to_axes, _scales, _summary, _window_folds, assess,
                                          fit_candidate)
from twin_nodes.discovery.locate import regimes
from twin_nodes.discovery.stages import (closed_loop, damping_pair, ground, inertia_given, instrument, mismatch,
                                        prepare, refit, report, retrim, selection, stand_in, terms, verdicts,
                                        yaw_pair, yaw_scale)
from twin_nodes.discovery.stages.closed_loop import CLOSED_LOOP_TOL_REL, _closed_loop_guard, _closed_loop_metrics, _worse
from twin_nodes.discovery.stages.instrument import (INSTRUMENTED_BLOCKS_MISSING, _axis_tests, _equation_axes,
                                                    _instrumented, attach_instrumented)
from twin_nodes.discovery.stages.motor_lag import rate_loop_lag as _rate_loop_lag
from twin_nodes.discovery.stages.prepare import PreparedFlight, prepare_flight
from twin_nodes.discovery.stages.refit import _joint_refit
from twin_nodes.discovery.stages.selection import _one_variant, _parsimonious, _pick, _tie_break
from twin_nodes.vehicle.params import VehicleParams

#: the names discovery had here before it was split into stages (tests, bench and other modules import them)
__all__ = [
    "discover", "N_FLIPS", "_block_stats", "_block_test", "_flip_sums", "ALT_FRACTION", "BLOCK_S", "HELDOUT_FRACTION",
    "JOINT_STARTS", "JOINT_STARTS_LEAN", "MAX_EFFECTS", "MIN_REL_IMPROVEMENT", "MOTOR_DYNAMICS", "OE_BLOCK_S",
    "OE_FIT_WINDOWS", "OE_MIN_CHANGE", "OUTPUT_ERROR_EFFECTS", "PRUNE_GAIN", "T_CHOICE", "T_CRIT", "Fit", "Judge",
    "_affine_form", "_blocks", "_equation_judge", "_fold_fit", "_fold_fits", "_mode_rms", "_output_judge",
    "_restrict_to_axes", "_scales", "_summary", "_window_folds", "assess", "fit_candidate", "regimes",
    "CLOSED_LOOP_TOL_REL", "_closed_loop_guard", "_closed_loop_metrics", "_worse", "INSTRUMENTED_BLOCKS_MISSING",
    "_axis_tests", "_equation_axes", "_instrumented", "_rate_loop_lag", "attach_instrumented", "PreparedFlight",
    "prepare_flight", "_joint_refit", "_one_variant", "_parsimonious", "_pick", "_tie_break"]

def discover(log, vp: VehicleParams, *, heldout_fraction: float = HELDOUT_FRACTION, max_effects: int = MAX_EFFECTS,
             progress: bool = False, closed_loop_metrics: bool = True, output_error: bool = True) -> dict:
    """Run discovery on a FlightLog with nominal params ``vp``; returns the JSON-ready result.

    The stages of :mod:`twin_nodes.discovery.stages`, in order (``docs/ARCHITECTURE.md``, "Discovery stages")."""
    t_start = time.time()
    # 1. the flight prepared once: data, the 2-fold split, both residuals' judges, excitation
    flight = prepare.run(prepare.FlightInput(log, vp, heldout_fraction, output_error))
    closed_loop.reset()
    if closed_loop_metrics:
        # the nominal twin's closed-loop run, in another process while the candidates are fitted
        closed_loop.prefetch(log, vp, flight)
    # 2. locate: where the nominal misses, per channel and regime
    found = mismatch.run(flight)
    # 3. name: greedy forward selection; each round lists the candidates on top of what is accepted
    # and judges them on both residuals, cross-validated
    chosen = selection.run(selection.SelectionInput(
        flight, max_effects, progress,
        on_first=(lambda vp_1: closed_loop.prefetch(log, vp_1, flight)) if closed_loop_metrics else None))
    # 4. refit what is accepted, jointly; 5. keep what does not make the closed-loop twin worse
    joint = refit.run(refit.RefitInput(flight, chosen.accepted, chosen.current))
    checked = closed_loop.run(closed_loop.CheckInput(log, flight, chosen.accepted, joint.vp, closed_loop_metrics))
    # a ground effect's size from the take-off and the landing together (each fold sees one), after the check
    # (which refits what it keeps on fold 1): stages.ground
    regrounded = ground.refit_accepted(flight, checked.accepted, checked.current, chosen.last)
    if regrounded is not checked.current and checked.closed is not None:
        # refitted from the nominal: its static trims remade as the check's were (stages.retrim)
        regrounded = retrim.retrim_for_flight(regrounded, flight.nominal, flight.data)
    checked.current = regrounded
    # an inertia accepted on the output error, judged again given the effects accepted beside it
    checked.accepted, checked.current = inertia_given.run(flight.oe, checked.accepted, checked.current, flight.eq)
    # an equation-error effect accepted before others that adds nothing given them: a stand-in, not kept
    checked.accepted, checked.current = stand_in.run(flight.eq, checked.accepted, checked.current)
    # 6. grade: confirmed, likely (what it lacks), rejected (why)
    graded = verdicts.run(verdicts.GradeInput(flight, checked.accepted, chosen.last, chosen.first_rank,
                                              found.base_held))
    verdicts.given_the_others(graded, flight.eq, checked.current, checked.accepted)
    # a likely lag and a likely delay, each fitted without the other: one kept, the other its pair unless it adds
    verdicts.lag_delay_pair(graded, flight.eq, checked.accepted)
    inertia_given.annotate(graded.ranked, graded.effects)
    ground.annotate(flight, graded.ranked, graded.effects)
    # 7. on PX4 logs: the inertia's roll/pitch axes and PX4's rate loop, the closed-loop twin permitting
    final = instrument.run(instrument.InstrumentInput(
        flight, graded, checked.current, closed_loop.guard(checked, log, flight, closed_loop_metrics)))
    # 8. before/after on the held-out part, the closed-loop twin's metrics
    result = report.run(report.ReportInput(log, flight, found, checked, graded, final, closed_loop_metrics,
                                           t_start)).result
    # 9. physics outside the effect list: the structured residual test, a sparse term, named and flown
    result = terms.run(terms.TermsInput(log, flight, checked.accepted, final.current, result,
                                        closed_loop_metrics)).result
    # 10. a yaw moment or yaw inertia beside a damping: the yaw axis gives their ratios only, roll/pitch choose
    yaw_pair.apply(result, flight)
    # 11. a yaw moment or yaw inertia alone: each reading's yaw error per its yaw scale, pair where they tie
    yaw_scale.apply(result, flight)
    # 12. a damping alone on the yaw axis: a rotor drag's hub damping (no airspeed), or a yaw moment and inertia together
    damping_pair.apply(result, flight)
    return result
