"""Observed runouts: the table every fit reads, and the block-size mapping.

Schema (CSV, one row per observation; ``data/README.md``)::

    block_size_m, runout_m, runout_sd_m, runout_min_m, runout_max_m, source

* ``block_size_m``: average block diameter d, m (the paper's wording, Sect. 4.1).
* A row is either a POINT (``runout_m`` with tolerance ``runout_sd_m`` > 0) or an
  INTERVAL (``runout_min_m`` <= ``runout_max_m``; the runout was seen to lie in
  it). A row that gives both uses the interval.
* ``source``: free text (where the number comes from); optional column.

Optional columns of tracked field runs (``calib.field``; absent columns read as
NaN or empty text, and files without them behave exactly as before):

* ``release_x_m``: abscissa of the release point on the profile, m (NOT the
  east coordinate that a runs file may call by the same name);
* ``release_speed_m_s``: speed at release, m/s (>= 0), where tracked;
* ``release_height_m``: height (m) of the block's lowest point above the
  profile's ground at release, where known (a block dropped or thrown from a
  hand, a bucket or a cliff edge), as measured: negative where a tracked
  release lies below the ground of a profile cut from a raster (the raster's
  error, not the rock's: CRSP draws the block's height from the error's
  distribution above the ground, ``solvers.crsp.init``; without an error,
  on the ground); empty: released on the ground;
* ``run_id``: the run's identifier in its source;
* ``shape``: CRSP shape class ``sphere``, ``cylinder`` or ``disc`` (empty:
  unknown, simulated as a sphere), from the block's dimensions (rule in
  ``calib.files.field_runs``); CRSP simulates the row's block in that class,
  of the volume of the sphere of diameter ``block_size_m``
  (``calib.model.entries``);
* ``profile``: the profile CSV this row's ``release_x_m`` and ``runout_m`` are
  measured along, relative to the observation file's folder (empty: the
  command's profile). Runs released from spots far apart follow different fall
  lines; ``calib.field`` with several ``--profile`` puts each run on the
  nearest one, and every solver run simulates a row on its own profile.

Other columns are ignored.

A second, optional table holds PASSAGE VELOCITIES at stations (``load_velocities``)::

    station_x_m, block_size_m, velocity_m_s, velocity_sd_m_s, source

* one row per block seen passing the abscissa ``station_x_m`` (m, profile
  coordinates) with speed ``velocity_m_s`` (speed of the centre of mass at its
  first downslope passage, ``solvers.stations``), tolerance ``velocity_sd_m_s``
  > 0. Such speeds come from video or radar tracking of natural or induced
  rockfalls (e.g. the induced-rockfall campaigns of Dorren et al. 2006, Volkwein
  et al. 2018, whose blocks were filmed through a forest and an instrumented
  slope). Runouts and sizes alone cannot tell a lower tangential restitution
  from a belt of trees that brakes blocks lower down; a speed measured ABOVE the
  belt can (``docs/studies.md``, "Passage speeds").

What the solvers make of the rows (the block-size rule, grouping rows by
release into simulated entries) is ``calib.model.entries``.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np
import pandas as pd

from solvers.crsp import SHAPES

__all__ = ["ObservationError", "Observations", "Velocities", "load_observations",
           "load_velocities", "on_command_profile", "read_table", "rows_on_profile"]

REQUIRED = ("block_size_m",)
OPTIONAL = ("runout_m", "runout_sd_m", "runout_min_m", "runout_max_m", "source",
            "release_x_m", "release_speed_m_s", "run_id", "shape", "release_height_m",
            "profile")


class ObservationError(ValueError):
    """Bad observation file; the message names file, row and column."""


@dataclasses.dataclass(frozen=True)
class Observations:
    """Validated observations (NumPy arrays of length n_obs).

    Attributes:
        block_size_m: average diameter d, m.
        runout_m, runout_sd_m: point value and tolerance, m (NaN for intervals).
        runout_min_m, runout_max_m: interval ends, m (NaN for points).
        is_interval: True where the row is an interval.
        source: provenance text per row.
        path: file the rows came from.
        release_x_m: release abscissa on the profile, m (NaN where not given).
        release_speed_m_s: speed at release, m/s (NaN where not given).
        run_id: run identifier per row ("" where not given), str array.
        shape: CRSP shape class per row ("" where not given), str array.
        release_height_m: release height above the ground, m (NaN where not
            given: on the ground).
        profile: profile file of each row, resolved against the observation
            file's folder ("" where not given: the command's profile), str array.
        columns, cells: the file's header and each row's cells as read (text),
            so that a subset of the rows is written back exactly as they were
            validated (``calib.files.split``); None for rows built in memory.
    """

    block_size_m: np.ndarray
    runout_m: np.ndarray
    runout_sd_m: np.ndarray
    runout_min_m: np.ndarray
    runout_max_m: np.ndarray
    is_interval: np.ndarray
    source: tuple[str, ...]
    path: str = "<memory>"
    release_x_m: np.ndarray | None = None
    release_speed_m_s: np.ndarray | None = None
    run_id: np.ndarray | None = None
    shape: np.ndarray | None = None
    release_height_m: np.ndarray | None = None
    profile: np.ndarray | None = None
    columns: tuple[str, ...] | None = None
    cells: tuple[tuple[str, ...], ...] | None = None

    def __post_init__(self):
        n = int(np.shape(self.block_size_m)[0])
        for name in ("release_x_m", "release_speed_m_s", "release_height_m"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(n, np.nan))
        for name in ("run_id", "shape", "profile"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(n, "", dtype=object))

    @property
    def n_obs(self) -> int:
        return int(self.block_size_m.shape[0])

    @property
    def sizes_m(self) -> np.ndarray:
        """Distinct block sizes, ascending (the solvers run once per size)."""
        return np.unique(self.block_size_m)

    @property
    def size_index(self) -> np.ndarray:
        """Index of each row's size in ``sizes_m``."""
        return np.searchsorted(self.sizes_m, self.block_size_m)

    @property
    def centre_m(self) -> np.ndarray:
        """The point value, or the interval's mid-point, m (for plots and residuals)."""
        mid = 0.5 * (self.runout_min_m + self.runout_max_m)
        return np.where(self.is_interval, mid, self.runout_m)

    @staticmethod
    def points(block_size_m, runout_m, runout_sd_m, source=None) -> Observations:
        """Point observations from arrays (synthetic data, tests)."""
        d = np.asarray(block_size_m, float)
        n = d.shape[0]
        nan = np.full(n, np.nan)
        return Observations(d, np.asarray(runout_m, float) * np.ones(n),
                            np.asarray(runout_sd_m, float) * np.ones(n), nan, nan.copy(),
                            np.zeros(n, bool), tuple(source or ("synthetic",) * n))


