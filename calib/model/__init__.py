"""The calibrated model: prior boxes, candidate effects, forward models (CRSP and
DEM runs of parameter sets), the DEM damping law and run configuration,
unfinished blocks.

``docs/architecture.md`` maps every module.
"""
