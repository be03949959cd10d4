"""``python -m calib.field RUNS.csv --profile P.csv --out observations.csv``: field
runs (release and stop points) as observed runouts on a profile.

The command only: options, reading, writing and printing. The definitions
(projection, equivalent diameter, shape class), their sources and the
defaults that are assumptions are in ``calib.files.field_runs``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

import numpy as np

from calib.files.field_runs import (
    DEFAULT_DENSITY_KG_M3,
    DEFAULT_MAX_OFFSET_M,
    DEFAULT_RUNOUT_SD_M,
    FieldError,
    RunColumns,
    load_runs,
    nearest_profiles,
    observations_csv_text,
    observations_on_profiles,
)
from solvers.cli import CliError, OneLineParser, run_guarded, text_writer, write_all_atomic

__all__ = ["main"]

PROG = "python -m calib.field"


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=PROG, description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(
            "Writes OUT (observations, schema of calib/files/observations.py): block_size_m, "
            "runout_m, runout_sd_m,\nrunout_min_m, runout_max_m (empty), source, run_id, "
            "block_id, release_x_m (release abscissa\non the profile), release_speed_m_s, "
            "shape (sphere|cylinder|disc from the dimensions), mass_kg,\nrelease_offset_m, "
            "stop_offset_m (signed distance from the line, + to the left looking "
            "downslope),\nbeyond_max_offset, release_height_m (height of the block's lowest "
            "point above the\nprofile's ground at release, from the release z, as measured: "
            "negative where the\nrelease lies below the profile's ground, the ground's error "
            "that the site's\nrelease_height_sd_m describes; empty without it), and with "
            "several\n--profile a last column profile (the run's profile, "
            "relative to OUT's folder).\nrunout_m = x(stop) - x(release) along the run's "
            "profile.\n\n"
            "block_size_m is the volume-equivalent sphere diameter d = (6 m / (pi rho))^(1/3); "
            "only where\nthe mass is missing, d = (a b c)^(1/3) of the three dimensions. "
            "Shape rule (our own, after\nZingg 1935): a >= b >= c; disc if c/b <= 2/3, "
            "cylinder if b/a <= 2/3 < c/b, else sphere.\n"
            "Defaults marked ASSUMPTION are stated in calib/files/field_runs.py and "
            "data/README.md.\n\n"
            "Example (the shipped Tschamut observations):\n"
            "  python -m calib.field data/tschamut2014/runs.csv "
            "--blocks data/tschamut2014/blocks.csv \\\n"
            "    --profile data/tschamut2014/profile.csv "
            "--profile data/tschamut2014/east_spot_profile.csv \\\n"
            "    --out data/tschamut2014/observations.csv"))
    p.add_argument("runs", help="field runs CSV, one run per row")
    p.add_argument("--profile", required=True, action="append",
                   help="profile CSV with east_m,north_m columns (python -m terrain.cut) "
                        "whose plan trace the points are projected onto. Give it once "
                        "per fall line for runs let go from spots far apart: each run goes "
                        "on the profile that passes nearest its release point, and a "
                        "profile column (path relative to OUT's folder) says which")
    p.add_argument("--blocks", default=None,
                   help="blocks CSV joined on the block id column, giving mass and/or "
                        "dimensions where a run's own cells are empty (default: none)")
    p.add_argument("--out", required=True, help="observations CSV to write")
    p.add_argument("--density-kg-m3", type=float, default=DEFAULT_DENSITY_KG_M3,
                   help="rock density of the mass-equivalent diameter, kg/m^3 (default "
                        f"{DEFAULT_DENSITY_KG_M3:g}: ASSUMPTION, quartz; granite and gneiss)")
    p.add_argument("--runout-sd-m", type=float, default=DEFAULT_RUNOUT_SD_M,
                   help="tolerance of every runout, m (default "
                        f"{DEFAULT_RUNOUT_SD_M:g}: ASSUMPTION, tracking accuracy at both ends)")
    p.add_argument("--max-offset-m", type=float, default=DEFAULT_MAX_OFFSET_M,
                   help="flag and name runs with a point farther than this from the line, m "
                        f"(default {DEFAULT_MAX_OFFSET_M:g})")
    p.add_argument("--source", default=None,
                   help="provenance text for the source column (default: the runs file name)")
    d = RunColumns()
    p.add_argument("--id-col", default=d.run_id, help=f"run id column (default {d.run_id})")
    p.add_argument("--block-col", default=d.block_id,
                   help=f"block id column, in both tables (default {d.block_id})")
    p.add_argument("--mass-col", default=d.mass, help=f"mass column, kg (default {d.mass})")
    p.add_argument("--release-cols", default=",".join(d.release),
                   help=f"release east,north columns, m (default {','.join(d.release)}); "
                        "z is not needed: runouts are horizontal")
    p.add_argument("--stop-cols", default=",".join(d.stop),
                   help=f"stop east,north columns, m (default {','.join(d.stop)})")
    p.add_argument("--velocity-cols", default=",".join(d.velocity),
                   help=f"release velocity columns, m/s (default {','.join(d.velocity)}; "
                        "absent columns: no release_speed_m_s)")
    p.add_argument("--release-z-col", default=d.release_z,
                   help=f"height of the release point (the block's centre), m, in the "
                        f"profile's vertical datum (default {d.release_z}; an absent column "
                        "or an empty name: no release_height_m)")
    p.add_argument("--size-cols", default=",".join(d.size),
                   help=f"three block dimensions, m (default {','.join(d.size)})")
    return p


def _names(text: str, n: int, option: str) -> tuple[str, ...]:
    parts = tuple(t.strip() for t in text.split(","))
    if len(parts) != n or not all(parts):
        raise CliError(f"{option}: expected {n} comma-separated column names, got {text!r}")
    return parts


def _run(args) -> int:
    from solvers.profile import ProfileError
    from terrain.plan_line import read_profile_trace
    from terrain.raster import RasterError

    for opt, val in (("--density-kg-m3", args.density_kg_m3), ("--runout-sd-m", args.runout_sd_m),
                     ("--max-offset-m", args.max_offset_m)):
        if not (math.isfinite(val) and val > 0):
            raise CliError(f"{opt}: expected a positive number, got {val:g}")
    if not args.out.endswith(".csv"):
        raise CliError(f"--out {args.out}: expected a .csv file name")
    columns = RunColumns(
        run_id=args.id_col, block_id=args.block_col, mass=args.mass_col,
        release=_names(args.release_cols, 2, "--release-cols"),
        stop=_names(args.stop_cols, 2, "--stop-cols"),
        velocity=_names(args.velocity_cols, 3, "--velocity-cols"),
        size=_names(args.size_cols, 3, "--size-cols"), release_z=args.release_z_col.strip())
    paths = list(dict.fromkeys(args.profile))
    try:
        runs = load_runs(args.runs, args.blocks, columns)
        rows = observations_on_profiles(
            runs, paths, os.path.dirname(os.path.abspath(args.out)),
            density_kg_m3=args.density_kg_m3, runout_sd_m=args.runout_sd_m,
            max_offset_m=args.max_offset_m,
            source=args.source if args.source is not None else os.path.basename(args.runs),
            columns=columns)
        which = nearest_profiles(runs, [read_profile_trace(p)[1] for p in paths])
    except (FieldError, RasterError, ProfileError) as e:
        raise CliError(str(e)) from None
    try:
        write_all_atomic({args.out: text_writer(observations_csv_text(rows))})
    except OSError as e:
        raise CliError(f"cannot write {args.out}: {e.strerror or e}; nothing written") from None
    runout = np.array([r["runout_m"] for r in rows])
    offsets = np.array([max(abs(r["release_offset_m"]), abs(r["stop_offset_m"])) for r in rows])
    sizes = np.array([r["block_size_m"] for r in rows])
    k = int(np.argmax(offsets))
    n_box = int(np.isnan(runs.mass_kg).sum())
    along = (paths[0] if len(paths) == 1 else
             "their profiles (" + ", ".join(f"{int(np.sum(which == k))} on {p}"
                                            for k, p in enumerate(paths)) + ")")
    print(f"{len(rows)} runs: runout {runout.min():.1f} to {runout.max():.1f} m (median "
          f"{np.median(runout):.1f} m) along {along}; block_size_m "
          f"{sizes.min():.3f} to {sizes.max():.3f} m ({len(rows) - n_box} from mass at "
          f"{args.density_kg_m3:g} kg/m^3, {n_box} from dimensions); largest lateral offset "
          f"{offsets[k]:.1f} m (run {rows[k]['run_id']})")
    clear = np.array([r["release_height_m"] for r in rows])
    known = np.isfinite(clear)
    if known.any():
        n_below = int((clear[known] < 0).sum())
        below = ("none lies below its profile's ground" if not n_below else
                 f"{n_below} releases lie below the profile's ground (by up to "
                 f"{-clear[known].min():.2f} m), recorded as measured (negative)")
        print(f"release_height_m (block's lowest point above the profile's ground at release) "
              f"for {int(known.sum())} runs: {clear[known].min():.2f} to "
              f"{clear[known].max():.2f} m; {below}")
    flagged = [r for r in rows if r["beyond_max_offset"]]
    if flagged:
        names = ", ".join(f"{r['run_id']} ({offsets[i]:.1f} m)"
                          for i, r in enumerate(rows) if r["beyond_max_offset"])
        print(f"warning: {len(flagged)} of {len(rows)} runs have a release or stop point more "
              f"than {args.max_offset_m:g} m off their profile line (kept, flagged "
              f"beyond_max_offset): {names}", file=sys.stderr)
    print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m calib.field``; bad input: one line on stderr, exit 2, nothing written."""
    return run_guarded(PROG, _run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
