"""What a site adds to its profile: its name, the station of interest (a road, a
house) and published reference values to draw next to a fit.

Nothing site-specific is a default of the commands: a site says it in a small
JSON file next to its profile, found by the profile's name:

* ``<folder>/<name>_profile.csv`` -> ``<folder>/<name>_site.json``;
* ``<folder>/<name>.csv`` -> ``<folder>/<name>_site.json`` (so a site folder's
  ``profile.csv`` has ``profile_site.json``),

the rule ``solvers.profile.default_materials_path`` follows for materials.

Schema (every key optional; ``data/README.md`` says where each shipped value
comes from)::

    {"name": "Postignano (central Italy)",
     "rock_density_kg_m3": 2350, "rock_density_source": "...",
     "release_height_sd_m": 0.6, "release_height_source": "...",
     "release_speed_sd_m_s": 0.3, "release_speed_source": "...",
     "rolling_threshold_m_s": 0.05, "rolling_threshold_source": "...",
     "dem_max_time_s": 200, "dem_max_time_source": "...",
     "station_of_interest": {"x_m": 230.0, "label": "road", "source": "..."},
     "alpha_reference": {"label": "paper, Table 1", "L_m": [0.2, 0.9, 1.8],
                         "alpha": [0.90, 0.43, 0.30], "source": "..."}}

``rock_density_kg_m3`` is the site's one rock density: every simulation of
the site's blocks (the fit, the predictive check, the discrepancy workflow,
the hazard run) builds its blocks with it, so that a simulated block weighs
what the rock weighed, and ``calibration.json`` records it; without it the
solvers' default ``solvers.material.ROCK_DENSITY_KG_M3`` (2350 kg/m^3).
``release_height_sd_m`` and ``release_speed_sd_m_s`` are the errors (sds, >= 0)
of the site's tracked release heights and speeds: the height of a tracked
release above a profile cut from a raster carries the raster's vertical error
(measured for Tschamut by ``scripts/raster_height_error.py``), the tracked
speed the tracker's. Every CRSP simulation of rows with a tracked release
(the fit, the predictive check, the discrepancy workflow) then draws each
block's release height and speed from truncated normals about the rows'
values (``solvers.crsp.init``); ``calibration.json`` records the sds. Each
needs its ``*_source`` text (where the number comes from). Without them: 0,
the tracked values taken as exact.
``rolling_threshold_m_s`` is the CRSP rolling threshold every simulation of
the site runs with (``solvers.crsp.ROLLING_THRESHOLD_M_S``, 0.5 m/s, where the
site file gives none): the rebound or landing normal speed below which a rock
stays on the ground and rolls. It is a numerical cutoff of the solver (RocFall
exposes its counterpart as an engine setting, the "normal velocity cutoff"),
set per site where the default is not converged there: a site gives the value
from which its releases' runouts no longer change when it is lowered
(``scripts/loglik_noise.py --rolling-threshold-m-s ... --entries``), with its
``rolling_threshold_source``. The fit records it in ``calibration.json`` and
the predictive check, the discrepancy workflow, the hazard run and the design
run the calibration's value.
``dem_max_time_s`` is the simulated time every DEM block of the site gets
(``calib.model.dem_run.DEM_RUN``'s 150 s where the site gives none): a block
still moving then is unfinished and has no runout, so a site whose slowest
blocks (small ones at the damping law's clip) need longer says so, with its
``dem_max_time_source``. ``calib.fit`` takes it as ``--dem-max-time-s``'s
default and records it in ``calibration.json`` (which ``calib.validate`` and
``calib.hazard`` then run), and ``calib.discover --model dem`` runs it.
``station_of_interest`` is where ``calib.hazard`` reports the reach probability
and design values (``--road-x-m`` overrides it); ``alpha_reference`` is drawn
on the DEM damping-law figure and reported next to the fitted alpha(L). A
profile without a site file has neither: the hazard summary then reports at
the profile's last station and says so.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os

from solvers.crsp import ROLLING_THRESHOLD_M_S, ROLLING_THRESHOLD_RANGE_M_S
from solvers.material import ROCK_DENSITY_KG_M3

__all__ = ["Site", "SiteError", "load_site", "site_path"]


class SiteError(ValueError):
    """Bad site file; the message names the file and the key."""


@dataclasses.dataclass(frozen=True)
class Site:
    """A site's additions to its profile (module docstring).

    Attributes:
        name: the site's name ("" where no site file exists).
        station_x_m: abscissa of the station of interest on the profile, m, or None.
        station_label: what stands there ("road", "house"; default "station").
        alpha_reference: ((L_m, alpha), ...) published damping values, or ().
        alpha_reference_label: their legend label.
        path: the site file read, or None.
        rock_density_kg_m3: the site's rock density, kg/m^3 (the solvers'
            default where the site file gives none).
        density_source: where the density comes from (the site file's
            ``rock_density_source``, or "default").
        release_height_sd_m: sd of a tracked release height's error, m (0:
            exact; module docstring).
        release_height_source: where it comes from ("" where 0 by default).
        release_speed_sd_m_s: sd of a tracked release speed's error, m/s.
        release_speed_source: where it comes from.
        rolling_threshold_m_s: the CRSP rolling threshold of the site's
            simulations, m/s (the solver's default where the site gives none).
        rolling_threshold_source: where it comes from ("default" without one).
        dem_max_time_s: the DEM's simulated time per block, s, or None: the
            toolkit's default (``calib.model.dem_run.DEM_RUN``).
        dem_max_time_source: where it comes from ("" without one).
    """

    name: str = ""
    station_x_m: float | None = None
    station_label: str = "station"
    alpha_reference: tuple[tuple[float, float], ...] = ()
    alpha_reference_label: str = "reference"
    path: str | None = None
    rock_density_kg_m3: float = ROCK_DENSITY_KG_M3
    density_source: str = "default (solvers.material.ROCK_DENSITY_KG_M3)"
    release_height_sd_m: float = 0.0
    release_height_source: str = ""
    release_speed_sd_m_s: float = 0.0
    release_speed_source: str = ""
    rolling_threshold_m_s: float = ROLLING_THRESHOLD_M_S
    rolling_threshold_source: str = "default (solvers.crsp.ROLLING_THRESHOLD_M_S)"
    dem_max_time_s: float | None = None
    dem_max_time_source: str = ""


def site_path(profile_path: str) -> str:
    """The site file of a profile (module docstring), whether or not it exists."""
    folder, base = os.path.split(profile_path)
    stem, _ = os.path.splitext(base)
    if stem.endswith("_profile"):
        stem = stem[: -len("_profile")]
    return os.path.join(folder, stem + "_site.json")


def _number(path: str, key: str, v, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (lo <= v <= hi):
        raise SiteError(f"{path}: key {key!r}: expected a finite number in [{lo:g}, {hi:g}], "
                        f"got {v!r}")
    return float(v)


def load_site(profile_path: str) -> Site:
    """The site of a profile: its site file, or an empty ``Site`` where none exists.

    Raises:
        SiteError: the file is not JSON or a key has the wrong type or range.
    """
    path = site_path(profile_path)
    if not os.path.isfile(path):
        return Site()
    try:
        with open(path) as fh:
            doc = json.load(fh)
    except (OSError, json.JSONDecodeError) as e:
        raise SiteError(f"{path}: not a readable JSON site file ({e})") from None
    if not isinstance(doc, dict):
        raise SiteError(f"{path}: expected a JSON object")
    name = doc.get("name", "")
    if not isinstance(name, str):
        raise SiteError(f"{path}: key 'name': expected text, got {name!r}")
    x, label = None, "station"
    st = doc.get("station_of_interest")
    if st is not None:
        if not isinstance(st, dict) or "x_m" not in st:
            raise SiteError(f"{path}: key 'station_of_interest': expected an object with 'x_m'")
        x = _number(path, "station_of_interest.x_m", st["x_m"])
        label = st.get("label", "station")
        if not isinstance(label, str) or not label:
            raise SiteError(f"{path}: key 'station_of_interest.label': expected text")
    ref, ref_label = (), "reference"
    ar = doc.get("alpha_reference")
    if ar is not None:
        ls, al = (ar.get("L_m"), ar.get("alpha")) if isinstance(ar, dict) else (None, None)
        if not (isinstance(ls, list) and isinstance(al, list) and len(ls) == len(al) > 0):
            raise SiteError(f"{path}: key 'alpha_reference': expected lists 'L_m' and 'alpha' "
                            "of one length")
        ref = tuple((_number(path, "alpha_reference.L_m", L, 1e-6),
                     _number(path, "alpha_reference.alpha", a, 0.0, 1.0))
                    for L, a in zip(ls, al))
        ref_label = ar.get("label", "reference")
        if not isinstance(ref_label, str):
            raise SiteError(f"{path}: key 'alpha_reference.label': expected text")
    rho, rho_source = ROCK_DENSITY_KG_M3, Site.density_source
    if "rock_density_kg_m3" in doc:
        rho = _number(path, "rock_density_kg_m3", doc["rock_density_kg_m3"], 1.0, 2.0e4)
        rho_source = doc.get("rock_density_source", path)
        if not isinstance(rho_source, str):
            raise SiteError(f"{path}: key 'rock_density_source': expected text")
    errors = [_sourced_number(path, doc, key, src) for key, src in (
        ("release_height_sd_m", "release_height_source"),
        ("release_speed_sd_m_s", "release_speed_source"))]
    threshold = (Site.rolling_threshold_m_s, Site.rolling_threshold_source)
    if "rolling_threshold_m_s" in doc or "rolling_threshold_source" in doc:
        threshold = _sourced_number(path, doc, "rolling_threshold_m_s",
                                   "rolling_threshold_source",
                                   *ROLLING_THRESHOLD_RANGE_M_S)
    dem_time = (None, "")
    if "dem_max_time_s" in doc or "dem_max_time_source" in doc:
        dem_time = _sourced_number(path, doc, "dem_max_time_s", "dem_max_time_source",
                                   1.0, 1.0e5)
    return Site(name, x, label, ref, ref_label, path, rho, rho_source,
                *errors[0], *errors[1], *threshold, *dem_time)


def _sourced_number(path: str, doc: dict, key: str, source_key: str, lo: float = 0.0,
                   hi: float = 100.0) -> tuple[float, str]:
    """(value, source) of a sourced number (a release error, the rolling
    threshold): the key's value in [lo, hi] with its source text (required with
    it), or (0, "")."""
    if key not in doc:
        if source_key in doc:
            raise SiteError(f"{path}: key {source_key!r}: given without {key!r}")
        return 0.0, ""
    value = _number(path, key, doc[key], lo, hi)
    source = doc.get(source_key)
    if not isinstance(source, str) or not source.strip():
        raise SiteError(f"{path}: key {source_key!r}: expected text saying where {key} "
                        "comes from")
    return value, source
