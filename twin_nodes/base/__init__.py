"""Foundations every layer may use: one-line errors and the only NED/FRD <-> ENU/FLU frame conversion.

May import: nothing from twin_nodes.
"""
