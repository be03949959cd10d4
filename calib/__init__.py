"""Calibration, hazard and discrepancy analysis on top of the solvers.

Modules (one concept each):

* ``observations``: the observed-runout table (load, validate) and the block-size
  mapping shared by every model.
* ``likelihood``: the observation model (simulated runout distribution vs an
  observed point or interval), the one every fit scores rows with.
* ``alpha_law``: the DEM damping law alpha(L) and its one clipping rule.
* ``dem_run``: the DEM numerics (stiffness scale, time limit, step bound) of
  every DEM run (fit, discrepancy candidates, hazard).
* ``crsp_fit`` / ``dem_fit``: the objective of each solver, evaluated with common
  random numbers.
* ``gradient``: the smoothed-gradient estimator and the optax loop.
* ``emulator`` / ``bayes``: the smooth emulator and the NumPyro posterior with
  its ArviZ diagnostics; ``inference_data``: that posterior as ArviZ
  InferenceData (NetCDF), written and read back.
* ``importance``: Pareto-smoothed importance weights and their k-hat (the
  discrepancy workflow's fits and held-out scores).
* ``fit``: the command ``python -m calib.fit``.
"""

import solvers  # noqa: F401  (enables float64)
