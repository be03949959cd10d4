"""Command line: ``python -m solvers.crsp --profile P --n-blocks N ... --out runouts.csv``.

Writes one row per block and prints a short summary. Bad arguments: one line on
stderr, exit status 2, nothing written.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from solvers.cli import (
    CliError,
    OneLineParser,
    fail,
    parse_stations,
    station_columns,
    write_csv_atomic,
)
from solvers.percentiles import few_blocks_warning
from solvers.status import STATUS_NAMES, finished


def build_parser() -> OneLineParser:
    p = OneLineParser(
        prog="python -m solvers.crsp",
        description=(
            "Simulate rockfall with the CRSP lumped-mass impact model along a 2D slope "
            "profile. Each block is released at the first profile vertex (or --release-x-m), "
            "bounces and rolls down the slope, and stops where friction allows. Writes one "
            "CSV row per block (runout, stop position, stopped flag, station records)."),
        epilog=(
            "Example: python -m solvers.crsp --profile data/postignano_profile.csv "
            "--n-blocks 10000 --radius-m 0.5 --Kn 0.41 --Kt 0.87 --roughness-m 2.0 --seed 0 "
            "--out runouts.csv --stations 110,230"))
    p.add_argument("--profile", required=True, help="profile CSV (x_m,z_m,zone)")
    p.add_argument("--materials", help="materials CSV (default: <site>_materials.csv "
                   "next to <site>_profile.csv)")
    p.add_argument("--n-blocks", type=int, default=1000, help="number of blocks (default 1000)")
    p.add_argument("--radius-m", type=float, default=0.5, help="block radius, m (default 0.5)")
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
    p.add_argument("--stations", help="analysis stations: '110,230' or 'start:stop:step' (m)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--max-events", type=int, default=None,
                   help="event budget per block; blocks still moving get status 'budget' "
                        "(default: 200 + 4 x segments + slope length / radius)")
    p.add_argument("--out", required=True, help="output CSV, one row per block")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    prog = parser.prog
    if args.n_blocks <= 0:
        fail(prog, f"--n-blocks must be positive, got {args.n_blocks}")
    if not (args.radius_m > 0 and np.isfinite(args.radius_m)):
        fail(prog, f"--radius-m must be a positive number, got {args.radius_m}")
    if args.max_events is not None and args.max_events <= 0:
        fail(prog, f"--max-events must be positive, got {args.max_events}")
    if args.release_spread_m < 0:
        fail(prog, f"--release-spread-m must be >= 0, got {args.release_spread_m}")

    import jax
    import pandas as pd
    from tqdm import tqdm

    from solvers import crsp
    from solvers.profile import ProfileError, load_profile

    try:
        profile = load_profile(args.profile, args.materials)
        overrides = {k: v for k, v in dict(
            Kn=args.Kn, Kt=args.Kt, roughness_m=args.roughness_m,
            rolling_friction_deg=args.rolling_friction_deg).items() if v is not None}
        if overrides:
            profile = profile.with_materials(**overrides)
        stations = parse_stations(args.stations, profile.x_range_m)
        lo, hi = profile.x_range_m
        release_x = lo if args.release_x_m is None else args.release_x_m
        if not (lo <= release_x < hi):
            raise CliError(f"--release-x-m {release_x:g} lies outside the profile "
                           f"[{lo:g}, {hi:g}) m")
        block = crsp.make_block(args.radius_m, args.shape, args.density_kg_m3)
    except (ProfileError, CliError, ValueError) as exc:
        fail(prog, str(exc))

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

    cols = {
        "block_id": np.arange(args.n_blocks),
        "runout_m": res.runout_m,
        "stop_x_m": res.stop_x_m,
        "stop_z_m": res.stop_z_m,
        "stopped": res.stopped.astype(bool),
        "status": [STATUS_NAMES.get(int(s), str(s)) for s in res.status],
        "n_impacts": res.n_impacts,
        "n_events": res.n_events,
    }
    cols.update(station_columns(stations, res.stations))
    try:
        write_csv_atomic(pd.DataFrame(cols), args.out)
    except OSError as exc:
        fail(prog, f"cannot write {args.out}: {exc.strerror or exc}")

    done = finished(res.status)
    ro = res.runout_m[done]
    counts = {STATUS_NAMES[int(c)]: int(np.sum(res.status == c)) for c in np.unique(res.status)}
    stats = (f"runout median {np.median(ro):.1f} m, p90 {np.percentile(ro, 90):.1f} m, "
             f"max {ro.max():.1f} m" if ro.size else "no block finished")
    print(f"CRSP: {args.n_blocks} blocks, radius {args.radius_m:g} m, seed {args.seed}: "
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
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
