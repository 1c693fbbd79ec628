"""Missing-physics discovery: equation-error residuals, candidate effects, cross-validated selection, refit, confirmation plans and the report.

May import: base, physics, vehicle, logs, twin, identify.

The evidence that it works (the prove suite) is :mod:`twin_nodes.prove`, which imports this package;
nothing here imports it (``tests/test_layout.py``).
"""
