"""Command line: ``python -m solvers.crsp --profile P --block-size-m 1 --n-blocks N ...
--out runouts.csv``.

Writes one row per block and prints a short summary. Bad arguments: one line on
stderr, exit status 2, nothing written.

The block size is the diameter d (``--block-size-m``); the CRSP sphere (or
cylinder, disc) has radius r = d/2. ``--radius-m`` (r) and ``--stations`` are
deprecated names kept one release (``solvers.cli.deprecated_alias``).

Output CSV (the schema of ``python -m solvers.dem`` too, ``solvers.cli.RUN_COLUMNS``):
block, fragment (0: a CRSP block is one piece), block_size_m, status, runout_m,
stop_x_m, stop_z_m; then n_impacts, n_events; then per station x
passed_<x>m, energy_kJ_<x>m (kJ per block), velocity_m_s_<x>m,
bounce_height_m_<x>m (``solvers.cli.station_columns``).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from solvers.cli import (
    CliError,
    OneLineParser,
    deprecated_alias,
    fail,
    parse_stations,
    run_columns,
    run_columns_help,
    station_columns,
    write_csv_atomic,
)
from solvers.percentiles import few_blocks_warning
from solvers.status import STATUS_NAMES, finished

# the CRSP's own columns of the output CSV, after solvers.cli.RUN_COLUMNS
OWN_COLUMNS = {"n_impacts": "CRSP impacts on the slope",
               "n_events": "events of the run (flights and rolling phases, solvers.crsp._model)"}


def build_parser() -> OneLineParser:
    import argparse
    import textwrap

    p = OneLineParser(
        prog="python -m solvers.crsp",
        description=textwrap.fill(
            "Simulate rockfall with the CRSP lumped-mass impact model along a 2D slope "
            "profile. Each block is released at the first profile vertex (or --release-x-m), "
            "bounces and rolls down the slope, and stops where friction allows. Writes one "
            "CSV row per block (runout, stop position, status, station records).", 80),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(
            run_columns_help(OWN_COLUMNS) + "\n\n"
            "Example: python -m solvers.crsp --profile data/postignano_profile.csv \\\n"
            "    --n-blocks 10000 --block-size-m 1 --Kn 0.41 --Kt 0.87 --roughness-m 2.0 \\\n"
            "    --seed 0 --out runouts.csv --stations-m 110,230"))
    p.add_argument("--profile", required=True, help="profile CSV (x_m,z_m,zone)")
    p.add_argument("--materials", help="materials CSV (default: <site>_materials.csv "
                   "next to <site>_profile.csv)")
    p.add_argument("--n-blocks", type=int, default=1000, help="number of blocks (default 1000)")
    p.add_argument("--block-size-m", type=float, default=1.0,
                   help="block size d, the diameter, m; the CRSP shape's radius is r = d/2 "
                        "(default 1.0)")
    deprecated_alias(p, "--radius-m", "--block-size-m", convert=lambda r: 2.0 * r,
                     note=" given as the radius r, read as d = 2 r")
    p.add_argument("--shape", choices=("sphere", "cylinder", "disc"), default="sphere",
                   help="block shape (default sphere)")
    p.add_argument("--density-kg-m3", type=float, default=2350.0,
                   help="rock density (default 2350, the paper's value)")
    p.add_argument("--Kn", type=float, help="normal restitution for every zone "
                   "(default: the materials file)")
    p.add_argument("--Kt", type=float, help="tangential restitution for every zone")
    p.add_argument("--roughness-m", type=float, help="slope roughness S for every zone, m")
    p.add_argument("--rolling-friction-deg", type=float,
                   help="rolling-resistance angle for every zone, degrees")
    p.add_argument("--release-x-m", type=float, help="release abscissa, m (default: first vertex)")
    p.add_argument("--release-spread-m", type=float, default=0.0,
                   help="release abscissa drawn uniformly over this width, m (default 0)")
    p.add_argument("--release-vx-m-s", type=float, default=1.0,
                   help="initial horizontal velocity, m/s (default 1)")
    p.add_argument("--stations-m", help="analysis stations, m: '110,230' or 'start:stop:step' "
                   "(default: none)")
    deprecated_alias(p, "--stations", "--stations-m")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--max-events", type=int, default=None,
                   help="event budget per block; blocks still moving get status 'budget' "
                        "(default: 200 + 4 x segments + slope length / r)")
    p.add_argument("--out", required=True, help="output CSV, one row per block")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    prog = parser.prog
    _check_numbers(args, prog)
    profile, stations, release_x, block = _setup(args, prog)
    res, wall = _simulate(args, profile, stations, release_x, block)

    import pandas as pd

    cols = run_columns(args.block_size_m, res.status, res.runout_m, res.stop_x_m, res.stop_z_m)
    cols.update(n_impacts=res.n_impacts, n_events=res.n_events)
    cols.update(station_columns(stations, res.stations))
    try:
        write_csv_atomic(pd.DataFrame(cols), args.out)
    except OSError as exc:
        fail(prog, f"cannot write {args.out}: {exc.strerror or exc}")
    _report(args, res, stations, wall)
    print(f"wrote {args.out}")
    return 0


def _check_numbers(args, prog: str) -> None:
    """Refuse, in one line, a non-positive block count, block size or event
    budget and a negative release spread (before anything is loaded)."""
    if args.n_blocks <= 0:
        fail(prog, f"--n-blocks must be positive, got {args.n_blocks}")
    if not (args.block_size_m > 0 and np.isfinite(args.block_size_m)):
        fail(prog, f"--block-size-m must be a positive number, got {args.block_size_m:g}")
    if args.max_events is not None and args.max_events <= 0:
        fail(prog, f"--max-events must be positive, got {args.max_events}")
    if args.release_spread_m < 0:
        fail(prog, f"--release-spread-m must be >= 0, got {args.release_spread_m}")


def _setup(args, prog: str):
    """The profile (with the command line's material overrides), the stations,
    the release abscissa and the block; a bad file or value fails in one line.

    Returns:
        (profile, stations, release_x_m, block).
    """
    from solvers import crsp
    from solvers.profile import ProfileError, load_profile

    try:
        profile = load_profile(args.profile, args.materials)
        overrides = {k: v for k, v in dict(
            Kn=args.Kn, Kt=args.Kt, roughness_m=args.roughness_m,
            rolling_friction_deg=args.rolling_friction_deg).items() if v is not None}
        if overrides:
            profile = profile.with_materials(**overrides)
        stations = parse_stations(args.stations_m, profile.x_range_m)
        lo, hi = profile.x_range_m
        release_x = lo if args.release_x_m is None else args.release_x_m
        if not (lo <= release_x < hi):
            raise CliError(f"--release-x-m {release_x:g} lies outside the profile "
                           f"[{lo:g}, {hi:g}) m")
        block = crsp.make_block(args.block_size_m / 2.0, args.shape, args.density_kg_m3)
    except (ProfileError, CliError, ValueError) as exc:
        fail(prog, str(exc))
    return profile, stations, release_x, block


def _simulate(args, profile, stations, release_x, block):
    """Run the ``--n-blocks`` blocks keyed ``--seed`` (with a progress bar).

    Returns:
        (the run's ``Result``, wall time in s including compilation).
    """
    import jax
    from tqdm import tqdm

    from solvers import crsp

    params = crsp.params_from_profile(
        profile, release_x_m=release_x, release_x_spread_m=args.release_spread_m,
        release_vx_m_s=args.release_vx_m_s)
    settings = crsp.Settings(max_events=args.max_events)
    bar = tqdm(total=args.n_blocks, unit="block", disable=args.no_progress, file=sys.stderr)
    t0 = time.perf_counter()
    res = crsp.run_blocks(params, block, jax.random.key(args.seed), args.n_blocks, profile,
                          stations_x_m=stations or None, settings=settings,
                          progress=bar.update)
    wall = time.perf_counter() - t0
    bar.close()
    return res, wall


def _report(args, res, stations, wall: float) -> None:
    """Print the run's summary: runout percentiles of the finished blocks, the
    status counts, each station's reach and energy p95; warn on stderr about
    unfinished blocks and about percentiles resting on few blocks."""
    done = finished(res.status)
    ro = res.runout_m[done]
    counts = {STATUS_NAMES[int(c)]: int(np.sum(res.status == c)) for c in np.unique(res.status)}
    stats = (f"runout median {np.median(ro):.1f} m, p90 {np.percentile(ro, 90):.1f} m, "
             f"max {ro.max():.1f} m" if ro.size else "no block finished")
    print(f"CRSP: {args.n_blocks} blocks of size {args.block_size_m:g} m (radius "
          f"{args.block_size_m / 2:g} m), seed {args.seed}: "
          f"{stats} (finished blocks); status "
          + ", ".join(f"{k} {v}" for k, v in counts.items())
          + f"; mean {res.n_events.mean():.1f} events/block"
          + f"; {args.n_blocks / wall:,.0f} blocks/s incl. compile ({wall:.2f} s)")
    if not done.all():
        print(f"warning: {int((~done).sum())} blocks did not finish (status budget or "
              "invalid); their rows are in the CSV but not in the statistics above",
              file=sys.stderr)
    few = [("runout", ro.size)] if ro.size else []
    for j, xs in enumerate(stations):
        passed = res.stations.passed[:, j]
        e = res.stations.energy_kJ[passed, j]
        e95 = f", E p95 {np.percentile(e, 95):.1f} kJ from {e.size} blocks" if e.size else ""
        print(f"  station x = {xs:g} m: reached by {passed.mean():.1%}{e95}")
        if e.size:
            few.append((f"station x = {xs:g} m", e.size))
    warning = few_blocks_warning(few)
    if warning:
        print(warning, file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
