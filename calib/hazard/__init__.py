"""Hazard: Monte Carlo over calibrated parameters, runout exceedance curves and
hazard tables (``python -m calib.hazard results/calibration.json``).

For each of a set of posterior draws (or the point estimate), blocks of each
size (or of each volume class of a block-volume law, released over a zone at
drawn heights and speeds: ``calib.model.release``; with an optional protection
barrier, ``Barrier``) are simulated with the calibrated solver, and at every
analysis station x the run reports the runout exceedance P(x_stop > x) with its posterior bands,
the reach probability, energy / bounce-height / velocity design values of the
blocks that pass x, the Swiss intensity class and, given a release rate, the
annual frequencies and hazard level. See ``_tables`` for the definitions,
``_intensity`` for the intensity-frequency matrix and its sources (part of it
recalled, not verified: labelled there), ``_units`` for the random numbers,
``_stats`` for the bounded-memory reductions, ``_sharding`` for devices.

Modules: ``calib.files.calibration_file`` (read calibration.json, draw parameter sets),
``_units`` (jitted simulate-and-reduce chunks), ``_sharding`` (devices),
``_run`` (the Monte Carlo loop), ``_stats`` (counts, histograms, quantiles),
``_tables`` (CSV tables and text summary), ``_intensity`` (classes, matrix),
``_figures`` (PNG), ``__main__`` (command line).
"""

import solvers  # noqa: F401  (enables float64)
from calib.files.calibration_file import (
    SCHEMA,
    Calibration,
    CalibrationError,
    Draws,
    draw_parameters,
    load_calibration,
)
from calib.hazard._figures import plot_envelopes, plot_exceedance
from calib.hazard._intensity import (
    ENERGY_THRESHOLDS_KJ,
    hazard_level,
    intensity_class,
    probability_class,
)
from calib.hazard._results import calibration_record, hazard_dataset
from calib.hazard._run import (
    HAZARD_SETTINGS,
    Barrier,
    HazardCounts,
    check_dem_draws,
    default_release_x_m,
    dem_alpha,
    run_hazard,
)
from calib.hazard._stats import BINS, Bins, hist_exceedance, hist_quantile
from calib.hazard._tables import exceedance_table, hazard_table, summary_text
from calib.model.dem_run import DemRun

__all__ = [
    "BINS",
    "Barrier",
    "ENERGY_THRESHOLDS_KJ",
    "HAZARD_SETTINGS",
    "SCHEMA",
    "Bins",
    "Calibration",
    "CalibrationError",
    "DemRun",
    "Draws",
    "HazardCounts",
    "calibration_record",
    "check_dem_draws",
    "default_release_x_m",
    "dem_alpha",
    "draw_parameters",
    "exceedance_table",
    "hazard_dataset",
    "hazard_level",
    "hazard_table",
    "hist_exceedance",
    "hist_quantile",
    "intensity_class",
    "load_calibration",
    "plot_envelopes",
    "plot_exceedance",
    "probability_class",
    "run_hazard",
    "summary_text",
]
