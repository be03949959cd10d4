"""``python -m terrain.cut RASTER --line LINE.csv --out profile.csv``: a slope
profile cut from an elevation raster (the command only: options, reading,
writing, printing; the cut, the sampling and the zones are ``terrain.raster``,
the lines in plan ``terrain.plan_line``; the profile format is
``solvers.profile``).

``python -m solvers.profile cut ...`` runs this command too, for one release,
after a warning line on stderr (``solvers.profile.main``).
"""

from __future__ import annotations

import math

import numpy as np

from solvers.profile import (
    MATERIAL_COLUMNS,
    ProfileError,
    default_materials_path,
    load_materials,
    make_profile,
)

__all__ = ["main"]

PROG = "python -m terrain.cut"

_CUT_DESCRIPTION = """\
Cut a slope profile from a digital elevation model along a line in plan.

The ground is sampled by bilinear interpolation between cell centres every
--step-m metres along the line (and at its vertices and end). Writes, atomically
(nothing is written on any error):

  OUT                   the profile: x_m,z_m,zone,east_m,north_m. x_m is the
                        horizontal distance along the line from its start, z_m
                        the ground elevation, zone the material zone of the
                        segment to the next vertex; east_m,north_m are each
                        vertex's position in the RASTER'S coordinate system
                        (load_profile ignores these two columns).
  <OUT stem>_materials.csv  the zones' materials (--materials-out to rename).
  <OUT stem>.cut.json   how the file was made: raster and its CRS (ESRI ASCII
                        grids carry none), line vertices, step, zones, materials
                        source, the command line.

The line is one of:
  --line LINE.csv       vertices in order, columns east_m,north_m or x_m,y_m or
                        x,y (in the raster's coordinates);
  --line LINE.geojson   one LineString (coordinates in the raster's system; no
                        reprojection is done);
  --fall-line RUNS.csv  the mean fall line of field runs: the straight line from
                        the mean release point to the mean stop point, extended
                        by --margin-m on both ends; with --fall-line-near E,N,R
                        only the runs released within R m of (E, N): one
                        release spot's own fall line, for a campaign whose
                        spots lie far apart (calib.field takes one --profile
                        per spot).

Materials: --materials CSV (zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg)
with a row for every zone of --zones; without it every zone gets placeholder
values, an ASSUMPTION: Kn 0.41, Kt 0.87, roughness 2 m, phi 30 deg (the
Postignano paper's one set, Sect. 4.1) and rolling friction 30 deg (as
data/README.md assumes for Postignano). Calibrate them for the cut site.
"""


def build_parser():
    """The ``python -m terrain.cut`` parser."""
    import argparse

    from solvers.cli import OneLineParser

    p = OneLineParser(
        prog=PROG, description=_CUT_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example (the shipped Tschamut profile, data/README.md):\n"
               "  python -m terrain.cut data/tschamut2014/terrain_proxy.asc \\\n"
               "    --fall-line data/tschamut2014/runs.csv --margin-m 40 \\\n"
               "    --zones steep:0:100,flat:100: --out data/tschamut2014/profile.csv")
    p.add_argument("raster", help="elevation raster: ESRI ASCII grid (.asc) or GeoTIFF "
                   "(.tif, needs the optional package rasterio)")
    line = p.add_mutually_exclusive_group(required=True)
    line.add_argument("--line", help="line vertices: CSV (east_m,north_m | x_m,y_m | x,y) or "
                      "GeoJSON LineString")
    line.add_argument("--fall-line", metavar="RUNS.csv",
                      help="field runs CSV: cut along their mean fall line")
    p.add_argument("--margin-m", type=float, default=20.0,
                   help="with --fall-line: extension beyond the mean release and the mean "
                        "stop point, m (default 20)")
    p.add_argument("--fall-line-near", metavar="E,N,R", default=None,
                   help="with --fall-line: only the runs released within R m of the point "
                        "(E, N), raster coordinates (default: all runs)")
    p.add_argument("--release-cols", default="release_x_m,release_y_m",
                   help="with --fall-line: release east,north columns "
                        "(default release_x_m,release_y_m)")
    p.add_argument("--stop-cols", default="stop_x_m,stop_y_m",
                   help="with --fall-line: stop east,north columns (default stop_x_m,stop_y_m)")
    p.add_argument("--step-m", type=float, default=1.0,
                   help="sampling step along the line, m (default 1)")
    p.add_argument("--zones", default=None,
                   help="material zones as distance ranges along the line, "
                        "'name:start_m:end_m,...' (empty end: to the end of the line), e.g. "
                        "'steep:0:60,flat:60:' (default: one zone 'ground')")
    p.add_argument("--materials", default=None,
                   help="materials CSV with a row per zone (default: the placeholder values "
                        "above, an assumption)")
    p.add_argument("--out", required=True, help="profile CSV to write")
    p.add_argument("--materials-out", default=None,
                   help="materials CSV to write (default <OUT stem>_materials.csv)")
    return p


