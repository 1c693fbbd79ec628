"""Missing-physics discovery: equation-error residuals, candidate effects, cross-validated selection, refit, the report and the prove suite.

May import: base, physics, vehicle, logs, twin, identify.
"""
