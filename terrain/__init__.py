"""Terrain: elevation rasters, lines in plan, and slope profiles cut from them.

* ``terrain.raster``: terrain rasters (ESRI ASCII grid; GeoTIFF with the
  optional ``rasterio``), bilinear sampling, the profile cut along a line.
* ``terrain.plan_line``: lines in plan (CSV, GeoJSON, the mean fall line of
  field runs) and the plan trace of a cut profile.
* ``terrain.cut``: the command ``python -m terrain.cut RASTER --line LINE.csv
  --out profile.csv`` (not imported here, so that ``python -m`` does not find
  it already imported by the package).

The profile written is the one the solvers run on (``solvers.profile``).
Terrain depends on ``solvers`` (the profile format, the CSV reader, the
command-line kit) and never on ``calib``; ``solvers`` never imports terrain.
"""

from terrain.plan_line import (
    Polyline,
    mean_fall_line,
    read_fall_line,
    read_line,
    read_profile_trace,
)
from terrain.raster import (
    DEFAULT_MATERIALS,
    ProfileCut,
    Raster,
    RasterError,
    ZoneRange,
    cut_profile,
    parse_zones,
    read_ascii_grid,
    read_geotiff,
    read_raster,
)

__all__ = [
    "DEFAULT_MATERIALS",
    "Polyline",
    "ProfileCut",
    "Raster",
    "RasterError",
    "ZoneRange",
    "cut_profile",
    "mean_fall_line",
    "parse_zones",
    "read_ascii_grid",
    "read_fall_line",
    "read_geotiff",
    "read_line",
    "read_profile_trace",
    "read_raster",
]
