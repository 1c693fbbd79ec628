"""Identification of a multirotor's parameters from data: the fits, their flight-log adapters, results and figures.

May import: base, physics, vehicle, logs.

Reference 2, "Quad-C model verification".  Pure numpy/scipy functions on arrays;
:mod:`.from_log` adapts flight logs to them, one function per ``rotortwin identify``
method (:mod:`twin_nodes.cli.identify` only parses arguments and writes the output).

- :mod:`.step_response` motor ``K/(tau s + 1)`` (+ delay, up/down) fit and its ZOH difference equation
- :mod:`.hover` steady-hover segments, hover throttle, ``kt = m g / (N omega^2)``
- :mod:`.delay` command -> response delay by cross-correlation, sub-sample, with a bootstrap interval
- :mod:`.regression` equation-error least squares with SVD / structural identifiability
- :mod:`.noise` IMU bias, white noise, Allan deviation and the params ``sensors`` block
- :mod:`.from_log` the above on a :class:`~twin_nodes.logs.ulog_io.FlightLog` (airborne masks, heights
  above take-off, angular acceleration, rotor geometry, delay pairs)
- :mod:`.results` one result type per method: parameter-file block, report, console summary, figure
- :mod:`.plots` figures (Agg canvas)
"""

from twin_nodes.identify.delay import DelayEstimate, estimate_delay
from twin_nodes.identify.hover import (HoverSegment, HoverSummary, detect_hover_segments, hover_mask,
                                       kt_from_hover, params_from_hover_command, summarize_hover)
from twin_nodes.identify.noise import (AllanResult, ImuNoise, allan_deviation, analyse_allan, imu_noise,
                                       sensors_block, stationary_runs)
from twin_nodes.identify.regression import (LinearFit, RotorGeometry, StructuralResult, fit_linear,
                                            rotational_regression, rotor_states_from_commands,
                                            structural_identifiability, thrust_regressor,
                                            translational_regression)
from twin_nodes.identify.step_response import (DiscreteLag, StepFit, c2d_scipy, discretize_zoh,
                                               fit_step_response, read_step_csv, simulate_lag)

__all__ = [
    "DelayEstimate", "estimate_delay",
    "HoverSegment", "HoverSummary", "detect_hover_segments", "hover_mask", "kt_from_hover",
    "params_from_hover_command", "summarize_hover",
    "AllanResult", "ImuNoise", "allan_deviation", "analyse_allan", "imu_noise", "sensors_block",
    "stationary_runs",
    "LinearFit", "RotorGeometry", "StructuralResult", "fit_linear", "rotational_regression",
    "rotor_states_from_commands", "structural_identifiability", "thrust_regressor", "translational_regression",
    "DiscreteLag", "StepFit", "c2d_scipy", "discretize_zoh", "fit_step_response", "read_step_csv",
    "simulate_lag",
]
