"""Field rockfall runs (release and stop points) as observed runouts on a profile:
the library of ``python -m calib.field`` (the command is ``calib/field.py``).

Reads tracked field runs, one row per run: a release point and a stop point in
plan (east, north, in the coordinates of the profile's raster), the block's
mass (or its three dimensions), optionally the velocity at release; projects
both points onto the profile's plan trace (the ``east_m,north_m`` columns that
``python -m terrain.cut`` writes); and writes one observation row per
run in the schema of ``calib.files.observations``.

Definitions (the equations are standard; which one applies is our choice):

* Along-line position: the orthogonal projection onto the plan trace
  (``terrain.plan_line.Polyline.project``); ``release_x_m`` is the release's
  profile abscissa, and ``runout_m = x(stop) - x(release)``, a horizontal
  distance along the profile. The lateral offset of each point from the trace
  (m, positive to the left looking downslope) is reported per row; the 2D
  profile ignores it, so rows beyond ``--max-offset-m`` are flagged and named
  in a warning (and kept).
* Block size ``block_size_m`` (the "average diameter" d of
  ``calib.files.observations``): by default the VOLUME-EQUIVALENT SPHERE diameter
  from the mass, d = (6 m / (pi rho))^(1/3), with density rho from
  ``--density-kg-m3``. Only when a run's mass is missing (empty) it is the
  geometric mean of the three block dimensions, d = (a b c)^(1/3): the edge of
  the cube with the volume of the bounding box, which overestimates a natural
  rock's volume-equivalent diameter (a rock fills only part of its box).
* ``shape`` (CRSP's classes sphere / cylinder / disc, ``solvers.crsp.make_block``)
  from the dimensions where known. OUR OWN RULE, after Zingg's (1935) form
  classes: with a >= b >= c, p = b / a and q = c / b (both rounded to 6
  decimals), a block is a ``disc`` if q <= 2/3 (flat: Zingg's discs and
  blades), a ``cylinder`` if p <= 2/3 < q (one long axis: Zingg's rods), else a
  ``sphere`` (equant). A ratio on a class boundary goes to the less equant
  class. The CRSP 4.0 manual's own rule, if it has one, was not found.
* ``release_speed_m_s``: |v| = sqrt(vx^2 + vy^2 + vz^2) of the release velocity
  columns, where they are given.
* ``release_height_m``: where the runs give the release point's height (a
  ``release_z_m`` column, in the vertical datum of the profile) and the profile
  its heights: h = z_release - d / 2 - ground(x_release), the height of the
  block's lowest point above the profile's ground under the projected release.
  OUR OWN CHOICES: the tracked point is the block's centre (a sensor inside the
  block, as in the Tschamut campaign's LPS) and d is ``block_size_m``. h is
  recorded AS MEASURED, negative values included: a release that lies below
  the profile's ground (h < 0, counted in the command's summary) says that the
  profile's ground there, a raster's (and a 2D line's, for a release off the
  line), lies above the true ground, not that the rock started inside it. The
  CRSP runs (``calib.model.forward.CrspForward``, ``solvers.crsp.init``) start
  each block at a height drawn from N(h, sd^2) truncated to >= 0, sd the
  site's ``release_height_sd_m`` (``calib.files.site``; a negative h is then a
  release from the error's tail above the ground); with sd 0 a negative h is
  clipped, a release on the ground. The DEM releases on the ground where h < 0
  (``calib.model.entries``).

Defaults that are ASSUMPTIONS (state them with the data they make):

* ``--density-kg-m3`` 2650: the density of quartz and a common value for
  granite and gneiss; field data sets give masses, seldom densities.
* ``--runout-sd-m`` 2 m: a tracking system's metre-scale position error at
  each end of a run, plus the last tracked sample preceding the final rest.
* ``--max-offset-m`` 20 m: four 5 m cells of a typical terrain raster.

Bad input (one line naming the file, line and column; exit 2; nothing
written): a missing or non-numeric coordinate; a mass or dimension that is
negative, zero, NaN or not a number; a run with neither a mass nor three
dimensions; a run whose stop lies upslope of (before) its release along the
line; a point that projects beyond either end of the profile.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
from collections.abc import Sequence

import numpy as np

from calib.model.entries import sphere_diameter_m
from solvers.csv_rows import cell_float, read_csv_rows

__all__ = [
    "DEFAULT_DENSITY_KG_M3",
    "DEFAULT_MAX_OFFSET_M",
    "DEFAULT_RUNOUT_SD_M",
    "FieldError",
    "FieldRuns",
    "RunColumns",
    "box_diameter_m",
    "crsp_shape",
    "field_observations",
    "load_runs",
    "nearest_profiles",
    "observations_csv_text",
    "observations_on_profiles",
    "take_runs",
    "sphere_diameter_m",
]

DEFAULT_DENSITY_KG_M3 = 2650.0
DEFAULT_RUNOUT_SD_M = 2.0
DEFAULT_MAX_OFFSET_M = 20.0
OUTPUT_COLUMNS = ("block_size_m", "runout_m", "runout_sd_m", "runout_min_m", "runout_max_m",
                  "source", "run_id", "block_id", "release_x_m", "release_speed_m_s", "shape",
                  "mass_kg", "release_offset_m", "stop_offset_m", "beyond_max_offset",
                  "release_height_m")


class FieldError(ValueError):
    """Bad field-run input; the message names the file, line and column."""


@dataclasses.dataclass(frozen=True)
class RunColumns:
    """Column names of a runs table (and of a blocks table joined on ``block_id``).

    The defaults are those of the Tschamut 2014 files (``data/tschamut2014``).
    """

    run_id: str = "run_id"
    block_id: str = "block_id"
    mass: str = "mass_kg"
    release: tuple[str, str] = ("release_x_m", "release_y_m")
    stop: tuple[str, str] = ("stop_x_m", "stop_y_m")
    velocity: tuple[str, str, str] = ("release_vx_m_s", "release_vy_m_s", "release_vz_m_s")
    size: tuple[str, str, str] = ("size_x_m", "size_y_m", "size_z_m")
    release_z: str = "release_z_m"


@dataclasses.dataclass(frozen=True)
class FieldRuns:
    """Validated field runs (arrays of length R, one entry per run).

    Attributes:
        run_id, block_id: identifiers (text; row numbers when the column is absent).
        line: the file line of each run (header = line 1), for messages.
        release_east_m, release_north_m, stop_east_m, stop_north_m: plan points, m.
        mass_kg: block mass, kg; NaN where unknown.
        size_m: (R, 3) block dimensions, m; NaN rows where unknown.
        release_speed_m_s: speed at release, m/s; NaN where not given.
        release_z_m: height of the release point, m; NaN where not given.
        path: the runs file.
    """

    run_id: tuple[str, ...]
    block_id: tuple[str, ...]
    line: tuple[int, ...]
    release_east_m: np.ndarray
    release_north_m: np.ndarray
    stop_east_m: np.ndarray
    stop_north_m: np.ndarray
    mass_kg: np.ndarray
    size_m: np.ndarray
    release_speed_m_s: np.ndarray
    release_z_m: np.ndarray | None = None
    path: str = "<memory>"

    def __post_init__(self):
        if self.release_z_m is None:
            object.__setattr__(self, "release_z_m", np.full(len(self.run_id), np.nan))

    @property
    def n_runs(self) -> int:
        return len(self.run_id)


def box_diameter_m(size_m) -> np.ndarray:
    """Geometric mean of three dimensions, d = (a b c)^(1/3), m: the edge of the
    cube of the bounding box's volume.

    Args:
        size_m: (..., 3) dimensions, m.
    """
    return np.cbrt(np.prod(np.asarray(size_m, float), axis=-1))


def crsp_shape(size_m) -> str:
    """CRSP shape class of a block of dimensions (a, b, c), m (module docstring:
    our own rule after Zingg 1935)."""
    c, b, a = np.sort(np.asarray(size_m, float))
    p, q = round(b / a, 6), round(c / b, 6)
    limit = round(2.0 / 3.0, 6)
    if q <= limit:
        return "disc"
    if p <= limit:
        return "cylinder"
    return "sphere"


def _read(path: str, what: str) -> tuple[list[str], list[tuple[int, dict[str, str]]]]:
    return read_csv_rows(path, what, FieldError)


def _value(path: str, line: int, row: dict, col: str, *, positive: bool = False,
           required: bool = True) -> float:
    """A cell as a float; empty -> NaN unless required; errors name line and column."""
    text = row.get(col, "")
    if text == "":
        if required:
            raise FieldError(f"{path}: line {line}: column {col!r}: missing value")
        return math.nan
    v = cell_float(path, line, row, col, FieldError)
    if positive and v <= 0:
        raise FieldError(f"{path}: line {line}: column {col!r}: expected a positive value, "
                         f"got {text!r}")
    return v


def load_runs(path: str | os.PathLike, blocks_path: str | os.PathLike | None = None,
              columns: RunColumns = RunColumns()) -> FieldRuns:
    """Read and validate a runs CSV, joining a blocks table on the block id.

    A run's mass is its own ``mass`` cell; if that is empty (or the column
    absent), the blocks table's. Dimensions likewise (``size`` columns). A
    non-empty mass or dimension must be a positive finite number.

    Args:
        path: runs CSV (columns named by ``columns``).
        blocks_path: optional blocks CSV with the block id column and mass
            and/or size columns.
        columns: the column names.

    Returns:
        ``FieldRuns``.

    Raises:
        FieldError: naming file, line and column (module docstring).
    """
    path = os.fspath(path)
    c = columns
    header, rows = _read(path, ",".join(c.release + c.stop))
    missing = [k for k in c.release + c.stop if k not in header]
    if missing:
        raise FieldError(f"{path}: line 1: missing column(s) {', '.join(missing)} (found "
                         f"{', '.join(header)})")
    if not rows:
        raise FieldError(f"{path}: no runs after the header")
    bpath = os.fspath(blocks_path) if blocks_path is not None else None
    blocks = {} if bpath is None else _read_blocks(path, bpath, header, c)
    out: dict[str, list] = {k: [] for k in ("run_id", "block_id", "line", "re", "rn", "se", "sn",
                                            "mass", "size", "speed", "z")}
    for i, (line, row) in enumerate(rows):
        for key, val in _run_row(path, bpath, blocks, header, c, i, line, row).items():
            out[key].append(val)
    return FieldRuns(tuple(out["run_id"]), tuple(out["block_id"]), tuple(out["line"]),
                     np.array(out["re"]), np.array(out["rn"]), np.array(out["se"]),
                     np.array(out["sn"]), np.array(out["mass"]), np.array(out["size"]),
                     np.array(out["speed"]), np.array(out["z"]), path)


def _read_blocks(path: str, bpath: str, header: list[str],
                 c: RunColumns) -> dict[str, tuple[int, dict]]:
    """The blocks table keyed by block id: (line, row) of each block; the runs
    file must have the block id column to join on, and each id is given once."""
    if c.block_id not in header:
        raise FieldError(f"{path}: line 1: missing column {c.block_id!r} to join "
                         f"{bpath} on")
    bheader, brows = _read(bpath, c.block_id)
    if c.block_id not in bheader:
        raise FieldError(f"{bpath}: line 1: missing column {c.block_id!r}")
    blocks: dict[str, tuple[int, dict]] = {}
    for bline, brow in brows:
        key = brow[c.block_id]
        if key in blocks:
            raise FieldError(f"{bpath}: line {bline}: column {c.block_id!r}: duplicate "
                             f"block {key!r}")
        blocks[key] = (bline, brow)
    return blocks


def _run_row(path: str, bpath: str | None, blocks: dict[str, tuple[int, dict]],
             header: list[str], c: RunColumns, i: int, line: int, row: dict) -> dict:
    """One run's validated values (row ``i``, file line ``line``): its ids, release
    and stop points, mass and dimensions (its own cells, else its block's in the
    blocks table), release speed (NaN unless every velocity component is given:
    the Euclidean norm) and release height (NaN without the column)."""
    run_id = row.get(c.run_id) or f"row {i + 1}"
    block = row.get(c.block_id, "")
    brow = None
    if bpath is not None:
        if block not in blocks:
            raise FieldError(f"{path}: line {line}: column {c.block_id!r}: block {block!r} "
                             f"is not in {bpath}")
        brow = blocks[block]
    re_, rn = (_value(path, line, row, k) for k in c.release)
    se, sn = (_value(path, line, row, k) for k in c.stop)
    mass = _value(path, line, row, c.mass, positive=True, required=False)
    if math.isnan(mass) and brow is not None:
        mass = _value(bpath, brow[0], brow[1], c.mass, positive=True, required=False)
    size = _size(path, line, row, c.size)
    if np.isnan(size).all() and brow is not None:
        size = _size(bpath, brow[0], brow[1], c.size)
    if math.isnan(mass) and np.isnan(size).all():
        where = f" or in {bpath} for block {block!r}" if bpath else ""
        raise FieldError(f"{path}: line {line}: column {c.mass!r}: run {run_id} has no mass "
                         f"and no dimensions ({', '.join(c.size)}){where}")
    speed = math.nan
    if all(k in header for k in c.velocity):
        v = [_value(path, line, row, k, required=False) for k in c.velocity]
        if not any(math.isnan(x) for x in v):
            speed = math.sqrt(sum(x * x for x in v))
    z = (_value(path, line, row, c.release_z, required=False)
         if c.release_z and c.release_z in header else math.nan)
    return {"run_id": run_id, "block_id": block, "line": line, "re": re_, "rn": rn, "se": se,
            "sn": sn, "mass": mass, "size": size, "speed": speed, "z": z}


def _size(path: str, line: int, row: dict, cols: Sequence[str]) -> np.ndarray:
    """Three dimensions, or NaNs when all are absent; a partial set is an error."""
    vals = np.array([_value(path, line, row, k, positive=True, required=False)
                     if k in row else math.nan for k in cols])
    if np.isnan(vals).any() and not np.isnan(vals).all():
        k = cols[int(np.flatnonzero(np.isnan(vals))[0])]
        raise FieldError(f"{path}: line {line}: column {k!r}: missing value (a block needs all "
                         f"three dimensions {', '.join(cols)}, or none)")
    return vals


def field_observations(runs: FieldRuns, profile_x_m: np.ndarray, trace, *,
                       density_kg_m3: float = DEFAULT_DENSITY_KG_M3,
                       runout_sd_m: float = DEFAULT_RUNOUT_SD_M,
                       max_offset_m: float = DEFAULT_MAX_OFFSET_M,
                       source: str = "", columns: RunColumns = RunColumns(),
                       profile_path: str = "<profile>",
                       profile_z_m: np.ndarray | None = None) -> list[dict]:
    """One observation row per run (columns ``OUTPUT_COLUMNS``).

    Args:
        runs: the validated runs.
        profile_x_m: (V,) profile abscissae, m.
        trace: the profile's plan trace (``terrain.plan_line.Polyline``, V vertices).
        density_kg_m3: rho of d = (6 m / (pi rho))^(1/3).
        runout_sd_m: tolerance written to every row, m.
        max_offset_m: rows with a point farther than this from the trace are
            flagged (``beyond_max_offset``).
        source: provenance text; each row's ``source`` is ``"<source>: run <id>"``.
        columns: column names (for messages).
        profile_path: name of the profile (for messages).
        profile_z_m: (V,) profile heights, m, in the datum of the runs'
            ``release_z_m``; None: no ``release_height_m``.

    Returns:
        A list of dicts, one per run, in file order.

    Raises:
        FieldError: a stop upslope of its release, or a point beyond an end of
            the profile (naming the runs file, line and column).
    """
    c = columns
    x0 = float(profile_x_m[0])
    x_end = float(profile_x_m[-1])
    r_along, r_off = trace.project(runs.release_east_m, runs.release_north_m)
    s_along, s_off = trace.project(runs.stop_east_m, runs.stop_north_m)
    r_x, s_x = r_along + x0, s_along + x0
    for i in range(runs.n_runs):
        for what, col, x in (("release", c.release[0], r_x[i]), ("stop", c.stop[0], s_x[i])):
            if not (x0 <= x <= x_end):
                raise FieldError(
                    f"{runs.path}: line {runs.line[i]}: column {col!r}: the {what} of run "
                    f"{runs.run_id[i]} projects to {x:.2f} m along the profile, outside "
                    f"{profile_path} ({x0:g} to {x_end:.2f} m); cut a longer profile")
        if s_x[i] < r_x[i]:
            raise FieldError(
                f"{runs.path}: line {runs.line[i]}: column {c.stop[0]!r}: the stop of run "
                f"{runs.run_id[i]} lies upslope of its release along the profile ({s_x[i]:.2f} m "
                f"< {r_x[i]:.2f} m)")
    use_mass = ~np.isnan(runs.mass_kg)
    d = np.where(use_mass, sphere_diameter_m(np.where(use_mass, runs.mass_kg, 1.0),
                                             density_kg_m3),
                 box_diameter_m(np.nan_to_num(runs.size_m, nan=1.0)))
    clearance = np.full(runs.n_runs, np.nan)
    if profile_z_m is not None:
        ground = np.interp(r_x, np.asarray(profile_x_m, float), np.asarray(profile_z_m, float))
        clearance = runs.release_z_m - 0.5 * d - ground
    rows = []
    for i in range(runs.n_runs):
        size = runs.size_m[i]
        flag = bool(max(abs(r_off[i]), abs(s_off[i])) > max_offset_m)
        rows.append({
            "block_size_m": float(d[i]),
            "runout_m": float(s_x[i] - r_x[i]),
            "runout_sd_m": runout_sd_m,
            "runout_min_m": None, "runout_max_m": None,
            "source": f"{source}: run {runs.run_id[i]}" if source else f"run {runs.run_id[i]}",
            "run_id": runs.run_id[i], "block_id": runs.block_id[i],
            "release_x_m": float(r_x[i]),
            "release_speed_m_s": float(runs.release_speed_m_s[i]),
            "release_height_m": float(clearance[i]),
            "shape": "" if np.isnan(size).any() else crsp_shape(size),
            "mass_kg": float(runs.mass_kg[i]),
            "release_offset_m": float(r_off[i]), "stop_offset_m": float(s_off[i]),
            "beyond_max_offset": flag,
        })
    return rows


_FORMATS = {"block_size_m": "{:.4f}", "runout_m": "{:.3f}", "runout_sd_m": "{:g}",
            "release_x_m": "{:.3f}", "release_speed_m_s": "{:.3f}", "mass_kg": "{:g}",
            "release_height_m": "{:.3f}",
            "release_offset_m": "{:.3f}", "stop_offset_m": "{:.3f}"}


def nearest_profiles(runs: FieldRuns, traces) -> np.ndarray:
    """(R,) index of the profile each run belongs to, among profiles with plan
    traces ``traces`` (``terrain.plan_line.Polyline``): the one whose trace
    passes nearest the run's RELEASE point (smallest lateral offset; the first
    on a tie). Our choice: a run follows the fall line of the spot it was let
    go from, and where it stops is what is observed, so the stop point must not
    choose its own line. One profile per release spot is the 2D model's answer
    to runs let go from spots far apart across the slope."""
    off = np.stack([np.abs(t.project(runs.release_east_m, runs.release_north_m)[1])
                    for t in traces])
    return np.argmin(off, axis=0)


def observations_on_profiles(runs: FieldRuns, profile_paths: Sequence[str],
                             out_dir: str = ".", **options) -> list[dict]:
    """One observation row per run (``field_observations``), each run on the
    profile whose plan trace passes nearest its release (``nearest_profiles``).

    Args:
        runs: the validated runs (``load_runs``).
        profile_paths: profile CSVs with plan traces (``python -m terrain.cut``
            writes them); a path given twice counts once.
        out_dir: the folder of the observations CSV the rows are for: with
            more than one profile, each row's ``profile`` is its profile's path
            relative to it (``calib.files.observations`` resolves it so).
        **options: ``density_kg_m3``, ``runout_sd_m``, ``max_offset_m``,
            ``source``, ``columns`` of ``field_observations``.

    Returns:
        The rows in the runs' order.

    Raises:
        FieldError: a profile no run's release lies nearest to, or bad runs
            (``field_observations``); ``terrain.raster.RasterError`` or
            ``solvers.profile.ProfileError``: a profile that does not read.
    """
    from solvers.profile import load_profile
    from terrain.plan_line import read_profile_trace

    paths = list(dict.fromkeys(profile_paths))
    traces = [read_profile_trace(p) for p in paths]
    which = nearest_profiles(runs, [t for _, t in traces])
    rows: list = [None] * runs.n_runs
    for k, (path, (x, trace)) in enumerate(zip(paths, traces)):
        idx = np.flatnonzero(which == k)
        if not idx.size:
            raise FieldError(f"--profile {path}: no run's release lies nearer this profile "
                             "than the others; leave it out")
        sub = field_observations(take_runs(runs, idx), x, trace, profile_path=path,
                                 profile_z_m=np.asarray(load_profile(path).z_m), **options)
        rel = os.path.relpath(path, os.path.abspath(out_dir))
        for i, r in zip(idx, sub):
            if len(paths) > 1:
                r["profile"] = rel
            rows[i] = r
    return rows


def take_runs(runs: FieldRuns, idx) -> FieldRuns:
    """The runs ``idx`` (indices into ``runs``), in that order."""
    idx = [int(i) for i in idx]
    out = {}
    for f in dataclasses.fields(runs):
        v = getattr(runs, f.name)
        if isinstance(v, tuple):
            out[f.name] = tuple(v[i] for i in idx)
        elif isinstance(v, np.ndarray):
            out[f.name] = v[idx]
        else:
            out[f.name] = v
    return FieldRuns(**out)


def observations_csv_text(rows: list[dict]) -> str:
    """Rows of ``field_observations`` as CSV text (NaN and None as empty cells);
    with a ``profile`` column last where the rows give one (runs on several
    profiles, ``calib.field``)."""
    columns = OUTPUT_COLUMNS + (("profile",) if rows and "profile" in rows[0] else ())
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        cells = []
        for k in columns:
            v = r[k]
            if v is None or (isinstance(v, float) and math.isnan(v)):
                cells.append("")
            elif isinstance(v, bool):
                cells.append("true" if v else "false")
            elif k in _FORMATS:
                cells.append(_FORMATS[k].format(v))
            else:
                cells.append(str(v))
        w.writerow(cells)
    return buf.getvalue()
