"""Barrier design from a hazard run (``python -m calib.design HAZARD.nc --barrier-x-m X``).

The design values of UNI 11211-4 as practised in Italy (Peila & Ronco 2009, NHESS
9:1291) at a barrier position, from the per-draw percentiles a hazard run records
at every station (``calib.files.hazard_results``): design block, partial factors
with their sources (``_factors``), checks against a kit catalogue (``_kits``,
``_checks``), posterior bands and Monte Carlo errors (``_values``), probabilities
and impacts without partial factors, the calibration's own predictive check, and
the residual hazard of a run with the barrier (``_residual``), the impact angle
from a run with the barrier element (``_angles``).

In a script or notebook: ``design_block`` and ``design_at`` on a results Dataset
(``calib.files.hazard_results.read_hazard_results``, or
``calib.hazard.hazard_dataset`` of a run) give a typed ``Design``; ``scan_rows``
the design along positions.

Modules: ``_factors`` (factors, rules, sources), ``_kits`` (catalogue CSV),
``_values`` (design values at a station), ``_checks`` (kit checks, probabilities,
impacts), ``_inputs`` (checked inputs), ``_design`` (one design, its record,
scans), ``_angles`` (impact angles), ``_residual`` (with and without the barrier), ``_report``
(design.md, design.json), ``_figures`` (PNG), ``__main__`` (command line).
"""

from calib.design._angles import ImpactAngles, impact_angles
from calib.design._checks import check_kits, impacts, kit_probabilities, smallest_passing
from calib.design._design import (
    Design,
    DesignOptions,
    best_position,
    design_at,
    design_record,
    scan_rows,
)
from calib.design._factors import DEFAULTS, GAMMA_E, SOURCES, Factors, free_board_m
from calib.design._figures import (
    distributions_figure,
    exceedance_figure,
    profile_figure,
    scan_figure,
)
from calib.design._inputs import DesignError, design_block
from calib.design._kits import Kit, KitError, load_kits
from calib.design._report import posterior_warning
from calib.design._residual import residual_exceedance
from calib.design._values import DesignBlock, DesignValues, design_values

__all__ = [
    "DEFAULTS",
    "GAMMA_E",
    "SOURCES",
    "Design",
    "DesignBlock",
    "DesignError",
    "DesignOptions",
    "DesignValues",
    "Factors",
    "ImpactAngles",
    "Kit",
    "KitError",
    "best_position",
    "check_kits",
    "design_at",
    "design_block",
    "design_record",
    "design_values",
    "distributions_figure",
    "exceedance_figure",
    "free_board_m",
    "impact_angles",
    "impacts",
    "kit_probabilities",
    "load_kits",
    "profile_figure",
    "posterior_warning",
    "residual_exceedance",
    "scan_figure",
    "scan_rows",
    "smallest_passing",
]
