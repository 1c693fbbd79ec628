"""The twin beside a flight: the PX4-like controller, the simulator, the streaming TwinRunner, comparison, metrics and the compare report.

May import: base, physics, vehicle, logs.
"""
