"""A run's ``HazardCounts`` as the hazard results Dataset (``calib.files.hazard_results``),
the one object the tables, the figures, ``hazard.nc`` and ``calib.design`` read."""

from __future__ import annotations

import numpy as np

from calib.files.hazard_results import hazard_results
from calib.hazard._run import HazardCounts
from calib.hazard._stats import BINS, DRAW_BINS, PERCENTILES
from solvers.jsonable import json_ready
from solvers.profile import Profile

__all__ = ["ENERGY_BASIS", "HEIGHT_CONVENTION", "as_results", "calibration_record",
           "hazard_dataset"]

ENERGY_BASIS = {
    "crsp": "kJ per block: the CRSP block of the volume of the sphere of diameter D "
            "(block_mass_kg)",
    "dem": "kJ per block taken as a cube of side D: the 2D DEM's energy per metre of width "
           "times D (calib.hazard._units; an assumption, the 2D runs have no thickness)",
}
HEIGHT_CONVENTION = ("bounce_height_m is the clearance: the vertical height of the block's "
                     "lowest point above the ground at the station (solvers.stations); the "
                     "block's top is D higher")


def _zone_at(profile: Profile, x_m: np.ndarray) -> list[str]:
    xs = np.asarray(profile.x_m)
    seg = np.clip(np.searchsorted(xs, x_m, side="right") - 1, 0, len(xs) - 2)
    names = profile.segment_zone_names()
    return [names[i] for i in seg]


def hazard_dataset(c: HazardCounts, profile: Profile | None = None, *, seed: int | None = None,
                   road_x_m: float | None = None, road_label: str | None = None,
                   release_rate_per_year: float | None = None, record: dict | None = None,
                   fitted: tuple | None = None):
    """The results Dataset of a run.

    A run of fixed sizes released at one point, without a barrier, gives the
    variables and attributes of ``calib.files.hazard_results.VARIABLES`` only. A run
    with release conditions (``c.release``) adds ``release_json`` and the range of
    the calibration's fitted sizes; over volume classes, the class variables
    (``OPTIONAL_VARIABLES``); a run with a barrier adds the barrier's attributes; a
    CRSP run records its event budget per block (``crsp_max_events``).

    Args:
        c: the run's counts (``run_hazard``).
        profile: the profile it ran on (zones of the stations, the vertices);
            None: zones "" and no vertices.
        seed: the run's seed.
        road_x_m, road_label: the station of interest and its name.
        release_rate_per_year: blocks of each size released per year, or None.
        record: more attributes: ``calibration`` (path), ``provenance_json``
            (``calib.files.provenance.provenance``), ``adequacy_json``,
            ``rock_density_kg_m3``, ...; dicts are stored as JSON text.
        fitted: (sizes, source) of the block sizes the calibration was fitted on
            (``calib.files.calibration_file.fitted_block_sizes_m``), or None.

    Returns:
        ``xarray.Dataset`` of schema ``calib.files.hazard_results.SCHEMA``.
    """
    data, bins = _count_variables(c, profile)
    coords = {"draw": np.arange(len(c.draws.values)), "block_size_m": c.sizes_m,
              "x_m": c.stations_x_m, "percentile": np.asarray(PERCENTILES),
              "parameter": np.asarray(c.draws.names, dtype=object),
              "vertex": np.arange(len(data["profile_x_m"]))}
    attrs = {"model": c.model, "n_blocks_per_draw": int(c.n_blocks),
             "release_x_m": float(c.release_x_m), "seed": -1 if seed is None else int(seed),
             "draws_source": c.draws.source, "energy_basis": ENERGY_BASIS[c.model],
             "height_convention": HEIGHT_CONVENTION,
             "percentile_interval": "distribution-free 95 % interval of order statistics "
                                    "(calib.hazard._stats.percentile_interval)",
             "provenance_json": {}, "road_x_m": road_x_m, "road_label": road_label,
             "release_rate_per_year": release_rate_per_year}
    if c.release is not None:
        _add_release(c, fitted, data, attrs)
    if c.shapes is not None and any(f != "sphere" for f in c.shapes):
        data["block_shape"] = np.asarray(c.shapes, dtype=object)
    if c.crsp_settings is not None:  # what a run of the same blocks must use
        m = c.crsp_settings.max_events
        attrs["crsp_max_events"] = "profile" if m is None else int(m)
    if c.barrier is not None:
        attrs.update(barrier_x_m=float(c.barrier.x_m), barrier_height_m=float(c.barrier.height_m),
                     barrier_capacity_kJ=float(c.barrier.capacity_kJ))
    attrs.update(record or {})
    return hazard_results(data, coords, attrs, bins)


