"""Barrier design from a hazard run (``python -m calib.design HAZARD.nc --barrier-x-m X``).

The design values of UNI 11211-4 as practised in Italy (Peila & Ronco 2009, NHESS
9:1291) at a barrier position, from the per-draw percentiles a hazard run records
at every station (``calib.files.hazard_results``): design block, partial factors
with their sources (``_factors``), checks against a kit catalogue (``_kits``,
``_checks``), posterior bands and Monte Carlo errors (``_values``), probabilities
and impacts without partial factors, the calibration's own predictive check, and
the residual hazard of a run with the barrier (``_residual``).

Modules: ``_factors`` (factors, rules, sources), ``_kits`` (catalogue CSV),
``_values`` (design values at a station), ``_checks`` (kit checks, probabilities,
impacts), ``_inputs`` (checked command-line inputs), ``_design`` (the record of
one design, scans), ``_residual`` (with and without the barrier), ``_report``
(design.md, design.json), ``_figures`` (PNG), ``__main__`` (command line).
"""

from calib.design._checks import check_kits, impacts, kit_probabilities, smallest_passing
from calib.design._factors import DEFAULTS, GAMMA_E, SOURCES, Factors, free_board_m
from calib.design._kits import Kit, KitError, load_kits
from calib.design._residual import residual_exceedance
from calib.design._values import DesignBlock, DesignValues, design_values

__all__ = [
    "DEFAULTS",
    "GAMMA_E",
    "SOURCES",
    "DesignBlock",
    "DesignValues",
    "Factors",
    "Kit",
    "KitError",
    "check_kits",
    "design_values",
    "free_board_m",
    "impacts",
    "kit_probabilities",
    "load_kits",
    "residual_exceedance",
    "smallest_passing",
]
