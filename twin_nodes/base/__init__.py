"""Foundations every layer may use: one-line errors, the only NED/FRD <-> ENU/FLU frame conversion, constants.

May import: nothing from twin_nodes.
"""
