"""Discovery as stages: one module per stage, each ``run(input) -> output`` with one input and one
output dataclass (``docs/ARCHITECTURE.md``, "Discovery stages").  :func:`twin_nodes.discovery.discover.discover`
runs them in order:

1. :mod:`.prepare`: the flight, prepared once (``FlightInput`` -> ``PreparedFlight``)
2. :mod:`.mismatch`: the located mismatch (``PreparedFlight`` -> ``Mismatch``)
3. :mod:`.selection`: greedy forward selection (``SelectionInput`` -> ``Selection``); each round runs
   3a. :mod:`.candidates` (``CandidateQuery`` -> ``CandidateSet``) and
   3b. :mod:`.judge` (``JudgeQuery`` -> ``JudgedFits``, the fits per residual)
   (where nothing passes but a ``likely`` fit is solid, one provisional round on top of it:
   :mod:`.provisional`)
4. :mod:`.refit`: the accepted effects refitted jointly (``RefitInput`` -> ``Refit``)
5. :mod:`.closed_loop`: the closed-loop check (``CheckInput`` -> ``Checked``)
5b. :mod:`.inertia_given`: an output-error inertia judged again given the others (``run``)
5c. :mod:`.stand_in`: an equation-error effect accepted before others, judged again given them (``run``)
6. :mod:`.verdicts`: confirmed / likely / rejected (``GradeInput`` -> ``Verdicts``)
7. :mod:`.instrument`: on PX4 logs, the inertia's roll/pitch axes and PX4's rate loop
   (``InstrumentInput`` -> ``Instrumented``)
8. :mod:`.report`: the JSON-ready result (``ReportInput`` -> ``Report``)
9. :mod:`.terms`: physics outside the effect list: the structured residual test, a sparse term named,
   flown and graded (``TermsInput`` -> ``Terms``, adds ``terms`` to the result)
10. :mod:`.yaw_pair`: a yaw moment or yaw inertia beside a damping, read on roll/pitch (``apply`` on the
    result; adds ``yaw_pair``)
"""
