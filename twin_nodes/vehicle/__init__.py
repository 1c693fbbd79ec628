"""The vehicle description: parameter files (schema, validation, YAML), the paper's derivations, PX4/Gazebo export and rotor geometry.

May import: base, physics.
"""