@dataclasses.dataclass(frozen=True)
class Velocities:
    """Validated passage-velocity observations (NumPy arrays of length n_obs).

    Attributes:
        station_x_m: abscissa of the station, m.
        block_size_m: average diameter d, m.
        velocity_m_s, velocity_sd_m_s: observed speed and its tolerance, m/s.
        source: provenance text per row.
        path: file the rows came from.
    """

    station_x_m: np.ndarray
    block_size_m: np.ndarray
    velocity_m_s: np.ndarray
    velocity_sd_m_s: np.ndarray
    source: tuple[str, ...]
    path: str = "<memory>"

    @property
    def n_obs(self) -> int:
        return int(self.block_size_m.shape[0])

    @property
    def stations_m(self) -> np.ndarray:
        """Distinct station abscissae, ascending (the solver records each once)."""
        return np.unique(self.station_x_m)

    @property
    def station_index(self) -> np.ndarray:
        """Index of each row's station in ``stations_m``."""
        return np.searchsorted(self.stations_m, self.station_x_m)


def _number(df: pd.DataFrame, col: str, path: str) -> np.ndarray:
    """Column as floats; a non-number names its file line and column."""
    out = np.full(len(df), np.nan)
    if col not in df.columns:
        return out
    for i, v in enumerate(df[col].tolist()):
        if v is None or (isinstance(v, float) and math.isnan(v)) or str(v).strip() == "":
            continue
        try:
            out[i] = float(v)
        except ValueError:
            raise ObservationError(f"{path}: line {i + 2}, column {col!r}: expected a number, "
                                   f"got {v!r}") from None
    return out


def read_table(path: str, header: str) -> pd.DataFrame:
    """The CSV at ``path`` as strings; a missing, empty or unreadable file raises."""
    if not os.path.isfile(path):
        raise ObservationError(f"{path}: no such file")
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False, comment="#")
    except pd.errors.EmptyDataError:
        raise ObservationError(f"{path}: empty file (expected a header '{header}')") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as e:
        raise ObservationError(f"{path}: not a readable CSV ({e})") from None
    df.columns = [c.strip() for c in df.columns]
    return df