def _count_variables(c: HazardCounts, profile: Profile | None) -> tuple[dict, dict]:
    """The variables every run has (``calib.files.hazard_results.VARIABLES``): the
    counts, the histograms and the percentiles with their intervals, the draws, the
    stations' zones and the profile's vertices; and the bin edges of each histogram."""
    data = {
        "n_exceed": c.exceed, "n_reach": c.reach, "n_reach_E_gt_30kJ": c.e30,
        "n_reach_E_gt_300kJ": c.e300, "n_unfinished": c.n_unfinished,
        "n_left_profile": c.n_left_profile, "energy_p95_binned_kJ": c.energy_p95_per_draw_kJ,
        "block_mass_kg": c.block_mass_kg, "parameter_value": c.draws.values,
        "posterior_row": np.asarray(c.draws.rows, np.int64),
        "zone": np.asarray(_zone_at(profile, c.stations_x_m) if profile is not None
                           else [""] * len(c.stations_x_m), dtype=object),
        "profile_x_m": np.asarray([] if profile is None else profile.x_m, np.float64),
        "profile_z_m": np.asarray([] if profile is None else profile.z_m, np.float64),
    }
    bins = {}
    for q, b in BINS.items():
        data[f"hist_{q}"] = c.hist[q]
        bins[f"hist_{q}"] = b
        value, lo, hi = c.percentiles[q]
        data[f"{q}_pct"], data[f"{q}_pct_lo"], data[f"{q}_pct_hi"] = value, lo, hi
        value, lo, hi = c.pooled_percentiles[q]
        data[f"{q}_pct_pooled"], data[f"{q}_pct_pooled_lo"], data[f"{q}_pct_pooled_hi"] = (
            value, lo, hi)
    for q, counts in c.draw_hist.items():
        data[f"draw_hist_{q}"] = counts
        bins[f"draw_hist_{q}"] = DRAW_BINS[q]
    return data, bins


def _add_release(c: HazardCounts, fitted: tuple | None, data: dict, attrs: dict) -> None:
    """Into ``data`` and ``attrs``, what a run with release conditions adds:
    ``release_json``, the range of the calibration's fitted sizes and, over volume
    classes, the class variables (``OPTIONAL_VARIABLES``) with the fraction of each
    class outside the fitted sizes (NaN without them)."""
    attrs["release_json"] = json_ready(c.release.record())  # unbounded classes: null
    if fitted is not None:
        attrs.update(fitted_block_size_min_m=float(np.min(fitted[0])),
                     fitted_block_size_max_m=float(np.max(fitted[0])),
                     fitted_block_sizes_source=str(fitted[1]))
    if c.release.law is not None:
        cls = c.release.classes
        data.update(
            class_label=np.asarray([k.label for k in cls], dtype=object),
            class_volume_min_m3=np.asarray([k.volume_min_m3 for k in cls]),
            class_volume_max_m3=np.asarray([k.volume_max_m3 for k in cls]),
            class_volume_m3=np.asarray([k.volume_m3 for k in cls]),
            class_probability=np.asarray([k.probability for k in cls]),
            extrapolated_fraction=(np.full(len(cls), np.nan) if fitted is None
                                   else c.release.extrapolated_fraction(fitted[0])))


def as_results(results, profile: Profile | None = None):
    """``results`` as a results Dataset: a Dataset as it is, a ``HazardCounts``
    through ``hazard_dataset`` (with ``profile``, for the stations' zones)."""
    if isinstance(results, HazardCounts):
        return hazard_dataset(results, profile)
    return results


def calibration_record(prog: str, seed: int, cal, path: str) -> dict:
    """What ``hazard.nc`` says about its calibration (``hazard_dataset``'s ``record``):
    the provenance of the run (``calib.files.provenance``), the calibration's own
    predictive check
    (``adequacy`` of its model section, ``calib.inference.adequacy``), the verdict
    of its posterior's diagnostics (``posterior_check_json``: ``ok`` and
    ``problems`` of the section's ``bayes`` record; None for a fit without a
    posterior) and the rock
    density the run simulated, where the calibration file states it (key
    ``rock_density_kg_m3``; older files fall back on the solvers' default, and
    ``hazard.nc`` then names no density), and CRSP's rolling threshold it
    simulated with (the calibration's; None for the DEM)."""
    import os

    from calib.files.calibration_file import CalibrationFile
    from calib.files.provenance import provenance
    from solvers.profile import default_materials_path

    doc = CalibrationFile.from_json(path)
    section = doc.models.get(cal.model, {})
    stated = "rock_density_kg_m3" in doc.record
    source = doc.record.get("rock_density_source")
    materials = default_materials_path(cal.profile_csv)
    return {
        "calibration": path,
        "provenance_json": provenance(prog, seed, {
            "calibration": path, "posterior": cal.posterior_csv, "profile": cal.profile_csv,
            "materials": materials if os.path.isfile(materials) else None}),
        "adequacy_json": section.get("adequacy"),
        "posterior_check_json": _posterior_check(section.get("bayes")),
        "rock_density_kg_m3": float(cal.rock_density_kg_m3) if stated else None,
        "rock_density_source": (f"{path}: rock_density_kg_m3"
                                + (f" ({source})" if isinstance(source, str) else ""))
        if stated else None,
        # the CRSP rolling threshold the run simulated with (the calibration's)
        "rolling_threshold_m_s": (float(cal.rolling_threshold_m_s) if cal.model == "crsp"
                                  else None),
    }


def _posterior_check(bayes: dict | None) -> dict | None:
    """``ok`` and ``problems`` of a model section's ``bayes`` record (R-hat, ESS,
    chains, mass at the bounds, the GP's realisation check: ``calib.inference``),
    or None where the fit has no posterior."""
    if not isinstance(bayes, dict) or "ok" not in bayes:
        return None
    return {"ok": bool(bayes["ok"]), "problems": [str(p) for p in bayes.get("problems", [])]}
