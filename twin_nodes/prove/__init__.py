"""The evidence for discovery: flights with one known change each, discovered blind, scored per source.

May import: base, physics, vehicle, logs, twin, identify, discovery.

Discovery (the method) never imports this package; ``tests/test_layout.py`` fails if it does.

- :mod:`.ours` our generator's suite: one hidden effect per flight at a realistic strength, flown and
  logged like PX4 by :mod:`twin_nodes.twin.simflight`
- :mod:`.sih` PX4 SIH flights (real firmware) with one SIH parameter changed, and their truth
- :mod:`.rotorpy_flights` flights flown in RotorPy (its vehicle, aerodynamics, wind and SE(3) controller)
- :mod:`.scoring` the rules every source is scored by, one row per flight, the tables
- :mod:`.sources` ``rotortwin prove --source``: each source in turn
- :mod:`.grid_rotorpy`, :mod:`.grid_missions`, :mod:`.grid_sih` issue 26's declared grids (RotorPy, PX4 SIH)
  and :mod:`.grid_prove` their scoring with one or two effects per flight (``rotortwin prove --grid``)
"""