def load_observations(path: str | os.PathLike) -> Observations:
    """Read and validate an observation CSV.

    Raises:
        ObservationError: missing file, empty table, missing column, non-numeric,
            non-finite or non-positive sizes, a row that is neither a point with a
            positive tolerance nor an interval, or an interval with min > max.
            The message names the file, line (header = line 1) and column.
    """
    path = os.fspath(path)
    df = read_table(path, "block_size_m,runout_m,runout_sd_m,...")
    for col in REQUIRED:
        if col not in df.columns:
            raise ObservationError(f"{path}: line 1: missing column {col!r} (columns: "
                                   f"{', '.join(df.columns)})")
    if not ({"runout_m", "runout_sd_m"} <= set(df.columns)
            or {"runout_min_m", "runout_max_m"} <= set(df.columns)):
        raise ObservationError(f"{path}: line 1: expected columns 'runout_m' and "
                               f"'runout_sd_m', or 'runout_min_m' and 'runout_max_m'")
    if len(df) == 0:
        raise ObservationError(f"{path}: no observation rows after the header")
    d = _number(df, "block_size_m", path)
    y = _number(df, "runout_m", path)
    sd = _number(df, "runout_sd_m", path)
    lo = _number(df, "runout_min_m", path)
    hi = _number(df, "runout_max_m", path)
    for i in range(len(df)):
        line = i + 2
        if not (np.isfinite(d[i]) and d[i] > 0):
            raise ObservationError(f"{path}: line {line}, column 'block_size_m': expected a "
                                   f"positive size in metres, got {df['block_size_m'][i]!r}")
        has_lo, has_hi = np.isfinite(lo[i]), np.isfinite(hi[i])
        if has_lo != has_hi:
            col = "runout_max_m" if has_lo else "runout_min_m"
            raise ObservationError(f"{path}: line {line}, column {col!r}: an interval needs "
                                   f"both runout_min_m and runout_max_m")
        if has_lo:
            if lo[i] < 0:
                raise ObservationError(f"{path}: line {line}, column 'runout_min_m': expected "
                                       f"a runout >= 0 m, got {lo[i]:g}")
            if lo[i] > hi[i]:
                raise ObservationError(f"{path}: line {line}, column 'runout_min_m': interval "
                                       f"min {lo[i]:g} > max {hi[i]:g}")
            continue
        if not np.isfinite(y[i]):
            raise ObservationError(f"{path}: line {line}, column 'runout_m': expected a runout "
                                   f"in metres (or an interval runout_min_m/runout_max_m)")
        if y[i] < 0:
            raise ObservationError(f"{path}: line {line}, column 'runout_m': expected a runout "
                                   f">= 0 m, got {y[i]:g}")
        if not (np.isfinite(sd[i]) and sd[i] > 0):
            raise ObservationError(f"{path}: line {line}, column 'runout_sd_m': expected a "
                                   f"positive tolerance in metres for a point observation")
    is_int = np.isfinite(lo)
    src = tuple(df["source"].tolist()) if "source" in df.columns else ("",) * len(df)
    x0, speed, run_id, shape, height, prof = _field_columns(df, path)
    return Observations(d, np.where(is_int, np.nan, y), np.where(is_int, np.nan, sd),
                        lo, hi, is_int, src, path, x0, speed, run_id, shape, height, prof,
                        tuple(df.columns), tuple(map(tuple, df.itertuples(index=False))))


def _field_columns(df: pd.DataFrame, path: str):
    """The optional field-run columns (module docstring), validated."""
    x0 = _number(df, "release_x_m", path)
    speed = _number(df, "release_speed_m_s", path)
    bad = np.flatnonzero(np.isinf(x0))
    if bad.size:
        raise ObservationError(f"{path}: line {bad[0] + 2}, column 'release_x_m': expected a "
                               f"finite abscissa in metres, got {df['release_x_m'][bad[0]]!r}")
    bad = np.flatnonzero(~(np.isnan(speed) | (np.isfinite(speed) & (speed >= 0))))
    if bad.size:
        raise ObservationError(f"{path}: line {bad[0] + 2}, column 'release_speed_m_s': "
                               f"expected a speed >= 0 m/s, got "
                               f"{df['release_speed_m_s'][bad[0]]!r}")
    height = _number(df, "release_height_m", path)
    bad = np.flatnonzero(~(np.isnan(height) | np.isfinite(height)))
    if bad.size:
        raise ObservationError(f"{path}: line {bad[0] + 2}, column 'release_height_m': "
                               f"expected a finite height above the ground, m, got "
                               f"{df['release_height_m'][bad[0]]!r}")
    text = {}
    for col in ("run_id", "shape", "profile"):
        vals = df[col].tolist() if col in df.columns else [""] * len(df)
        text[col] = np.array([str(v).strip() for v in vals], dtype=object)
    bad = [i for i, v in enumerate(text["shape"]) if v not in SHAPES + ("",)]
    if bad:
        raise ObservationError(f"{path}: line {bad[0] + 2}, column 'shape': expected one of "
                               f"{', '.join(SHAPES)} or empty, got {text['shape'][bad[0]]!r}")
    prof = text["profile"]
    folder = os.path.dirname(path)
    for i, v in enumerate(prof):
        if v:
            prof[i] = os.path.normpath(v if os.path.isabs(v) else os.path.join(folder, v))
            if not os.path.isfile(prof[i]):
                raise ObservationError(f"{path}: line {i + 2}, column 'profile': no such "
                                       f"profile file {v!r} (looked for {prof[i]})")
    return x0, speed, text["run_id"], text["shape"], height, prof


