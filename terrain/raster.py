"""Ground elevations from a raster, and a slope profile cut along a line in plan.

A digital elevation model (DEM raster) is read into a ``Raster``; a ``Polyline``
in the raster's horizontal coordinates (``terrain.plan_line``) says where to cut;
``cut_profile`` samples the ground along it and returns the vertices of a profile
in the format of ``solvers.profile`` (``x_m,z_m,zone``) plus the plan position
of each vertex (``east_m,north_m``, in the raster's coordinate reference system).

Rasters:

* ESRI ASCII grid (``.asc``), read natively. Header (keys in any case, one per
  line, in this order or any other)::

      ncols N / nrows M / xllcorner X | xllcenter X / yllcorner Y | yllcenter Y /
      cellsize C / [NODATA_value V]

  then M rows of N numbers, the first row the northernmost, one grid row per
  line. ``xllcorner`` is the west edge of the lower-left cell, ``xllcenter`` its
  centre (ESRI's "Esri ASCII raster format" page).
* GeoTIFF (``.tif``, ``.tiff``) through the optional package ``rasterio``
  (north-up, square cells, band 1). Without rasterio the reader refuses with a
  message saying so.

Sampling: a cell's value is the elevation at the cell's CENTRE, and between
centres the ground is the bilinear interpolant of the four surrounding centres,

    z(u, v) = (1-fu)(1-fv) z[j, i] + fu (1-fv) z[j, i+1] + (1-fu) fv z[j+1, i] + fu fv z[j+1, i+1],

with u = (east - east0) / c, v = (north - north0) / c, i = floor(u), fu = u - i
(likewise j, fv), east0/north0 the centre of the south-west cell and c the cell
size. This is the usual bilinear resampling of GIS tools (e.g. GDAL's
``bilinear``) and it reproduces any plane a + b east + c north exactly. The
data area is the rectangle spanned by the cell centres (half a cell inside the
raster's outer edge): there is no extrapolation. A sample is NODATA when any
cell with a non-zero weight is NODATA.

Cutting (our own choices, documented here): the ground is sampled at distances
0, step, 2 step, ... along the line (horizontal distance, measured along the
polyline in plan), at every vertex of the polyline, and at its end; a regular
station closer than step / 10 to a vertex or to the end is dropped so that no
segment is degenerate. ``x_m`` of the profile is that horizontal distance from
the line's start (a polyline that bends in plan is unrolled). Zones are given as
distance ranges along the line; a segment takes the zone whose range holds its
mid-point.

Every problem is a ``RasterError`` whose message names the file and what is
wrong (a header key, a line and column, or a distance along the line).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the line's module imports this one (RasterError)
    from terrain.plan_line import Polyline

__all__ = [
    "DEFAULT_MATERIALS",
    "ProfileCut",
    "Raster",
    "RasterError",
    "ZoneRange",
    "cut_profile",
    "parse_zones",
    "read_ascii_grid",
    "read_geotiff",
    "read_raster",
]

# Placeholder materials of a cut profile when no --materials file is given:
# the Postignano paper's one set (Sect. 4.1: Kn 0.41, Kt 0.87, roughness 2 m
# "typical for talus and firm soil slopes (Jones et al., 2000)", DEM phi 30 deg)
# and the rolling angle data/README.md assumes for Postignano (30 deg). They are
# NOT measurements of the cut site: an ASSUMPTION, to be calibrated.
DEFAULT_MATERIALS = {"Kn": 0.41, "Kt": 0.87, "roughness_m": 2.0,
                     "rolling_friction_deg": 30.0, "phi_deg": 30.0}

_HEADER_KEYS = ("ncols", "nrows", "xllcorner", "xllcenter", "yllcorner", "yllcenter",
                "cellsize", "nodata_value")


class RasterError(ValueError):
    """A raster, line or cut that cannot be used; the message names the file and
    what is wrong (header key, line and column, or distance along the line)."""


@dataclasses.dataclass(frozen=True)
class Raster:
    """A north-up elevation grid with square cells.

    Attributes:
        z_m: (nrows, ncols) elevations at the cell centres, m; row 0 is the
            SOUTHERNMOST row (the file's last), NaN where the file has NODATA.
        east0_m: east coordinate of the centre of column 0 (westernmost), m.
        north0_m: north coordinate of the centre of row 0 (southernmost), m.
        cell_m: cell size c, m (> 0).
        path: file the grid came from (for messages).
        crs: coordinate reference system as text, "" when the file has none
            (ESRI ASCII grids carry none; a ``.prj`` beside them is not read).
    """

    z_m: np.ndarray
    east0_m: float
    north0_m: float
    cell_m: float
    path: str = "<memory>"
    crs: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.z_m.shape[0]), int(self.z_m.shape[1])

    @property
    def east_range_m(self) -> tuple[float, float]:
        """West and east ends of the data area (first and last cell centres), m."""
        return self.east0_m, self.east0_m + (self.z_m.shape[1] - 1) * self.cell_m

    @property
    def north_range_m(self) -> tuple[float, float]:
        """South and north ends of the data area (first and last cell centres), m."""
        return self.north0_m, self.north0_m + (self.z_m.shape[0] - 1) * self.cell_m

    def contains(self, east_m, north_m) -> np.ndarray:
        """True where a point lies in the data area (between the outer cell centres).

        Args:
            east_m, north_m: arrays of one shape, m.

        Returns:
            bool array of that shape.
        """
        e, n = np.asarray(east_m, float), np.asarray(north_m, float)
        (w, ea), (s, no) = self.east_range_m, self.north_range_m
        tol = 1e-9 * max(1.0, self.cell_m)
        return (e >= w - tol) & (e <= ea + tol) & (n >= s - tol) & (n <= no + tol)

    def sample(self, east_m, north_m) -> np.ndarray:
        """Bilinear elevation at points in the data area (module docstring).

        Args:
            east_m, north_m: arrays of one shape, m.

        Returns:
            Elevations in m, same shape; NaN where a cell with non-zero weight is
            NODATA.

        Raises:
            RasterError: if any point lies outside the data area.
        """
        e, n = np.broadcast_arrays(np.asarray(east_m, float), np.asarray(north_m, float))
        inside = self.contains(e, n)
        if not inside.all():
            k = int(np.flatnonzero(~inside.ravel())[0])
            raise RasterError(f"{self.path}: point (east {e.ravel()[k]:g}, north "
                              f"{n.ravel()[k]:g}) lies outside the data area "
                              f"{_area_text(self)}")
        nrows, ncols = self.shape
        u = np.clip((e - self.east0_m) / self.cell_m, 0.0, ncols - 1)
        v = np.clip((n - self.north0_m) / self.cell_m, 0.0, nrows - 1)
        i = np.minimum(np.floor(u).astype(int), ncols - 2)
        j = np.minimum(np.floor(v).astype(int), nrows - 2)
        fu, fv = u - i, v - j
        corners = ((j, i, (1 - fu) * (1 - fv)), (j, i + 1, fu * (1 - fv)),
                   (j + 1, i, (1 - fu) * fv), (j + 1, i + 1, fu * fv))
        z = np.zeros(e.shape)
        nodata = np.zeros(e.shape, bool)
        for jj, ii, w in corners:
            zc = self.z_m[jj, ii]
            used = w > 0
            nodata |= used & np.isnan(zc)
            z += np.where(used & ~np.isnan(zc), w * np.nan_to_num(zc), 0.0)
        return np.where(nodata, np.nan, z)


def _area_text(r: Raster) -> str:
    (w, e), (s, n) = r.east_range_m, r.north_range_m
    return f"(cell centres span east {w:g} to {e:g} m, north {s:g} to {n:g} m)"


def read_ascii_grid(path: str | os.PathLike) -> Raster:
    """Read an ESRI ASCII grid (format in the module docstring).

    Args:
        path: the ``.asc`` file.

    Returns:
        A ``Raster`` (row 0 southernmost, NaN at NODATA).

    Raises:
        RasterError: missing, unknown, duplicate or bad header keys; fewer than
            2 rows or columns; a grid row with the wrong number of values; a
            value that is not a finite number; too few or too many rows. The
            message names the file, the line and (for values) the column.
    """
    path = os.fspath(path)
    expected = ("an ESRI ASCII grid starts with ncols, nrows, xllcorner|xllcenter, "
                "yllcorner|yllcenter, cellsize and optionally NODATA_value")
    lines = _text_lines(path, expected)
    header: dict[str, float] = {}
    rows: list[np.ndarray] = []
    nrows = ncols = None
    for lineno, text in enumerate(lines, start=1):
        tokens = text.split()
        if not tokens:
            continue
        if nrows is None and tokens[0][0].isalpha():
            _header_entry(path, lineno, tokens, header, expected)
            continue
        if nrows is None:
            ncols, nrows, east0, north0, cell, nodata = _check_header(path, header, expected)
        if len(rows) == nrows:
            raise RasterError(f"{path}: line {lineno}: more grid rows than nrows = {nrows}")
        rows.append(_grid_row(path, lineno, tokens, len(rows) + 1, ncols, nodata))
    if nrows is None:
        if not header:
            raise RasterError(f"{path}: empty file; {expected}")
        ncols, nrows, *_ = _check_header(path, header, expected)
    if len(rows) != nrows:
        raise RasterError(f"{path}: expected nrows = {nrows} grid rows, got {len(rows)}")
    z = np.array(rows[::-1])  # file rows run north to south; row 0 here is southernmost
    return Raster(z, east0, north0, cell, path, "")


def _text_lines(path: str, expected: str) -> list[str]:
    """The file's lines; a missing file or one that is not UTF-8 text fails in
    one line."""
    if not os.path.isfile(path):
        raise RasterError(f"{path}: file not found")
    try:
        fh = open(path, encoding="utf-8")
        lines = fh.read().splitlines()
        fh.close()
    except UnicodeDecodeError:
        raise RasterError(f"{path}: not a text file ({expected})") from None
    return lines


def _header_entry(path: str, lineno: int, tokens: list[str], header: dict[str, float],
                  expected: str) -> None:
    """Add one header line (a known key, given once, with one finite number) to
    ``header``; anything else fails naming the line and the key."""
    key = tokens[0].lower()
    if key not in _HEADER_KEYS:
        raise RasterError(f"{path}: line {lineno}: unknown header key {tokens[0]!r}; "
                          f"{expected}")
    if key in header:
        raise RasterError(f"{path}: line {lineno}: header key {tokens[0]!r} given twice")
    if len(tokens) != 2:
        raise RasterError(f"{path}: line {lineno}: header key {tokens[0]!r}: expected "
                          f"one value, got {len(tokens) - 1}")
    try:
        header[key] = float(tokens[1])
    except ValueError:
        raise RasterError(f"{path}: line {lineno}: header key {tokens[0]!r}: expected "
                          f"a number, got {tokens[1]!r}") from None
    if not math.isfinite(header[key]):
        raise RasterError(f"{path}: line {lineno}: header key {tokens[0]!r}: expected "
                          f"a finite number, got {tokens[1]!r}")


def _grid_row(path: str, lineno: int, tokens: list[str], row: int, ncols: int,
              nodata: float | None) -> np.ndarray:
    """Grid row number ``row`` (1-based, from the north): ``ncols`` finite
    numbers, NaN where they equal ``nodata``; a wrong count or a bad value fails
    naming the line (and the column)."""
    if len(tokens) != ncols:
        raise RasterError(f"{path}: line {lineno}: grid row {row}: expected "
                          f"ncols = {ncols} values, got {len(tokens)}")
    try:
        vals = np.array(tokens, dtype=float)
    except ValueError:
        vals = None
    if vals is None or not np.isfinite(vals).all():
        for col, tok in enumerate(tokens, start=1):
            try:
                ok = math.isfinite(float(tok))
            except ValueError:
                ok = False
            if not ok:
                raise RasterError(f"{path}: line {lineno}: column {col}: expected a "
                                  f"finite number, got {tok!r}")
    if nodata is not None:
        vals = np.where(vals == nodata, np.nan, vals)
    return vals


def _check_header(path: str, header: dict[str, float], expected: str):
    """Validated (ncols, nrows, east0, north0, cell, nodata) from header values."""
    for key in ("ncols", "nrows", "cellsize"):
        if key not in header:
            raise RasterError(f"{path}: header: missing {key!r}; {expected}")
    for axis in ("x", "y"):
        corner, centre = f"{axis}llcorner", f"{axis}llcenter"
        if (corner in header) == (centre in header):
            raise RasterError(f"{path}: header: expected exactly one of {corner!r} and "
                              f"{centre!r}; {expected}")
    ncols, nrows, cell = header["ncols"], header["nrows"], header["cellsize"]
    for key, val in (("ncols", ncols), ("nrows", nrows)):
        if val != int(val) or val < 2:
            raise RasterError(f"{path}: header: {key!r}: expected a whole number >= 2 (bilinear "
                              f"sampling needs two cell centres per axis), got {val:g}")
    if cell <= 0:
        raise RasterError(f"{path}: header: 'cellsize': expected a positive size, got {cell:g}")
    half = 0.5 * cell
    east0 = header["xllcenter"] if "xllcenter" in header else header["xllcorner"] + half
    north0 = header["yllcenter"] if "yllcenter" in header else header["yllcorner"] + half
    return int(ncols), int(nrows), east0, north0, cell, header.get("nodata_value")


def read_geotiff(path: str | os.PathLike) -> Raster:
    """Read band 1 of a north-up GeoTIFF with square cells through ``rasterio``.

    ``rasterio`` is optional and not a dependency of this project: without it
    this refuses with a message saying how to proceed.

    Raises:
        RasterError: rasterio missing, unreadable file, rotated or non-square
            cells, fewer than 2 rows or columns.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise RasterError(f"{path}: file not found")
    try:
        import rasterio
    except ImportError:
        raise RasterError(f"{path}: reading a GeoTIFF needs the optional package rasterio, "
                          "which is not installed (pip install rasterio), or convert it to an "
                          "ESRI ASCII grid first (gdal_translate -of AAIGrid in.tif out.asc)"
                          ) from None
    try:
        with rasterio.open(path) as src:
            band = src.read(1, masked=True)
            t = src.transform
            crs = src.crs.to_string() if src.crs else ""
    except Exception as e:  # rasterio raises its own error classes
        raise RasterError(f"{path}: cannot read as a GeoTIFF ({e})") from None
    if t.b != 0 or t.d != 0 or t.e >= 0 or t.a <= 0 or not math.isclose(t.a, -t.e):
        raise RasterError(f"{path}: only north-up rasters with square cells are supported "
                          f"(affine transform {tuple(t)[:6]})")
    nrows, ncols = band.shape
    if nrows < 2 or ncols < 2:
        raise RasterError(f"{path}: expected at least 2 rows and 2 columns, got {nrows} x {ncols}")
    z = np.ma.filled(band.astype(float), np.nan)[::-1]
    cell = float(t.a)
    return Raster(np.ascontiguousarray(z), float(t.c) + 0.5 * cell,
                  float(t.f) - (nrows - 0.5) * cell, cell, path, crs)


def read_raster(path: str | os.PathLike) -> Raster:
    """``read_ascii_grid`` for ``.asc``/``.txt``, ``read_geotiff`` for ``.tif``/``.tiff``."""
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext in (".asc", ".txt"):
        return read_ascii_grid(path)
    if ext in (".tif", ".tiff"):
        return read_geotiff(path)
    raise RasterError(f"{path}: unknown raster type {ext or '(no extension)'!r}; expected an "
                      "ESRI ASCII grid (.asc) or a GeoTIFF (.tif, needs rasterio)")




@dataclasses.dataclass(frozen=True)
class ZoneRange:
    """A material zone from ``start_m`` (inclusive) to ``end_m`` (exclusive; None:
    the end of the line), horizontal distance along the line, m."""

    name: str
    start_m: float
    end_m: float | None


def parse_zones(text: str | None, default_name: str = "ground") -> list[ZoneRange]:
    """``"steep:0:60,flat:60:"`` -> zone ranges (empty end: to the end of the line).

    ``None`` or an empty text gives one zone ``default_name`` over the whole line.

    Raises:
        RasterError: malformed item, non-number, end <= start, ranges that are
            not in increasing order or that overlap.
    """
    if not text:
        return [ZoneRange(default_name, 0.0, None)]
    out: list[ZoneRange] = []
    for item in text.split(","):
        parts = item.strip().split(":")
        if len(parts) != 3 or not parts[0]:
            raise RasterError(f"--zones: expected name:start_m:end_m (end may be empty), "
                              f"got {item.strip()!r}")
        name, a, b = (p.strip() for p in parts)
        try:
            start = float(a)
            end = float(b) if b else None
        except ValueError:
            raise RasterError(f"--zones: {item.strip()!r}: expected numbers of metres") from None
        if not math.isfinite(start) or (end is not None and not math.isfinite(end)):
            raise RasterError(f"--zones: {item.strip()!r}: expected finite numbers")
        if end is not None and end <= start:
            raise RasterError(f"--zones: {item.strip()!r}: end must exceed start")
        if out and (out[-1].end_m is None or start < out[-1].end_m):
            raise RasterError(f"--zones: {item.strip()!r} overlaps or precedes the zone before "
                              "it; give the ranges in order along the line")
        out.append(ZoneRange(name, start, end))
    return out


@dataclasses.dataclass(frozen=True)
class ProfileCut:
    """A profile cut from a raster along a line.

    Attributes:
        x_m: (V,) horizontal distance of each vertex along the line from its start, m.
        z_m: (V,) ground elevation there (bilinear), m.
        east_m, north_m: (V,) plan position of each vertex, in the raster's CRS, m.
        zone: V-1 zone names, one per segment.
    """

    x_m: np.ndarray
    z_m: np.ndarray
    east_m: np.ndarray
    north_m: np.ndarray
    zone: tuple[str, ...]


def cut_profile(raster: Raster, line: Polyline, step_m: float = 1.0,
                zones: Sequence[ZoneRange] | None = None) -> ProfileCut:
    """Sample the ground along a line (stations as in the module docstring).

    Args:
        raster: the elevation grid.
        line: the line, in the raster's coordinates.
        step_m: spacing of the regular stations, m (> 0).
        zones: zone ranges along the line (``parse_zones``); default one zone
            ``ground``.

    Returns:
        A ``ProfileCut``.

    Raises:
        RasterError: a non-positive step; a line shorter than one step (fewer
            than two samples one step apart); a line that leaves the raster's
            data area (naming the first distance outside); NODATA under the line
            (naming the first distance); a segment that no zone range covers.
    """
    if not (math.isfinite(step_m) and step_m > 0):
        raise RasterError(f"--step-m: expected a positive number of metres, got {step_m}")
    length = line.length_m
    if length < step_m:
        raise RasterError(f"{line.source}: the line is {length:.3g} m long, shorter than one "
                          f"step ({step_m:g} m): a profile needs at least two samples")
    s = _stations(line.vertex_distance_m, step_m)
    e, n = line.at(s)
    outside = ~raster.contains(e, n)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        raise RasterError(f"{raster.path}: the line ({line.source}) leaves the raster's data "
                          f"area at {s[k]:.2f} m along it (east {e[k]:.2f}, north {n[k]:.2f} m) "
                          f"{_area_text(raster)}")
    z = raster.sample(e, n)
    bad = np.flatnonzero(np.isnan(z))
    if bad.size:
        k = int(bad[0])
        raise RasterError(f"{raster.path}: NODATA under the line ({line.source}) at "
                          f"{s[k]:.2f} m along it (east {e[k]:.2f}, north {n[k]:.2f} m)")
    zones = list(zones) if zones else parse_zones(None)
    mid = 0.5 * (s[1:] + s[:-1])
    names = []
    for m in mid:
        hit = [zr.name for zr in zones
               if zr.start_m <= m and (zr.end_m is None or m < zr.end_m)]
        if not hit:
            raise RasterError(f"--zones: no zone covers the segment at {m:.2f} m along the line "
                              f"(line length {length:.2f} m)")
        names.append(hit[0])
    return ProfileCut(s, z, e, n, tuple(names))


def _stations(vertex_distance_m: np.ndarray, step_m: float) -> np.ndarray:
    """Regular stations every ``step_m``, the line's vertices and its end; regular
    stations closer than step / 10 to a vertex or the end are dropped."""
    length = float(vertex_distance_m[-1])
    regular = np.arange(0.0, length, step_m)
    keep = np.min(np.abs(regular[:, None] - vertex_distance_m[None, :]), axis=1) >= 0.1 * step_m
    return np.unique(np.concatenate([regular[keep], vertex_distance_m]))


def profile_csv_text(cut: ProfileCut) -> str:
    """The cut as profile CSV text: ``x_m,z_m,zone,east_m,north_m``, 0.1 mm resolution.

    ``load_profile`` reads ``x_m,z_m,zone`` and ignores the plan columns; the last
    row's zone is empty (it names no segment).
    """
    out = ["x_m,z_m,zone,east_m,north_m"]
    zones = list(cut.zone) + [""]
    for x, z, zn, e, n in zip(cut.x_m, cut.z_m, zones, cut.east_m, cut.north_m):
        out.append(f"{x:.4f},{z:.4f},{zn},{e:.4f},{n:.4f}")
    return "\n".join(out) + "\n"
