"""The hazard results file: ``hazard.nc``, one xarray Dataset (NetCDF-4, h5netcdf),
its one constructor, writer and reader.

``python -m calib.hazard`` writes it and builds its CSV tables from it;
``python -m calib.design`` reads it. Schema ``rockfall-hazard-results/1``
(attribute ``schema``); a file of another schema is refused in one line.
D draws, T block sizes, S stations, P percentiles.

Coordinates: ``draw`` (0 .. D-1), ``block_size_m`` (the block's average diameter D,
m), ``x_m`` (stations, m), ``percentile`` (50, 95, 99), ``parameter`` (the
calibrated parameters' names), ``vertex`` (the profile's vertices), and for each
histogram the lower edge of its bins (the first bin holds 0 <= v < v_min, the
last v >= v_max; attributes ``v_min``, ``v_max``, ``per_decade`` of the variable
give the bins, ``calib.hazard._stats.Bins``).

Variables (``VARIABLES``: dims, units, meaning) hold per-draw counts
(exceedance, reach, E > 30 / 300 kJ, unfinished, left the profile), pooled
histograms of energy, speed and clearance of the passers, each draw's 50/95/99th
percentiles of those three at every station with their 95 % Monte Carlo
intervals (``calib.hazard._stats.percentile_interval``) and the same pooled over
draws, per-draw histograms of energy and clearance (50 bins per decade), the
simulated block masses, the drawn parameter values, the zone of each station
and the profile; a run over volume classes adds the classes (``OPTIONAL_VARIABLES``:
volume range, representative volume, probability, share of extrapolated sizes), and a
CRSP run of blocks other than spheres their shape classes (``block_shape``).
Attributes: how the run was made (``model``,
``n_blocks_per_draw``, ``release_x_m``, ``seed``, ``draws_source``, optional
``release_rate_per_year``, ``road_x_m``, ``road_label``, ``rock_density_kg_m3``;
runs with release conditions: ``release_json``, ``fitted_block_size_min_m`` /
``_max_m`` / ``fitted_block_sizes_source``, ``design_block_json``; runs with a
barrier: ``barrier_x_m``, ``barrier_height_m``, ``barrier_capacity_kJ``; CRSP runs:
``crsp_max_events``, the event budget per block, an integer or ``"profile"`` for the
solver's size- and profile-derived budget, ``crsp_event_budget`` reads it, and
``rolling_threshold_m_s``, the calibration's rolling threshold it ran with; runs
given CRSP shape classes: ``fitted_block_shapes``, the shape classes the
calibration's fit simulated, comma separated),
what its numbers mean (``energy_basis``, ``height_convention``), and where it
came from (``provenance_json``: command, seed, SHA-256 of the inputs, package
versions, ``calib.files.provenance``; ``adequacy_json``: the calibration's own
predictive check, ``calib.inference.adequacy``), JSON text where a value is a
record. Optional attributes are absent rather than empty.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

__all__ = ["OPTIONAL_VARIABLES", "SCHEMA", "VARIABLES", "HazardResultsError",
           "crsp_event_budget", "hazard_results", "json_attr", "optional_attr",
           "read_hazard_results", "results_writer", "write_hazard_results"]

SCHEMA = "rockfall-hazard-results/1"

_DTS = ("draw", "block_size_m", "x_m")
_Q = {"energy_kJ": "kJ", "velocity_m_s": "m s-1", "bounce_height_m": "m"}
_QNAME = {"energy_kJ": "kinetic energy (translational + rotational) at first passage",
          "velocity_m_s": "speed of the centre of mass at first passage",
          "bounce_height_m": "clearance: vertical height of the block's lowest point above "
                             "the ground at first passage"}

# name -> (dims, units, meaning)
VARIABLES: dict[str, tuple[tuple[str, ...], str, str]] = {
    "n_exceed": (_DTS, "1", "finished blocks (stopped or left the profile) whose final "
                            "abscissa lies beyond x"),
    "n_reach": (_DTS, "1", "blocks that passed x moving downslope (invalid blocks excluded)"),
    "n_reach_E_gt_30kJ": (_DTS, "1", "passers with E > 30 kJ"),
    "n_reach_E_gt_300kJ": (_DTS, "1", "passers with E > 300 kJ"),
    "n_unfinished": (("draw", "block_size_m"), "1",
                     "blocks still moving at the solver's budget, or invalid"),
    "n_left_profile": (("draw", "block_size_m"), "1", "blocks that left the profile moving"),
    "energy_p95_binned_kJ": (_DTS, "kJ", "each draw's E p95 read from its 200-per-decade "
                                         "histogram (the hazard table's band)"),
    "block_mass_kg": (("block_size_m",), "kg", "mass of the simulated block of each size"),
    "parameter_value": (("draw", "parameter"), "", "the calibrated parameters of each draw"),
    "posterior_row": (("draw",), "1", "posterior CSV data row of each draw (-1: point "
                                      "estimate)"),
    "zone": (("x_m",), "", "material zone of the profile segment at each station"),
    "profile_x_m": (("vertex",), "m", "profile vertex abscissa"),
    "profile_z_m": (("vertex",), "m", "profile vertex elevation"),
}
for _q, _u in _Q.items():
    VARIABLES[f"hist_{_q}"] = (("block_size_m", "x_m", f"{_q}_bin"), "1",
                               f"passers of all draws per bin: {_QNAME[_q]}")
    VARIABLES[f"{_q}_pct"] = (_DTS + ("percentile",), _u, f"each draw's percentile: "
                                                          f"{_QNAME[_q]}")
    VARIABLES[f"{_q}_pct_pooled"] = (("block_size_m", "x_m", "percentile"), _u,
                                     f"percentile of the passers of all draws: {_QNAME[_q]}")
    for _end in ("lo", "hi"):
        VARIABLES[f"{_q}_pct_{_end}"] = (_DTS + ("percentile",), _u,
                                         f"{_end} end of the 95 % Monte Carlo interval of "
                                         f"{_q}_pct")
        VARIABLES[f"{_q}_pct_pooled_{_end}"] = (("block_size_m", "x_m", "percentile"), _u,
                                                f"{_end} end of the 95 % Monte Carlo interval "
                                                f"of {_q}_pct_pooled")
for _q in ("energy_kJ", "bounce_height_m"):
    VARIABLES[f"draw_hist_{_q}"] = (_DTS + (f"{_q}_draw_bin",), "1",
                                    f"each draw's passers per bin: {_QNAME[_q]}")

# variables of runs that have them, absent from the others (a run over volume
# classes, ``calib.model.release``: its ``block_size_m`` are the classes'
# representative sizes)
_T = ("block_size_m",)
OPTIONAL_VARIABLES: dict[str, tuple[tuple[str, ...], str, str]] = {
    "class_label": (_T, "", "volume range of the volume class"),
    "class_volume_min_m3": (_T, "m3", "smallest block volume of the class"),
    "class_volume_max_m3": (_T, "m3", "largest block volume of the class (inf: unbounded "
                                      "law)"),
    "class_volume_m3": (_T, "m3", "representative volume: the law's median within the "
                                  "class (block_size_m is its sphere's diameter)"),
    "class_probability": (_T, "1", "the class's probability under the volume law, its share "
                                   "of the released blocks (each class is simulated with "
                                   "n_blocks_per_draw blocks)"),
    "extrapolated_fraction": (_T, "1", "fraction of the class's blocks (by the law) whose "
                                       "size lies outside the sizes the calibration was "
                                       "fitted on; NaN: not known"),
    "block_shape": (_T, "", "CRSP shape class of the blocks (solvers.crsp.make_block: "
                            "sphere, cylinder of length 2 r, disc of thickness r / 2) of "
                            "the volume of the sphere of diameter D (calib.model.entries); "
                            "absent: spheres"),
}

# attributes every file has
_REQUIRED_ATTRS = ("schema", "model", "n_blocks_per_draw", "release_x_m", "seed",
                   "draws_source", "energy_basis", "height_convention", "provenance_json")
_COMPRESSED = tuple(k for k in VARIABLES if "hist" in k)


class HazardResultsError(ValueError):
    """A hazard results file that cannot be used; the message names the file."""


def _bin_coord(bins) -> np.ndarray:
    return np.concatenate([[0.0], bins.v_min * 10.0 ** (np.arange(bins.n_log + 1)
                                                        / bins.per_decade)])


def hazard_results(data: dict, coords: dict, attrs: dict, bins: dict):
    """Build the results Dataset (the one constructor; module docstring).

    Args:
        data: variable name -> array, for every name of ``VARIABLES`` (dims in
            its order).
        coords: ``draw``, ``block_size_m``, ``x_m``, ``percentile``, ``parameter``,
            ``vertex`` -> 1-D arrays.
        attrs: the attributes (``_REQUIRED_ATTRS`` and the optional ones); a dict
            value is stored as JSON text, None values are left out.
        bins: ``"hist_<q>"`` / ``"draw_hist_<q>"`` -> ``calib.hazard._stats.Bins`` of
            each histogram variable.

    Returns:
        ``xarray.Dataset`` with units on every variable.
    """
    import xarray as xr

    missing = [k for k in VARIABLES if k not in data]
    if missing:
        raise ValueError(f"hazard results: variable(s) {', '.join(missing)} missing")
    cs = dict(coords)
    for name, b in bins.items():
        cs[VARIABLES[name][0][-1]] = _bin_coord(b)
    ds = xr.Dataset(coords=cs)
    described = VARIABLES | {k: v for k, v in OPTIONAL_VARIABLES.items() if k in data}
    for name, (dims, units, meaning) in described.items():
        var = xr.Variable(dims, np.asarray(data[name]))
        var.attrs.update(units=units, long_name=meaning)
        if name in bins:
            b = bins[name]
            var.attrs.update(v_min=float(b.v_min), v_max=float(b.v_max),
                             per_decade=int(b.per_decade))
        ds[name] = var
    ds["block_size_m"].attrs.update(units="m", long_name="block size: average diameter D "
                                    "(CRSP sphere of radius D/2 or its volume in another "
                                    "shape, DEM square of side D)")
    ds["x_m"].attrs.update(units="m", long_name="station abscissa, horizontal downslope")
    ds["percentile"].attrs.update(units="%")
    for key, value in attrs.items():
        if value is None:
            continue
        ds.attrs[key] = json.dumps(value, allow_nan=False) if isinstance(value, dict) else value
    ds.attrs["schema"] = SCHEMA
    return ds


def optional_attr(ds, key: str):
    """An optional attribute's value, or None where the file has none."""
    v = ds.attrs.get(key)
    if v is None or (isinstance(v, float | np.floating) and math.isnan(v)):
        return None
    return v.item() if isinstance(v, np.generic) else v


