"""Fleet scale: one task per flight on Dask, the Parquet flight catalog (DuckDB), per-vehicle trends, alarms and the fleet report.

May import: base, physics, vehicle, logs, twin, identify, discovery.
"""
