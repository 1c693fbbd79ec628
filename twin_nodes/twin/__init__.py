"""The twin beside a flight: the PX4-like controller, the simulator, simulated PX4-like flights with a hidden effect (``simflight``), the streaming TwinRunner, comparison, metrics and the compare report.

May import: base, physics, vehicle, logs.
"""