def json_attr(ds, key: str):
    """A record stored as JSON text (``provenance_json``, ``adequacy_json``), or None."""
    text = ds.attrs.get(key)
    return None if text is None else json.loads(text)


def crsp_event_budget(ds) -> tuple[bool, int | None]:
    """The CRSP event budget per block a run simulated with (attribute
    ``crsp_max_events``): (recorded, budget), budget an integer, or None for the
    solver's size- and profile-derived budget (``solvers.crsp.event_budget``);
    (False, None) where the file does not record it (a DEM run)."""
    v = optional_attr(ds, "crsp_max_events")
    if v is None:
        return False, None
    return True, None if v == "profile" else int(v)


def write_hazard_results(ds, path: str) -> None:
    """Write ``ds`` (``hazard_results``) as NetCDF-4 with the h5netcdf engine; the
    histograms compressed (zlib level 4: mostly empty bins)."""
    if ds.attrs.get("schema") != SCHEMA:
        raise ValueError(f"not a {SCHEMA} Dataset")
    encoding = {k: {"zlib": True, "complevel": 4} for k in _COMPRESSED if k in ds}
    ds.to_netcdf(path, engine="h5netcdf", encoding=encoding)


def results_writer(ds):
    """A ``write(path)`` callable for ``solvers.cli.write_all_atomic``."""
    return lambda path: write_hazard_results(ds, path)


