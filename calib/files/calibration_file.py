"""The calibration file: ``results/calibration.json``, its one reader, and
drawing parameter sets from it. The document a fit writes is assembled from its
typed results in ``calib.files.fit_record``; ``CalibrationFile.to_json`` writes it.

``python -m calib.fit`` writes it (``SCHEMA``); every consumer reads it through
``load_calibration`` (``python -m calib.hazard``, ``python -m calib.validate``,
the notebooks), never by re-parsing the JSON with its own names. Schema
``rockfall-calibration/1``:

* ``crsp``: ``Kn``, ``Kt``, ``roughness_m`` (and ``rolling_friction_deg`` when
  it was fitted: one angle for every zone) with ``map``/``mean``/``q05``/``q95``
  and ``posterior_csv`` (columns ``Kn,Kt,roughness_m[,rolling_friction_deg]``, or one
  ``rolling_friction_deg[<zone>]`` per zone;
  null after a gradient-only fit);
* ``crsp.effects``: the candidate effects of ``calib.model.effects`` the fit
  switched on (``python -m calib.fit --effect``; [] or absent: none); their
  parameters (e.g. ``gamma``, ``belt_start_m``, ``belt_loss``) follow the
  baseline's in ``parameters``, as keys with ``map``/``mean``/``q05``/``q95``
  and as posterior CSV columns, and every consumer simulates them
  (``calib.model.effects.draw_overrides``). A file naming an effect the solver
  cannot run (unknown, twice, or ``rolling_resistance`` beside a fitted
  rolling angle) is refused;
* ``dem``: ``alpha_law`` (``form`` "power" with ``a``, ``b``: alpha = a L^-b, L
  the square side in m; or ``form`` "constant" with ``alpha``; every model runs
  it clipped to [0, 0.95], ``calib.model.alpha_law``) and ``posterior_csv`` (columns
  ``a,b`` or ``alpha``; may be null);
* ``block_size_mapping``: a block of average diameter D is a CRSP block of
  mass rho pi D^3 / 6 (a sphere of radius D/2, or the group's shape class of
  that volume: ``release_groups.groups[*].shape``, absent in older files, which
  simulated spheres) and a DEM square of side D.
* ``row_shapes``: true where CRSP simulated each row in its ``shape`` column's
  class (``calib.fit --row-shapes``); false or absent: spheres.
* ``dem_max_time_source`` (fits of the DEM): where ``dem.run.max_time_s``
  came from: the site file's ``dem_max_time_source``, ``--dem-max-time-s``, or
  the default.
* ``release_height_sd_m``, ``release_speed_sd_m_s`` (with their
  ``*_source`` texts): the errors of the tracked release heights and speeds
  with which the CRSP fit drew its blocks' releases (the site's,
  ``calib.files.site``; absent in older files: 0); ``calib.validate``
  draws the held-out rows' releases with the same.
* ``rolling_threshold_m_s`` (with ``rolling_threshold_source``): CRSP's
  rolling threshold the fit ran with (the site's, ``calib.files.site``; absent
  in older files: ``solvers.crsp.ROLLING_THRESHOLD_M_S``, which they ran
  with); ``calib.validate``, ``calib.discover``, ``calib.hazard`` and
  ``calib.design`` simulate the fitted model with it.

``posterior_csv`` is relative to the folder of the json file; ``profile_csv``
is relative to the working directory (as ``calib.fit`` writes it, run from the
repository root) or, failing that, to the json's folder.

Every error is a ``CalibrationError`` whose message names the file and, where
it applies, the row (file line) and the column.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
from typing import NamedTuple

import numpy as np

from calib.model.alpha_law import FORMS, PARAMETER_RANGES
from calib.model.effects import EFFECTS, check_combination, effect_columns, effect_names
from calib.model.priors import base_name, rolling_zone
from solvers.crsp import ROLLING_THRESHOLD_M_S, ROLLING_THRESHOLD_RANGE_M_S
from solvers.dem import check_run_numerics
from solvers.material import ROCK_DENSITY_KG_M3

__all__ = ["SCHEMA", "Calibration", "CalibrationError", "CalibrationFile", "Draws",
           "ModelSummary", "ParameterSummary", "draw_parameters", "fitted_block_shapes",
           "fitted_block_sizes_m",
           "load_calibration", "posterior_csv_text"]

SCHEMA = "rockfall-calibration/1"

# name -> (lower, upper, lower bound inclusive) for every calibrated scalar
_CRSP_RANGES = {"Kn": (0.0, 1.0, False), "Kt": (0.0, 1.0, False),
                "roughness_m": (0.0, math.inf, True),
                "rolling_friction_deg": (0.0, 90.0 - 1e-9, True)}
_DEM_RANGES = PARAMETER_RANGES
_DEM_COLUMNS = FORMS


class CalibrationError(ValueError):
    """A calibration file (or its posterior CSV) that cannot be used."""


class Calibration(NamedTuple):
    """What the hazard run needs from one model's calibration.

    Attributes:
        path: the json file.
        model: "crsp" or "dem".
        profile_csv: resolved path of the slope profile.
        names: parameter names (CRSP: Kn, Kt, roughness_m[, rolling angle(s)], then
            the columns of ``effects``; DEM: a, b or alpha).
        point: (P,) the point estimate (``map``) of each parameter.
        posterior: (R, P) posterior sample, or None (gradient-only fit).
        posterior_csv: its resolved path, or None.
        alpha_form: DEM only: "power" or "constant" ("" for CRSP).
        data_csv: the observations the fit used, resolved like ``profile_csv``,
            or None where that file is not found.
        release_x_m: the release abscissa the fit simulated, m (key
            ``release_x_m``), or None (older files: the profile's first vertex).
        dem_run: DEM only: the DEM numerics the fit used (key ``dem.run``:
            ``stiffness_scale``, ``max_time_s``, ``dt_size_m``; ``calib.model.dem_run``),
            or None (older files: the defaults).
        own_releases: the fit released each row from its own ``release_x_m``
            (rows without one at the profile's first vertex): always for CRSP,
            for the DEM where ``release_groups.models`` lists it; False: every
            block at ``release_x_m`` (DEM fits of older files).
        release_heights: the fit released its rows from their
            ``release_height_m`` and at their ``release_speed_m_s`` (CRSP fits
            that record a ``release_height_m`` for their release groups; DEM
            fits listed in ``release_groups.speed_and_height_models``); False:
            on the ground (DEM fits and CRSP fits of older files).
        rock_density_kg_m3: the rock density the fit simulated its blocks at
            (key ``rock_density_kg_m3``; older files: the solvers' default,
            ``solvers.material.ROCK_DENSITY_KG_M3``, which they ran with).
        release_height_sd_m, release_speed_sd_m_s: the errors (sds) of the
            tracked release heights and speeds the fit drew its blocks' releases
            with (keys of the same names, the site's, ``calib.files.site``;
            older files: 0, the tracked values taken as exact, as they ran).
        effects: CRSP: the effects the fit switched on (key ``crsp.effects``;
            ``calib.model.effects``), whose columns are the last of ``names``
            (``effect_columns``); () without any, and for the DEM.
        rolling_threshold_m_s: CRSP's rolling threshold the fit ran with, m/s
            (key of the same name; older files: the solver's default).
        row_shapes: CRSP simulated each row in its ``shape`` column's class (key
            ``row_shapes``, ``calib.fit --row-shapes``); False (and absent):
            spheres.
    """

    path: str
    model: str
    profile_csv: str
    names: tuple[str, ...]
    point: np.ndarray
    posterior: np.ndarray | None
    posterior_csv: str | None
    alpha_form: str
    data_csv: str | None = None
    release_x_m: float | None = None
    dem_run: dict | None = None
    own_releases: bool = True
    release_heights: bool = False
    rock_density_kg_m3: float = ROCK_DENSITY_KG_M3
    release_height_sd_m: float = 0.0
    release_speed_sd_m_s: float = 0.0
    effects: tuple[str, ...] = ()
    rolling_threshold_m_s: float = ROLLING_THRESHOLD_M_S
    row_shapes: bool = False

    @property
    def base_names(self) -> tuple[str, ...]:
        """``names`` without the effects' columns (the baseline's parameters)."""
        return self.names[:len(self.names) - len(effect_columns(self.effects))]

    def check_density(self, density_kg_m3: float, where: str) -> None:
        """Refuse to simulate this calibration's blocks at another rock density
        than the one it was fitted at (``where`` names what gives the other one)."""
        if float(density_kg_m3) != self.rock_density_kg_m3:
            raise CalibrationError(
                f"{self.path}: fitted at a rock density of {self.rock_density_kg_m3:g} kg/m^3, "
                f"but {where} gives {float(density_kg_m3):g} kg/m^3: refit at that density "
                "(the DEM's contact forces and CRSP's energies depend on it)")


class Draws(NamedTuple):
    """Parameter sets to simulate.

    Attributes:
        values: (D, P) one row per draw, columns ``names``.
        names: parameter names.
        rows: (D,) posterior CSV data row (1-based) of each draw, or -1 for the
            point estimate.
        source: "posterior", "point estimate" or "point estimate (no posterior
            sample: replicate runs)".
    """

    values: np.ndarray
    names: tuple[str, ...]
    rows: np.ndarray
    source: str


def _number(path: str, where: str, value, lo: float, hi: float, lo_incl: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise CalibrationError(f"{path}: {where}: expected a number, got {value!r}")
    v = float(value)
    ok_lo = v >= lo if lo_incl else v > lo
    if not (math.isfinite(v) and ok_lo and v <= hi):
        bracket = "[" if lo_incl else "("
        raise CalibrationError(f"{path}: {where}: {v:g} outside {bracket}{lo:g}, {hi:g}]")
    return v


def _section(path: str, doc: dict, key: str) -> dict:
    sec = doc.get(key)
    if not isinstance(sec, dict):
        raise CalibrationError(f"{path}: key {key!r}: expected an object")
    return sec


def _summary_value(path: str, sec: dict, prefix: str, name: str, rng) -> float:
    entry = sec.get(name)
    if not isinstance(entry, dict) or "map" not in entry:
        raise CalibrationError(f"{path}: key {prefix}.{name}: expected an object with 'map'")
    return _number(path, f"{prefix}.{name}.map", entry["map"], *rng)


def _resolve(path: str, rel: str, json_dir: str, what: str, prefer_cwd: bool) -> str:
    if not isinstance(rel, str) or not rel:
        raise CalibrationError(f"{path}: key {what!r}: expected a file name")
    if os.path.isabs(rel):
        candidates = [rel]
    elif prefer_cwd:
        candidates = [rel, os.path.join(json_dir, rel)]
    else:
        candidates = [os.path.join(json_dir, rel)]
    for c in candidates:
        if os.path.isfile(c):
            return c
    raise CalibrationError(f"{path}: key {what!r}: file {candidates[0]} not found")


def _read_posterior(csv_path: str, names: tuple[str, ...], ranges: dict) -> np.ndarray:
    try:
        with open(csv_path, newline="") as fh:
            reader = csv.DictReader(fh)
            header = reader.fieldnames or []
            missing = [n for n in names if n not in header]
            if missing:
                raise CalibrationError(f"{csv_path}: line 1: missing column(s) "
                                       f"{', '.join(missing)}")
            rows = []
            for i, row in enumerate(reader):
                line = i + 2
                vals = []
                for n in names:
                    text = (row.get(n) or "").strip()
                    try:
                        v = float(text)
                    except ValueError:
                        raise CalibrationError(f"{csv_path}: line {line}, column {n}: expected "
                                               f"a number, got {text!r}") from None
                    lo, hi, incl = ranges[n]
                    ok_lo = v >= lo if incl else v > lo
                    if not (math.isfinite(v) and ok_lo and v <= hi):
                        raise CalibrationError(f"{csv_path}: line {line}, column {n}: value "
                                               f"{v:g} out of range")
                    vals.append(v)
                rows.append(vals)
    except OSError as exc:
        raise CalibrationError(f"{csv_path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{csv_path}: not a text CSV file") from None
    if not rows:
        raise CalibrationError(f"{csv_path}: no data rows")
    return np.asarray(rows, dtype=np.float64)


def posterior_csv_text(names, samples) -> str:
    """The posterior CSV that ``load_calibration`` reads: a header ``names`` and one
    row per draw of ``samples`` (R, P), 8 significant digits."""
    body = "\n".join(",".join(f"{v:.8g}" for v in row) for row in np.asarray(samples, float))
    return ",".join(names) + "\n" + body + "\n"


def load_calibration(path: str, model: str | None = None) -> Calibration:
    """Read and validate a calibration file for one model.

    Args:
        path: ``calibration.json``.
        model: "crsp", "dem", or None for the first of those present.

    Returns:
        ``Calibration``.

    Raises:
        CalibrationError: missing or malformed file, section or value.
    """
    return _model_from_doc(path, _read_doc(path), model)


def _read_doc(path: str) -> dict:
    """The parsed file, its schema checked."""
    try:
        with open(path) as fh:
            text = fh.read()
    except FileNotFoundError:
        raise CalibrationError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read ({getattr(exc, 'strerror', None) or exc})"
                               ) from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}: line {exc.lineno}, column {exc.colno}: invalid JSON "
                               f"({exc.msg})") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: expected a JSON object at the top level")
    if doc.get("schema") != SCHEMA:
        raise CalibrationError(f"{path}: key 'schema': expected {SCHEMA!r}, got "
                               f"{doc.get('schema')!r}")
    return doc


def _model_from_doc(path: str, doc: dict, model: str | None) -> Calibration:
    if model is None:
        model = next((m for m in ("crsp", "dem") if m in doc and doc[m] is not None), None)
        if model is None:
            raise CalibrationError(f"{path}: neither a 'crsp' nor a 'dem' section")
    if model not in ("crsp", "dem"):
        raise CalibrationError(f"model: expected crsp or dem, got {model!r}")
    if doc.get(model) is None:
        present = ", ".join(m for m in ("crsp", "dem") if doc.get(m)) or "nothing"
        raise CalibrationError(f"{path}: no {model!r} section (this file calibrates "
                               f"{present})")
    json_dir = os.path.dirname(os.path.abspath(path))
    profile_csv = _resolve(path, doc.get("profile_csv"), json_dir, "profile_csv", True)
    sec = _section(path, doc, model)
    effects = _effects(path, sec, model)
    if model == "crsp":
        names = ("Kn", "Kt", "roughness_m") + tuple(
            k for k in sec if rolling_zone(k) is not None)  # one, or one per zone
        ranges = {n: _CRSP_RANGES[base_name(n)] for n in names}
        try:
            check_combination(effects, names)
        except ValueError as e:
            raise CalibrationError(f"{path}: key 'crsp.effects': {e}") from None
        ranges.update({c: v for e in effects for c, v in EFFECTS[e].valid.items()})
        names += effect_columns(effects)
        point = [_summary_value(path, sec, "crsp", n, ranges[n]) for n in names]
        form = ""
    else:
        law = sec.get("alpha_law")
        if not isinstance(law, dict):
            raise CalibrationError(f"{path}: key 'dem.alpha_law': expected an object")
        form = law.get("form")
        if form not in _DEM_COLUMNS:
            raise CalibrationError(f"{path}: key 'dem.alpha_law.form': expected 'power' or "
                                   f"'constant', got {form!r}")
        names = _DEM_COLUMNS[form]
        ranges = _DEM_RANGES
        point = [_summary_value(path, law, "dem.alpha_law", n, ranges[n]) for n in names]
    post_rel = sec.get("posterior_csv")
    if post_rel is None:
        posterior, post_path = None, None
    else:
        post_path = _resolve(path, post_rel, json_dir, f"{model}.posterior_csv", False)
        posterior = _read_posterior(post_path, names, ranges)
    try:
        data_csv = _resolve(path, doc.get("data_csv"), json_dir, "data_csv", True)
    except CalibrationError:
        data_csv = None
    release = doc.get("release_x_m")
    if release is not None:
        release = _number(path, "release_x_m", release, -math.inf, math.inf, True)
    rho = _number(path, "rock_density_kg_m3", doc.get("rock_density_kg_m3", ROCK_DENSITY_KG_M3),
                  0.0, math.inf, False)
    return Calibration(path=path, model=model, profile_csv=profile_csv, names=names,
                       point=np.asarray(point, dtype=np.float64), posterior=posterior,
                       posterior_csv=post_path, alpha_form=form, data_csv=data_csv,
                       release_x_m=release, dem_run=_dem_run(path, sec) if model == "dem"
                       else None, own_releases=model == "crsp" or "dem" in _grouped(doc),
                       release_heights=(model == "crsp" and _with_heights(doc))
                       or model in _grouped(doc, "speed_and_height_models"),
                       rock_density_kg_m3=rho, effects=effects,
                       row_shapes=model == "crsp" and doc.get("row_shapes") is True,
                       rolling_threshold_m_s=_number(
                           path, "rolling_threshold_m_s",
                           doc.get("rolling_threshold_m_s", ROLLING_THRESHOLD_M_S),
                           *ROLLING_THRESHOLD_RANGE_M_S, True),
                       **{k: _number(path, k, doc.get(k, 0.0), 0.0, math.inf, True)
                          for k in ("release_height_sd_m", "release_speed_sd_m_s")})


def _effects(path: str, sec: dict, model: str) -> tuple[str, ...]:
    """The effects a model section names (key ``<model>.effects``), checked: known
    CRSP effects, each once; the DEM runs none."""
    raw = sec.get("effects")
    if raw is None:
        return ()
    where = f"{path}: key '{model}.effects'"
    if not isinstance(raw, list) or not all(isinstance(e, str) for e in raw):
        raise CalibrationError(f"{where}: expected a list of effect names, got {raw!r}")
    if model == "dem" and [e for e in raw if e != "none"]:
        raise CalibrationError(f"{where}: the DEM runs no effect from a calibration file "
                               f"(calib.fit fits effects for CRSP only), got {', '.join(raw)}")
    try:
        return effect_names(raw)
    except ValueError as e:
        raise CalibrationError(f"{where}: {e}") from None


def fitted_block_sizes_m(cal: Calibration) -> tuple[np.ndarray, str] | None:
    """The block sizes d (m) of the rows a calibration was fitted on, and where they
    were read: the file's ``release_groups.groups[*].block_size_m``, else the column
    ``block_size_m`` of its ``data_csv``; None where neither is readable (a hazard
    run then cannot say which of its sizes are extrapolation)."""
    doc = _read_doc(cal.path)
    groups = doc.get("release_groups")
    rows = groups.get("groups") if isinstance(groups, dict) else None
    if isinstance(rows, list):
        sizes = [g.get("block_size_m") for g in rows if isinstance(g, dict)]
        sizes = [float(v) for v in sizes if isinstance(v, int | float)
                 and not isinstance(v, bool) and math.isfinite(v) and v > 0]
        if sizes:
            return np.asarray(sizes), f"{cal.path}: release_groups.groups[*].block_size_m"
    if cal.data_csv is None or not os.path.isfile(cal.data_csv):
        return None
    try:
        with open(cal.data_csv, newline="", encoding="utf-8") as fh:
            sizes = [float(r["block_size_m"]) for r in csv.DictReader(fh)
                     if (r.get("block_size_m") or "").strip()]
    except (KeyError, ValueError, OSError, UnicodeDecodeError):
        return None
    sizes = [v for v in sizes if math.isfinite(v) and v > 0]
    return (np.asarray(sizes), f"{cal.data_csv}: column block_size_m") if sizes else None


def fitted_block_shapes(cal: Calibration) -> tuple[str, ...]:
    """The CRSP shape classes a calibration simulated its rows as, sorted:
    ``release_groups.groups[*].shape``; ("sphere",) where the file records no
    shape (a fit of one release per size, and files written before the fit
    simulated the rows' shapes: both ran spheres)."""
    groups = _read_doc(cal.path).get("release_groups")
    rows = groups.get("groups") if isinstance(groups, dict) else None
    shapes = {g.get("shape") or "sphere" for g in rows if isinstance(g, dict)} if isinstance(
        rows, list) else set()
    return tuple(sorted(str(f) for f in shapes)) or ("sphere",)


def _with_heights(doc: dict) -> bool:
    """The fit recorded a release height for its release groups (``calib.fit``
    writes the key for every group, null where the rows give none)."""
    groups = doc.get("release_groups")
    rows = groups.get("groups") if isinstance(groups, dict) else None
    return isinstance(rows, list) and any(isinstance(g, dict) and "release_height_m" in g
                                          for g in rows)


def _grouped(doc: dict, key: str = "models") -> list:
    """The models that released each row from its own point (``release_groups.models``),
    or (``key`` "speed_and_height_models") also at its own speed and height."""
    groups = doc.get("release_groups")
    models = groups.get(key) if isinstance(groups, dict) else None
    return models if isinstance(models, list) else []


def _dem_run(path: str, sec: dict) -> dict | None:
    """The DEM section's ``run`` (the fit's numerics), checked, or None."""
    run = sec.get("run")
    if run is None:
        return None
    if not isinstance(run, dict):
        raise CalibrationError(f"{path}: key 'dem.run': expected an object")
    out = {}
    for key in ("stiffness_scale", "max_time_s", "dt_size_m"):
        if key not in run:
            raise CalibrationError(f"{path}: key 'dem.run.{key}' missing")
        out[key] = _number(path, f"key 'dem.run.{key}'", run[key], -math.inf, math.inf, True)
    try:  # the solver's one check of these numerics
        check_run_numerics(out["stiffness_scale"], out["max_time_s"],
                           names={k: f"key 'dem.run.{k}'" for k in out})
    except ValueError as e:
        raise CalibrationError(f"{path}: {e}") from None
    if not out["dt_size_m"] > 0.0:
        raise CalibrationError(f"{path}: key 'dem.run.dt_size_m': expected a positive size, "
                               f"got {out['dt_size_m']:g}")
    return out


def draw_parameters(cal: Calibration, n_posterior: int, seed: int) -> Draws:
    """The parameter sets of a hazard run.

    ``n_posterior == 1``: the point estimate (``map``). Otherwise ``n_posterior``
    distinct rows of the posterior sample, chosen without replacement by a NumPy
    generator seeded with ``seed`` (the same seed gives the same rows) and kept
    in file order. Without a posterior sample (gradient-only fit) every draw is
    the point estimate: the draws are then replicate runs with independent
    random numbers, and their spread is Monte Carlo noise only.

    Raises:
        CalibrationError: more draws asked for than the posterior has rows.
    """
    if n_posterior < 1:
        raise CalibrationError(f"--n-posterior: expected a positive count, got {n_posterior}")
    if n_posterior == 1:
        return Draws(cal.point[None, :], cal.names, np.array([-1]), "point estimate")
    if cal.posterior is None:
        return Draws(np.repeat(cal.point[None, :], n_posterior, axis=0), cal.names,
                     np.full(n_posterior, -1),
                     "point estimate (no posterior sample: replicate runs)")
    n_rows = cal.posterior.shape[0]
    if n_posterior > n_rows:
        raise CalibrationError(f"--n-posterior {n_posterior}: {cal.posterior_csv} has only "
                               f"{n_rows} rows")
    rng = np.random.default_rng(seed)
    rows = np.sort(rng.choice(n_rows, size=n_posterior, replace=False))
    return Draws(cal.posterior[rows], cal.names, rows + 1, "posterior")


class ParameterSummary(NamedTuple):
    """One fitted quantity as the file records it (``summary_stats``): the point
    estimate ``map``, and the posterior ``mean`` and 5 % / 95 % quantiles (None
    after a gradient-only fit)."""

    map: float
    mean: float | None
    q05: float | None
    q95: float | None


class ModelSummary(NamedTuple):
    """One model's section of the file, as a reader shows it (``CalibrationFile.summary``).

    Attributes:
        parameters: name -> ``ParameterSummary``, in the file's order (DEM: the
            alpha law's ``a``, ``b`` or ``alpha``).
        prior: name -> (lower, upper) of the prior box.
        alpha_form: DEM: "power" or "constant"; "" for CRSP.
        alpha_at_L: DEM: square side L (m) -> alpha(L) as a ``ParameterSummary``;
            {} for CRSP.
        alpha_reference: DEM: L -> the published alpha the site file gives
            there (``calib.files.site``); {} where it gives none.
        diagnostics_ok: the posterior passed its diagnostics; None without a
            Bayesian fit.
        problems: the diagnostics that failed, in words.
        adequacy: the adequacy record (``calib.inference.adequacy``), or None.
        fit_quality: one record per observed row (``calib.inference.fit_check``).
        timings_s: stage -> seconds.
    """

    parameters: dict
    prior: dict
    alpha_form: str
    alpha_at_L: dict
    alpha_reference: dict
    diagnostics_ok: bool | None
    problems: tuple[str, ...]
    adequacy: dict | None
    fit_quality: list
    timings_s: dict


def _parameter_summary(entry: dict) -> ParameterSummary:
    return ParameterSummary(entry["map"], entry.get("mean"), entry.get("q05"), entry.get("q95"))


@dataclasses.dataclass
class CalibrationFile:
    """The whole calibration file, as ``calib.fit`` writes it and everyone reads it.

    ``to_json`` is the one writer (schema version ``SCHEMA`` first, then the
    inputs, the record and the model sections; no NaN); ``from_json`` the one
    reader of the whole document: it checks the schema and runs every model
    section present through ``load_calibration``'s checks, so a file it accepts
    is one ``calib.hazard`` and ``calib.validate`` accept.

    Attributes:
        profile_csv, data_csv: the inputs of the fit (paths as written).
        seed: the fit's PRNG seed.
        release_x_m: the one release of the DEM fit, the figures and the hazard
            run's default, m, or None (the profile's first vertex).
        models: {"crsp": section, "dem": section}, the models fitted.
        record: every other key (command, provenance, versions, release groups,
            fit quality per model, timings, ...), kept as written.
        schema: the schema version.
        path: the file read (None for a document built in memory).
    """

    profile_csv: str
    data_csv: str
    seed: int
    release_x_m: float | None
    models: dict
    record: dict = dataclasses.field(default_factory=dict)
    schema: str = SCHEMA
    path: str | None = None

    _TOP = ("schema", "profile_csv", "data_csv", "seed", "release_x_m")

    @property
    def doc(self) -> dict:
        """The document as one dict (what ``to_json`` writes)."""
        out = {k: getattr(self, k) for k in self._TOP}
        out.update(self.record)
        out.update(self.models)
        return out

    @classmethod
    def from_dict(cls, doc: dict, path: str | None = None) -> CalibrationFile:
        """Split a document into its parts; the schema must be ``SCHEMA`` and
        ``profile_csv``, ``data_csv`` and ``seed`` present."""
        where = path or "<calibration>"
        if doc.get("schema") != SCHEMA:
            raise CalibrationError(f"{where}: key 'schema': expected {SCHEMA!r}, got "
                                   f"{doc.get('schema')!r}")
        for key in ("profile_csv", "data_csv", "seed"):
            if key not in doc:
                raise CalibrationError(f"{where}: key {key!r} missing")
        models = {m: doc[m] for m in ("crsp", "dem") if doc.get(m) is not None}
        record = {k: v for k, v in doc.items() if k not in cls._TOP and k not in
                  ("crsp", "dem")}
        return cls(doc["profile_csv"], doc["data_csv"], doc["seed"], doc.get("release_x_m"),
                   models, record, doc["schema"], path)

    def to_json(self) -> str:
        return json.dumps(self.doc, indent=1, allow_nan=False) + "\n"

    @classmethod
    def from_json(cls, path: str) -> CalibrationFile:
        doc = _read_doc(path)
        out = cls.from_dict(doc, path)
        if not out.models:
            raise CalibrationError(f"{path}: neither a 'crsp' nor a 'dem' section")
        for m in out.models:
            _model_from_doc(path, doc, m)
        return out

    @property
    def command(self) -> str | None:
        """The command line of the fit (key ``command``)."""
        return self.record.get("command")

    @property
    def quick(self) -> bool:
        """The fit ran with the small budgets (key ``quick``)."""
        return bool(self.record.get("quick"))

    @property
    def timings_s(self) -> dict:
        """Stage times per model and ``total_s``, s (key ``timings_s``)."""
        return self.record.get("timings_s", {})

    def summary(self, model: str) -> ModelSummary:
        """The section of ``model`` ("crsp" or "dem") as a ``ModelSummary``."""
        if model not in self.models:
            raise CalibrationError(f"{self.path or '<calibration>'}: no {model!r} section "
                                   f"(this file calibrates {', '.join(self.models)})")
        sec = self.models[model]
        for key in ("parameters", "prior"):
            if key not in sec:
                raise CalibrationError(f"{self.path or '<calibration>'}: key "
                                       f"'{model}.{key}' missing")
        law = sec.get("alpha_law") or {}
        values = law if model == "dem" else sec
        at_l = sec.get("alpha_at_L") or {}
        bayes = sec.get("bayes")
        return ModelSummary(
            {n: _parameter_summary(values[n]) for n in sec["parameters"]},
            {n: (float(lo), float(hi)) for n, (lo, hi) in sec["prior"].items()},
            law.get("form", ""),
            {float(k): _parameter_summary(v) for k, v in at_l.items()},
            {float(k): v["reference"] for k, v in at_l.items() if "reference" in v},
            None if bayes is None else bool(bayes["ok"]),
            () if bayes is None else tuple(bayes["problems"]),
            sec.get("adequacy"),
            list(self.record.get("fit_quality", {}).get(model, sec.get("fit_quality", []))),
            dict(sec.get("timings_s", {})))

    def calibration(self, model: str | None = None) -> Calibration:
        """One model's ``Calibration`` (what the hazard run and validate use)."""
        if self.path is None:
            raise CalibrationError("a calibration built in memory has no file to resolve "
                                   "its paths against; write it with to_json first")
        return _model_from_doc(self.path, self.doc, model)