def _columns(text: str, option: str) -> tuple[str, str]:
    from solvers.cli import CliError

    parts = [c.strip() for c in text.split(",")]
    if len(parts) != 2 or not all(parts):
        raise CliError(f"{option}: expected two column names 'east,north', got {text!r}")
    return parts[0], parts[1]


def _near(text: str | None) -> tuple[float, float, float] | None:
    import math

    from solvers.cli import CliError

    if text is None:
        return None
    try:
        e, n, r = (float(t) for t in text.split(","))
    except ValueError:
        raise CliError(f"--fall-line-near: expected E,N,R (three numbers), got {text!r}") from None
    if not (math.isfinite(e) and math.isfinite(n) and math.isfinite(r) and r > 0):
        raise CliError(f"--fall-line-near: expected finite E,N and a radius R > 0, got {text!r}")
    return e, n, r


def _line(args):
    """The line in plan the cut follows, and its record for the ``.cut.json``."""
    from solvers.cli import CliError
    from terrain import plan_line

    if args.line and args.fall_line_near:
        raise CliError("--fall-line-near: only with --fall-line")
    if args.line:
        line = plan_line.read_line(args.line)
        line_info = {"kind": "geojson" if not args.line.endswith(".csv") else "csv",
                     "source": args.line}
    else:
        release_cols = _columns(args.release_cols, "--release-cols")
        stop_cols = _columns(args.stop_cols, "--stop-cols")
        near = _near(args.fall_line_near)
        line = plan_line.read_fall_line(args.fall_line, args.margin_m, release_cols, stop_cols,
                                        near=near)
        line_info = {"kind": "mean fall line of field runs (mean release point to mean "
                             "stop point, extended by margin_m at both ends)",
                     "source": args.fall_line, "margin_m": args.margin_m,
                     "release_columns": list(release_cols), "stop_columns": list(stop_cols)}
        if near is not None:
            line_info["runs_released_near"] = {"east_m": near[0], "north_m": near[1],
                                               "radius_m": near[2]}
    return line, line_info


def _summary(args, cut, line, used, materials_out: str, sidecar: str) -> None:
    """What the cut printed: vertices, heights, each zone's extent and mean slope."""
    x, z = cut.x_m, cut.z_m
    print(f"cut {x.shape[0]} vertices every {args.step_m:g} m along {line.length_m:.2f} m of "
          f"line ({line.source}); z {z.min():.2f} to {z.max():.2f} m")
    seg_zone = np.array(cut.zone)
    for name in used:
        k = np.flatnonzero(seg_zone == name)
        x0, x1 = x[k[0]], x[k[-1] + 1]
        drop = z[k[0]] - z[k[-1] + 1]
        print(f"  zone {name}: x {x0:.2f} to {x1:.2f} m, {k.size} segments, mean slope "
              f"{math.degrees(math.atan2(drop, x1 - x0)):.1f} deg")
    print(f"wrote {args.out}, {materials_out}, {sidecar}")