def read_hazard_results(path: str):
    """Read ``hazard.nc`` fully into memory (the file is closed).

    Raises:
        HazardResultsError: the file is missing, not NetCDF, of another schema, or
            lacks a variable or attribute of this one; one line naming the file.
    """
    import xarray as xr

    if not os.path.isfile(path):
        raise HazardResultsError(f"{path}: file not found")
    try:
        with xr.open_dataset(path, engine="h5netcdf") as f:
            ds = f.load()
    except Exception as exc:  # h5py/h5netcdf raise several types for a bad file
        raise HazardResultsError(f"{path}: not a NetCDF-4 hazard results file "
                                 f"({type(exc).__name__})") from None
    schema = ds.attrs.get("schema")
    if schema != SCHEMA:
        raise HazardResultsError(f"{path}: attribute 'schema': expected {SCHEMA!r}, got "
                                 f"{schema!r} (rerun python -m calib.hazard)")
    for key in _REQUIRED_ATTRS:
        if key not in ds.attrs:
            raise HazardResultsError(f"{path}: attribute {key!r} missing ({SCHEMA})")
    for name, (dims, _, _) in (VARIABLES | OPTIONAL_VARIABLES).items():
        if name not in ds:
            if name in OPTIONAL_VARIABLES:
                continue
            raise HazardResultsError(f"{path}: variable {name!r} missing ({SCHEMA})")
        if ds[name].dims != dims:
            raise HazardResultsError(f"{path}: variable {name!r}: dims {ds[name].dims}, "
                                     f"expected {dims} ({SCHEMA})")
    return ds
