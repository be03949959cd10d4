"""Lines in plan: where a profile is cut, and where a cut profile lies.

A ``Polyline`` is a line in a raster's horizontal coordinates (east, north,
in the raster's coordinate reference system). It comes from a CSV of vertices
or a GeoJSON LineString (``read_line``), from the mean fall line of field runs
(``mean_fall_line``, ``read_fall_line``: the straight line from the mean
release to the mean stop point, extended at both ends), or from the
``east_m,north_m`` columns of a profile that ``terrain.raster.cut_profile``
wrote (``read_profile_trace``). Distances along a line are horizontal,
measured along the polyline in plan.

Every problem is a ``terrain.raster.RasterError`` (the error of the cut that
uses these lines) whose message names the file and what is wrong.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Sequence

import numpy as np

from solvers.csv_rows import cell_float, read_csv_rows
from terrain.raster import RasterError

__all__ = ["Polyline", "mean_fall_line", "read_fall_line", "read_line", "read_profile_trace"]

@dataclasses.dataclass(frozen=True)
class Polyline:
    """A line in plan: vertices in a raster's horizontal coordinates.

    Attributes:
        east_m, north_m: (V,) vertex coordinates, m, V >= 2, finite, no two
            consecutive vertices equal.
        source: where the line came from (for messages).
    """

    east_m: np.ndarray
    north_m: np.ndarray
    source: str = "<line>"

    def __post_init__(self):
        e = np.asarray(self.east_m, float)
        n = np.asarray(self.north_m, float)
        if e.ndim != 1 or e.shape != n.shape or e.shape[0] < 2:
            raise RasterError(f"{self.source}: a line needs at least 2 vertices, got "
                              f"{e.size if e.ndim == 1 else e.shape}")
        bad = np.flatnonzero(~(np.isfinite(e) & np.isfinite(n)))
        if bad.size:
            raise RasterError(f"{self.source}: vertex {bad[0] + 1}: expected finite coordinates, "
                              f"got ({e[bad[0]]}, {n[bad[0]]})")
        seg = np.hypot(np.diff(e), np.diff(n))
        bad = np.flatnonzero(seg <= 0)
        if bad.size:
            raise RasterError(f"{self.source}: vertices {bad[0] + 1} and {bad[0] + 2} coincide")
        object.__setattr__(self, "east_m", e)
        object.__setattr__(self, "north_m", n)

    @property
    def vertex_distance_m(self) -> np.ndarray:
        """(V,) horizontal distance of each vertex along the line from its start, m."""
        return np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(self.east_m),
                                                          np.diff(self.north_m)))])

    @property
    def length_m(self) -> float:
        return float(self.vertex_distance_m[-1])

    def at(self, distance_m) -> tuple[np.ndarray, np.ndarray]:
        """Plan position at horizontal distances along the line.

        Args:
            distance_m: any shape, m, in [0, length_m].

        Returns:
            (east_m, north_m), each of the shape of ``distance_m``.
        """
        s = np.asarray(distance_m, float)
        cum = self.vertex_distance_m
        return np.interp(s, cum, self.east_m), np.interp(s, cum, self.north_m)

    def project(self, east_m, north_m) -> tuple[np.ndarray, np.ndarray]:
        """Orthogonal projection of points onto the line.

        Each point goes to the nearest point of the polyline, whose first and last
        segments are extended beyond the ends (so a point past an end gets a
        distance below 0 or above ``length_m`` rather than being pinned there).

        Args:
            east_m, north_m: (P,) point coordinates, m.

        Returns:
            (distance_m, offset_m), each (P,): horizontal distance of the foot
            along the line from its start, m; signed perpendicular distance of
            the point from the line, m, positive to the LEFT of the direction of
            travel (counter-clockwise).
        """
        pe = np.atleast_1d(np.asarray(east_m, float))[:, None]
        pn = np.atleast_1d(np.asarray(north_m, float))[:, None]
        ae, an = self.east_m[:-1][None], self.north_m[:-1][None]
        de, dn = np.diff(self.east_m)[None], np.diff(self.north_m)[None]
        seg_len = np.hypot(de, dn)
        t = ((pe - ae) * de + (pn - an) * dn) / seg_len**2
        lo = np.zeros_like(seg_len)
        hi = np.ones_like(seg_len)
        lo[0, 0], hi[0, -1] = -np.inf, np.inf
        t = np.clip(t, lo, hi)
        dist = np.hypot(pe - (ae + t * de), pn - (an + t * dn))
        k = np.argmin(dist, axis=1)
        rows = np.arange(pe.shape[0])
        tk, lk = t[rows, k], seg_len[0, k]
        along = self.vertex_distance_m[k] + tk * lk
        cross = (de[0, k] * (pn[:, 0] - an[0, k]) - dn[0, k] * (pe[:, 0] - ae[0, k])) / lk
        return along, cross


def _read_csv_rows(path: str, what: str) -> tuple[list[str], list[tuple[int, dict]]]:
    return read_csv_rows(path, what, RasterError)


def _cell_float(path: str, line: int, row: dict, col: str) -> float:
    return cell_float(path, line, row, col, RasterError)


_LINE_COLUMNS = (("east_m", "north_m"), ("x_m", "y_m"), ("x", "y"))


def read_line(path: str | os.PathLike) -> Polyline:
    """A polyline from a CSV of vertices or a GeoJSON LineString.

    CSV: a header naming the coordinate columns, one of ``east_m,north_m``,
    ``x_m,y_m`` or ``x,y`` (other columns are ignored), then one vertex per row
    in order along the line. GeoJSON (``.geojson``, ``.json``): a LineString
    geometry, or a Feature or a FeatureCollection holding exactly one
    LineString; a third coordinate is ignored. In both cases the coordinates
    must be in the raster's coordinate system (no reprojection is done, even
    though RFC 7946 GeoJSON is nominally WGS 84 longitude/latitude).

    Raises:
        RasterError: naming the file, and the line and column for CSV values.
    """
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext in (".geojson", ".json"):
        return _read_geojson_line(path)
    header, rows = _read_csv_rows(path, "east_m,north_m or x_m,y_m or x,y")
    cols = next((c for c in _LINE_COLUMNS if set(c) <= set(header)), None)
    if cols is None:
        raise RasterError(f"{path}: line 1: expected coordinate columns east_m,north_m or "
                          f"x_m,y_m or x,y; found {', '.join(header)}")
    e = [_cell_float(path, line, row, cols[0]) for line, row in rows]
    n = [_cell_float(path, line, row, cols[1]) for line, row in rows]
    return Polyline(np.array(e), np.array(n), path)


def _read_geojson_line(path: str) -> Polyline:
    if not os.path.isfile(path):
        raise RasterError(f"{path}: file not found")
    try:
        with open(path, encoding="utf-8") as fh:
            obj = json.load(fh)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise RasterError(f"{path}: not valid JSON ({e})") from None
    geoms = []

    def collect(o):
        if not isinstance(o, dict):
            return
        kind = o.get("type")
        if kind == "FeatureCollection":
            for f in o.get("features") or []:
                collect(f)
        elif kind == "Feature":
            collect(o.get("geometry"))
        elif kind == "LineString":
            geoms.append(o)

    collect(obj)
    if len(geoms) != 1:
        raise RasterError(f"{path}: expected exactly one GeoJSON LineString, found {len(geoms)}")
    coords = geoms[0].get("coordinates")
    if not isinstance(coords, list):
        raise RasterError(f"{path}: LineString 'coordinates' must be a list of positions")
    e, n = [], []
    for k, pos in enumerate(coords, start=1):
        ok = (isinstance(pos, list) and len(pos) >= 2
              and all(isinstance(v, int | float) and not isinstance(v, bool) for v in pos[:2]))
        if not ok:
            raise RasterError(f"{path}: LineString position {k}: expected [x, y], got {pos!r}")
        e.append(float(pos[0]))
        n.append(float(pos[1]))
    return Polyline(np.array(e), np.array(n), path)


def mean_fall_line(release_east_m, release_north_m, stop_east_m, stop_north_m,
                   margin_m: float, source: str = "<runs>") -> Polyline:
    """The mean fall line of field runs: a straight line from the mean release
    point to the mean stop point, extended by ``margin_m`` beyond both.

    With P0 the mean release point, P1 the mean stop point and u = (P1 - P0) /
    |P1 - P0|, the line runs from P0 - margin u to P1 + margin u. (Our own
    definition of "the" fall line of a set of runs; it is the direction in
    which the runs moved on average.)

    Args:
        release_east_m, release_north_m, stop_east_m, stop_north_m: (R,) m.
        margin_m: extension at each end, m (>= 0).
        source: name used in messages.

    Returns:
        A two-vertex ``Polyline``.
    """
    if not (math.isfinite(margin_m) and margin_m >= 0):
        raise RasterError(f"{source}: the margin must be a number of metres >= 0, got {margin_m}")
    p0 = np.array([np.mean(release_east_m), np.mean(release_north_m)])
    p1 = np.array([np.mean(stop_east_m), np.mean(stop_north_m)])
    span = float(np.hypot(*(p1 - p0)))
    if not span > 0:
        raise RasterError(f"{source}: the mean release and mean stop points coincide; "
                          "no fall direction")
    u = (p1 - p0) / span
    a, b = p0 - margin_m * u, p1 + margin_m * u
    return Polyline(np.array([a[0], b[0]]), np.array([a[1], b[1]]), source)


def read_fall_line(path: str | os.PathLike, margin_m: float,
                   release_columns: Sequence[str] = ("release_x_m", "release_y_m"),
                   stop_columns: Sequence[str] = ("stop_x_m", "stop_y_m"),
                   near: tuple[float, float, float] | None = None) -> Polyline:
    """``mean_fall_line`` of the runs in a CSV (one run per row).

    Args:
        near: (east_m, north_m, radius_m): only the runs released within
            radius_m of that point (one release spot of a campaign); None: all.

    Raises:
        RasterError: missing file or column, a value that is not a finite
            number (naming the line and column), no rows, no run near the point.
    """
    path = os.fspath(path)
    cols = tuple(release_columns) + tuple(stop_columns)
    header, rows = _read_csv_rows(path, ",".join(cols))
    missing = [c for c in cols if c not in header]
    if missing:
        raise RasterError(f"{path}: line 1: missing column(s) {', '.join(missing)}; found "
                          f"{', '.join(header)}")
    if not rows:
        raise RasterError(f"{path}: no runs after the header")
    vals = np.array([[_cell_float(path, line, row, c) for c in cols] for line, row in rows])
    if near is not None:
        e, n, r = near
        keep = np.hypot(vals[:, 0] - e, vals[:, 1] - n) <= r
        if not keep.any():
            raise RasterError(f"{path}: no run is released within {r:g} m of "
                              f"({e:g}, {n:g}); nearest at "
                              f"{np.hypot(vals[:, 0] - e, vals[:, 1] - n).min():.1f} m")
        vals = vals[keep]
    return mean_fall_line(vals[:, 0], vals[:, 1], vals[:, 2], vals[:, 3], margin_m, path)


def read_profile_trace(path: str | os.PathLike) -> tuple[np.ndarray, Polyline]:
    """The plan trace of a profile CSV that has ``east_m,north_m`` columns.

    Args:
        path: profile CSV written by ``python -m terrain.cut`` (or any
            profile with those columns).

    Returns:
        (x_m, line): (V,) profile abscissae, m, and the polyline of the vertices'
        plan positions. x_m must be the horizontal distance along that polyline
        up to a constant (checked to 1 mm per segment, which the files' 0.1 mm
        rounding satisfies).

    Raises:
        RasterError: missing columns or bad values (naming line and column), or
            x_m that is not the distance along the plan trace.
    """
    path = os.fspath(path)
    header, rows = _read_csv_rows(path, "x_m,z_m,zone,east_m,north_m")
    missing = [c for c in ("x_m", "east_m", "north_m") if c not in header]
    if missing:
        raise RasterError(f"{path}: line 1: missing column(s) {', '.join(missing)}: the profile "
                          "has no plan trace (cut it with python -m terrain.cut)")
    vals = np.array([[_cell_float(path, line, row, c) for c in ("x_m", "east_m", "north_m")]
                     for line, row in rows])
    if vals.shape[0] < 2:
        raise RasterError(f"{path}: a profile needs at least 2 vertices, got {vals.shape[0]}")
    x = vals[:, 0]
    line = Polyline(vals[:, 1], vals[:, 2], path)
    gap = np.abs(np.diff(x) - np.diff(line.vertex_distance_m))
    if gap.max() > 1e-3:
        k = int(np.argmax(gap))
        raise RasterError(f"{path}: line {rows[k + 1][0]}: column 'x_m': the step in x_m "
                          f"({x[k + 1] - x[k]:.4f} m) is not the plan distance between the "
                          f"vertices ({np.diff(line.vertex_distance_m)[k]:.4f} m)")
    return x, line