def _run_cut(args, argv: list[str]) -> int:
    import json
    import shlex

    from solvers.cli import CliError, text_writer, write_all_atomic
    from terrain import raster as rs

    if not args.out.endswith(".csv"):
        raise CliError(f"--out {args.out}: expected a .csv file name")
    materials_out = args.materials_out or default_materials_path(args.out)
    sidecar = args.out[:-4] + ".cut.json"
    try:
        grid = rs.read_raster(args.raster)
        line, line_info = _line(args)
        zones = rs.parse_zones(args.zones)
        cut = rs.cut_profile(grid, line, args.step_m, zones)
        used = list(dict.fromkeys(cut.zone))
        if args.materials:
            table = load_materials(args.materials)
            missing = [z for z in used if z not in table]
            if missing:
                raise CliError(f"{args.materials}: no row for zone(s) {', '.join(missing)} "
                               f"(zones of the cut: {', '.join(used)})")
            materials = {z: table[z] for z in used}
            materials_source = args.materials
        else:
            materials = {z: dict(rs.DEFAULT_MATERIALS) for z in used}
            materials_source = ("ASSUMPTION: placeholder values of terrain.raster."
                                "DEFAULT_MATERIALS (the Postignano paper's Kn, Kt, roughness "
                                "and phi; rolling friction as data/README.md assumes for "
                                "Postignano), not measurements of this site")
        # the profile must load as the solvers will load it
        make_profile(np.round(cut.x_m, 4), np.round(cut.z_m, 4), list(cut.zone), materials,
                     source=args.out)
    except (rs.RasterError, ProfileError) as e:
        raise CliError(str(e)) from None

    mat_lines = ["zone," + ",".join(MATERIAL_COLUMNS)]
    mat_lines += [z + "," + ",".join(f"{materials[z][c]:g}" for c in MATERIAL_COLUMNS)
                  for z in used]
    info = {
        "what": "slope profile cut from a raster by python -m terrain.cut",
        "command": shlex.join(PROG.split() + argv),
        "argv": argv,
        "raster": args.raster,
        "raster_crs": grid.crs or "none given in the file: east_m,north_m are in the "
                                  "raster's own (local) coordinates",
        "raster_cell_m": grid.cell_m,
        "line": {**line_info, "east_m": [round(float(v), 4) for v in line.east_m],
                 "north_m": [round(float(v), 4) for v in line.north_m],
                 "length_m": round(line.length_m, 4)},
        "step_m": args.step_m,
        "sampling": "bilinear between cell centres (terrain.raster)",
        "zones": [{"name": z.name, "start_m": z.start_m, "end_m": z.end_m} for z in zones],
        "materials": materials_source,
        "columns": {
            "x_m": "horizontal distance along the line from its start, m",
            "z_m": "ground elevation, m (raster units)",
            "zone": "material zone of the segment to the next vertex",
            "east_m": "vertex east coordinate in the raster's coordinate system, m",
            "north_m": "vertex north coordinate in the raster's coordinate system, m"},
        "n_vertices": int(cut.x_m.shape[0]),
    }
    try:
        write_all_atomic({
            args.out: text_writer(rs.profile_csv_text(cut)),
            materials_out: text_writer("\n".join(mat_lines) + "\n"),
            sidecar: text_writer(json.dumps(info, indent=1) + "\n"),
        })
    except OSError as e:
        raise CliError(f"cannot write {args.out}: {e.strerror or e}; nothing written") from None
    _summary(args, cut, line, used, materials_out, sidecar)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m terrain.cut ...``; bad input: one line on stderr, exit 2."""
    import sys

    from solvers.cli import run_guarded

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    return run_guarded(PROG, _run_cut, args, argv)


if __name__ == "__main__":
    import sys

    sys.exit(main())