VELOCITY_COLUMNS = ("station_x_m", "block_size_m", "velocity_m_s", "velocity_sd_m_s")


def load_velocities(path: str | os.PathLike,
                    x_range_m: tuple[float, float] | None = None) -> Velocities:
    """Read and validate a passage-velocity CSV (schema in the module docstring).

    Args:
        path: the CSV.
        x_range_m: (x0, x1) of the profile the speeds are simulated on: every
            station must lie strictly inside it; None: not checked.

    Raises:
        ObservationError: missing file, empty table, missing column, or a row
            whose station is not a finite number (or not inside ``x_range_m``),
            whose size or tolerance is not positive, or whose speed is
            negative. The message names the file, line (header = line 1) and
            column.
    """
    path = os.fspath(path)
    df = read_table(path, ",".join(VELOCITY_COLUMNS))
    for col in VELOCITY_COLUMNS:
        if col not in df.columns:
            raise ObservationError(f"{path}: line 1: missing column {col!r} (columns: "
                                   f"{', '.join(df.columns)})")
    if len(df) == 0:
        raise ObservationError(f"{path}: no observation rows after the header")
    x, d, v, sd = (_number(df, c, path) for c in VELOCITY_COLUMNS)
    checks = (("station_x_m", x, lambda a: np.isfinite(a), "an abscissa in metres"),
              ("block_size_m", d, lambda a: np.isfinite(a) & (a > 0),
               "a positive size in metres"),
              ("velocity_m_s", v, lambda a: np.isfinite(a) & (a >= 0),
               "a speed >= 0 m/s"),
              ("velocity_sd_m_s", sd, lambda a: np.isfinite(a) & (a > 0),
               "a positive tolerance in m/s"))
    if x_range_m is not None:
        x0, x1 = x_range_m
        checks += (("station_x_m", x, lambda a: (a > x0) & (a < x1),
                    f"an abscissa inside the profile ({x0:g} to {x1:g} m)"),)
    for col, a, ok, what in checks:
        bad = np.flatnonzero(~ok(a))
        if bad.size:
            i = int(bad[0])
            raise ObservationError(f"{path}: line {i + 2}, column {col!r}: expected {what}, "
                                   f"got {df[col][i]!r}")
    src = tuple(df["source"].tolist()) if "source" in df.columns else ("",) * len(df)
    return Velocities(x, d, v, sd, src, path)


def on_command_profile(obs: Observations, profile_path: str) -> Observations:
    """Rows that name the command's own profile file run on it ("" in
    ``Observations.profile``), so that only the others are simulated apart."""
    own = getattr(obs, "profile", None)
    if own is None or not any(own):
        return obs
    prof = np.array([("" if p and os.path.samefile(p, profile_path) else p) for p in own],
                    dtype=object)
    return dataclasses.replace(obs, profile=prof)


def rows_on_profile(obs: Observations, profile, profile_path: str,
                    profile_of) -> Observations:
    """``obs`` with the rows that name ``profile_path`` moved onto it
    (``on_command_profile``), checked: every row's release lies on its profile
    (its own, read by ``profile_of(path)``, or the command's ``profile``) and
    its observed runout between that release and the profile's end; a row
    without a release is released at its profile's first vertex.

    Raises:
        ObservationError: the first row that fails, by line and column.
    """
    obs = on_command_profile(obs, profile_path)
    rel = np.asarray(getattr(obs, "release_x_m", np.full(obs.n_obs, np.nan)), float)
    own = getattr(obs, "profile", None)
    for i in range(obs.n_obs):
        if own is not None and own[i]:
            row_profile, row_path = profile_of(own[i]), own[i]
        else:
            row_profile, row_path = profile, profile_path
        start, x1 = float(row_profile.x_m[0]), float(row_profile.x_m[-1])
        x0 = rel[i] if np.isfinite(rel[i]) else start
        if not start <= x0 < x1:
            raise ObservationError(f"{obs.path}: line {i + 2}, column 'release_x_m': release "
                                   f"{x0:g} m lies outside the profile {row_path} ({start:g} "
                                   f"to {x1:g} m)")
        col, val = (("runout_min_m", obs.runout_min_m[i]) if obs.is_interval[i]
                    else ("runout_m", obs.runout_m[i]))
        if val > x1 - x0:
            raise ObservationError(f"{obs.path}: line {i + 2}, column {col!r}: runout {val:g} m "
                                   f"lies beyond the end of the profile {row_path} (it covers "
                                   f"{x1 - x0:g} m from the release at x = {x0:g} m); the "
                                   f"blocks can never reach it")
    return obs
