"""Calibration, hazard and discrepancy analysis on top of the solvers.

The map of the modules, grouped by workflow stage (commands; inputs and
outputs; model; inference; discovery; hazard; validation; plots), and the data
flow from an observations CSV to a calibration file, hazard tables and a
predictive check, is ``docs/architecture.md`` (a test keeps it true).
"""

import solvers  # noqa: F401  (enables float64)
