"""Inputs and outputs: observations, profiles' site files, the calibration file
and its posterior (CSV, NetCDF), provenance, field runs, the hold-out split.

``docs/architecture.md`` maps every module.
"""
