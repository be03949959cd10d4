"""Command line: ``python -m calib.hazard results/calibration.json [options]``.

Writes into ``--out`` (default ``results/hazard/``): ``hazard.nc`` (the results
Dataset, ``calib.files.hazard_results``: what ``python -m calib.design`` reads),
and from it ``exceedance.csv``, ``hazard_table.csv``, ``exceedance.png``,
``envelopes.png``, ``summary.txt`` (and with fragmentation ``fragments.csv``,
``calib.hazard._fragments``), each through a temporary file and a
rename, only after the whole run succeeded. Bad input: one line on stderr, exit
status 2, nothing written.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from typing import NamedTuple

from calib.hazard._fragment_options import add_options as add_fragment_options
from calib.hazard._run import HAZARD_SETTINGS
from calib.model.dem_run import DEM_RUN
from solvers.cli import (
    CliError,
    OneLineParser,
    deprecated_alias,
    fail,
    json_ready,
    parse_floats,
    parse_stations,
    write_outputs,
)
from solvers.dem import check_run_numerics

DEFAULT_SIZES = "0.2,0.5,1.0,2.0"
# model -> (blocks per draw and size, posterior draws); DEM defaults keep the
# default DEM run under 10 minutes on 2 CPU cores (254 s on 2026-11-21: docs/studies.md)
DEFAULTS = {"crsp": (20000, 100), "dem": (64, 16)}


def build_parser() -> OneLineParser:
    p = OneLineParser(
        prog="python -m calib.hazard",
        description=(
            "Rockfall hazard along the slope profile from a calibration: Monte Carlo over "
            "posterior draws x block sizes x blocks; runout exceedance curves with posterior "
            "bands, reach probability, energy / bounce-height / velocity design values, Swiss "
            "intensity classes and (with --release-rate-per-year) annual frequencies and "
            "hazard levels. Writes hazard.nc (every result, for python -m calib.design) and "
            "from it exceedance.csv, hazard_table.csv, two PNG figures and summary.txt."),
        epilog="Example: python -m calib.hazard results/calibration.json --n-posterior 20 "
               "--n-blocks 5000 --release-rate-per-year 0.5 --out results/hazard/")
    p.add_argument("calibration", help="calibration.json written by python -m calib.fit")
    p.add_argument("--model", choices=("crsp", "dem"),
                   help="solver (default: crsp if calibrated, else dem)")
    p.add_argument("--stations-m", help="stations 'start:stop:step' or 'x1,x2,...' in m "
                   "(default: the profile's range every 5 m)")
    deprecated_alias(p, "--stations", "--stations-m")
    p.add_argument("--block-sizes-m", default=None,
                   help="block sizes d (the diameter), m: CRSP spheres of radius d/2, DEM "
                        f"squares of side d (default {DEFAULT_SIZES}; not with a volume "
                        "distribution, whose classes replace the sizes)")
    deprecated_alias(p, "--block-sizes", "--block-sizes-m")
    p.add_argument("--block-shape", default=None,
                   help="CRSP shape class of the blocks (solvers.crsp.make_block, CRSP 4.0): "
                        "sphere, cylinder (length 2 r, rolling on its curved face) or disc "
                        "(thickness r / 2, rolling on its rim); one for every size or volume "
                        "class, or one per size (class), comma-separated. A size d is the "
                        "diameter of the sphere of the block's volume, as the fit reads a "
                        "row's size: the shape's radius is s d / 2, s = 0.874 (cylinder), "
                        "1.387 (disc) (default sphere; CRSP only)")
    p.add_argument("--n-blocks", type=int, help="blocks per draw and size (or volume class) "
                   f"(default {DEFAULTS['crsp'][0]} CRSP, {DEFAULTS['dem'][0]} DEM)")
    p.add_argument("--n-posterior", type=int, help="posterior draws; 1 = the point "
                   f"estimate (default {DEFAULTS['crsp'][1]} CRSP, {DEFAULTS['dem'][1]} DEM)")
    p.add_argument("--release-rate-per-year", type=float,
                   help="blocks of each size released per year (gives annual frequencies "
                        "and hazard levels)")
    p.add_argument("--release-x-m", type=float, default=None,
                   help="release abscissa of every block, m (default: the calibration's "
                        "release_x_m, the median release of the rows it fitted; files "
                        "without one: the profile's first vertex)")
    p.add_argument("--road-x-m", type=float, default=None,
                   help="abscissa of the station of interest (a road) where the summary "
                        "reports, m (default: the site file's station_of_interest next to "
                        "the calibration's profile, calib/files/site.py; without one, the "
                        "profile's last station)")
    p.add_argument("--out", default="results/hazard/",
                   help="output folder (default results/hazard/)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--chunk-blocks", type=int, default=16384,
                   help="most blocks per size in one compiled call (bounds memory; "
                        "default 16384)")
    p.add_argument("--pool", type=int, default=None,
                   help="CRSP lanes per call (default: 256 on a CPU, 4096 on an accelerator; "
                        "results do not depend on it)")
    p.add_argument("--max-events", type=int, default=HAZARD_SETTINGS.max_events,
                   help="CRSP event budget per block; a block still moving after it is "
                        f"counted unfinished (default {HAZARD_SETTINGS.max_events})")
    p.add_argument("--dem-stiffness-scale", type=float, default=None,
                   help="DEM: multiply kn = ks = 50 GPa/m by this (default: the fit's, "
                        f"from the calibration file; {DEM_RUN.stiffness_scale:g} for files "
                        "without one)")
    p.add_argument("--dem-max-time-s", type=float, default=None,
                   help="DEM: simulated-time bound per block, s (default: the fit's, from "
                        f"the calibration file; {DEM_RUN.max_time_s:g} for files without one)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _release_options(p)
    _barrier_options(p)
    add_fragment_options(p)
    return p


def _release_options(p: OneLineParser) -> None:
    g = p.add_argument_group(
        "release conditions (calib/model/release.py)",
        "Blocks drawn one by one: a volume from a block-volume distribution (a block of "
        "volume V is the sphere of diameter d = (6 V / pi)^(1/3) and mass rho V; CRSP "
        "only), an abscissa in a release zone, a height and a speed (both models; the "
        "DEM's blocks are the fixed sizes). The tables then report per "
        "volume class, each simulated with --n-blocks blocks per draw; with "
        "--release-rate-per-year (blocks per year of the whole distribution) a class's "
        "frequencies are scaled by its probability. Classes or sizes outside the block "
        "sizes the calibration was fitted on are flagged as extrapolation.")
    g.add_argument("--volumes-csv", help="block survey CSV, column volume_m3 (m^3) or mass_kg "
                   "(kg, divided by the calibration's rock_density_kg_m3): each block drawn "
                   "from the surveyed volumes")
    g.add_argument("--volume-law", help="a named block-volume law: "
                   "'lognormal:median_m3=M,sigma=S' (sigma of ln V) or "
                   "'powerlaw:vmin_m3=A,vmax_m3=B,b=B' (N(>V) ~ V^-b on [A, B], the "
                   "magnitude-frequency relation)")
    g.add_argument("--volume-classes-m3", help="interior edges of the volume classes, "
                   "m^3, e.g. '0.1,1,5' (default: the distribution's 50, 90 and 99 %% "
                   "quantiles)")
    g.add_argument("--return-period-yr", type=float, help="report the design block of this "
                   "return period: the volume V_T exceeded by R (1 - F(V_T)) = 1/T blocks per "
                   "year (De Biagi et al. 2017; needs a volume distribution and "
                   "--release-rate-per-year R)")
    g.add_argument("--release-zone-m", help="release zone: 'A:B' (uniform on [A, B]) or "
                   "'x1:w1,x2:w2,...' (points with weights), m (default: --release-x-m)")
    g.add_argument("--release-height-m", type=float, help="release height above the ground, "
                   "m: CRSP's lumped mass, the DEM square's lowest possible point, as the "
                   "fit reads a tracked release (default: the solver's, on the ground)")
    g.add_argument("--release-height-sd-m", type=float, default=None,
                   help="standard deviation of the release height's error, m; each block's "
                        "height a normal truncated to >= 0 (default, with "
                        "--release-height-m: the calibration's release_height_sd_m, the "
                        "site's tracked-height error; else 0)")
    g.add_argument("--release-speed-m-s", type=float, help="horizontal release speed, m/s "
                   "(default: 1 m/s, the solver's)")
    g.add_argument("--release-speed-sd-m-s", type=float, default=None,
                   help="standard deviation of the release speed's error, m/s; a normal "
                        "truncated to >= 0 (default, with --release-speed-m-s: the "
                        "calibration's release_speed_sd_m_s; else 0)")


def _barrier_options(p: OneLineParser) -> None:
    g = p.add_argument_group(
        "protection barrier (CRSP; solvers/crsp/_barrier.py)",
        "A vertical barrier at X: a block whose lowest point passes below H is stopped "
        "where its kinetic energy is at most the capacity, else breaks through keeping E "
        "minus the capacity; over H it flies over. The run writes its own hazard.nc: "
        "python -m calib.design RUN_WITHOUT/hazard.nc --with-barrier THIS/hazard.nc "
        "shows the residual hazard beside the run without it (same seed: common random "
        "numbers).")
    g.add_argument("--barrier-x-m", type=float, help="barrier abscissa, m: inside the "
                   "profile, downslope of every release point (default: no barrier)")
    g.add_argument("--barrier-height-m", type=float, help="its height above the ground, m "
                   "(default: unlimited)")
    g.add_argument("--barrier-capacity-kJ", type=float, dest="barrier_capacity_kJ",
                   help="the energy it absorbs, kJ (a kit's MEL; default: unlimited)")


def _positive_int(name: str, v: int) -> None:
    if v <= 0:
        raise CliError(f"{name}: expected a positive count, got {v}")


def main(argv: list[str] | None = None) -> int:
    """The command: options checked, the run prepared from the files, simulated,
    its results written at once; bad input one line on stderr and exit status 2."""
    from calib.files.provenance import command_args

    with command_args(argv):
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    prog = parser.prog
    try:
        sizes = _checked_options(args)
    except CliError as exc:
        fail(prog, str(exc))

    from calib.files.site import SiteError
    from calib.hazard import CalibrationError
    from solvers.profile import ProfileError

    try:
        run = _prepare(args, sizes)
    except (CalibrationError, ProfileError, CliError, SiteError) as exc:
        fail(prog, str(exc))

    counts, total, wall = _simulate(args, run, sizes)
    text, writers = _outputs(prog, args, run, counts)
    try:
        written = write_outputs(args.out, {"summary.txt": text + "\n"}, writers=writers)
    except OSError as exc:
        fail(prog, f"cannot write to {args.out}: {exc.strerror or exc}")
    print(text)
    import jax

    names = ", ".join(os.path.basename(w) for w in written)
    print(f"{total:,} blocks in {wall:.1f} s ({total / wall:,.0f} blocks/s incl. compile) on "
          f"{len(jax.devices())} device(s); wrote {names} to {args.out}")
    return 0


def _checked_options(args) -> list[float]:
    """The options checked for what needs no file (``CliError`` naming the option);
    returns the block sizes of ``--block-sizes-m``."""
    _check_conditions(args)
    sizes = parse_floats(args.block_sizes_m or DEFAULT_SIZES, "--block-sizes-m")
    bad = [s for s in sizes if s <= 0]
    if bad:
        raise CliError(f"--block-sizes-m: sizes must be positive, got {bad[0]:g}")
    if len(set(sizes)) != len(sizes):
        raise CliError("--block-sizes-m: sizes must be distinct")
    for name in ("n_blocks", "n_posterior"):
        v = getattr(args, name)
        if v is not None:
            _positive_int("--" + name.replace("_", "-"), v)
    _positive_int("--chunk-blocks", args.chunk_blocks)
    if args.pool is not None:
        _positive_int("--pool", args.pool)
    _positive_int("--max-events", args.max_events)
    if args.seed < 0:
        raise CliError(f"--seed: expected a non-negative integer, got {args.seed}")
    rate = args.release_rate_per_year
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise CliError(f"--release-rate-per-year: expected a positive rate, got {rate:g}")
    try:
        check_run_numerics(args.dem_stiffness_scale, args.dem_max_time_s,
                           {"stiffness_scale": "--dem-stiffness-scale",
                            "max_time_s": "--dem-max-time-s"})
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise CliError(f"--out {args.out}: exists and is not a folder")
    return sizes


class _Run(NamedTuple):
    """A run prepared from its options and files: the calibration ``cal``, the
    ``profile``, the ``stations`` (with the station of interest ``road_x``, named
    ``label``), the ``release_x``, the posterior ``draws``, ``n_blocks`` per draw and
    size, the release and barrier ``cond`` (``_Conditions``) and the ``fragments``
    (or None)."""

    cal: object
    profile: object
    stations: list
    road_x: float
    label: str
    release_x: float
    draws: object
    n_blocks: int
    cond: _Conditions
    fragments: object


def _prepare(args, sizes) -> _Run:
    """The ``_Run`` of the options: the calibration and its profile read, the
    station of interest and the release placed on the profile, the draws made
    (``CliError`` or the files' errors naming the option or the file)."""
    from calib.hazard import check_dem_draws, draw_parameters, load_calibration
    from calib.hazard._fragment_options import FragmentationError, fragmentation_from_args
    from solvers.profile import load_profile

    cal = load_calibration(args.calibration, args.model)
    profile = load_profile(cal.profile_csv)
    lo, hi = profile.x_range_m
    stations = parse_stations(args.stations_m or f"{lo:g}:{hi:g}:5", profile.x_range_m)
    road_x, label, where = _station_of_interest(args, cal, profile, stations)
    release_x, zone = _release(args, cal, profile, road_x, where)
    stations = sorted(set(stations) | {road_x})
    n_blocks = args.n_blocks or DEFAULTS[cal.model][0]
    n_post = args.n_posterior or DEFAULTS[cal.model][1]
    draws = draw_parameters(cal, n_post, args.seed)
    if cal.model == "dem":
        check_dem_draws(cal, draws, sizes)
    cond = _conditions(args, cal, profile, sizes, release_x, zone)
    try:
        fragments = fragmentation_from_args(args, cal, draws, profile)
    except FragmentationError as e:
        raise CliError(str(e)) from None
    return _Run(cal, profile, stations, road_x, label, release_x, draws, n_blocks, cond,
                fragments)


def _station_of_interest(args, cal, profile, stations) -> tuple[float, str, str]:
    """The station where the summary reports: ``--road-x-m``, else the site file's
    station of interest, else the last station (said on stdout); with its name and
    where it came from. Also checks the site's rock density against the calibration's,
    and says so where the site's CRSP rolling threshold is not the one the
    calibration was fitted at (the run keeps the calibration's: the fitted model)."""
    from calib.files.site import load_site, site_path

    lo, hi = profile.x_range_m
    road_x, label = args.road_x_m, "road"
    site = load_site(cal.profile_csv)
    cal.check_density(site.rock_density_kg_m3, f"the site file {site.path}"
                      if site.path else "the solvers' default")
    if cal.model == "crsp" and site.rolling_threshold_m_s != cal.rolling_threshold_m_s:
        print(f"{cal.path} was fitted at a CRSP rolling threshold of "
              f"{cal.rolling_threshold_m_s:g} m/s and {site.path or 'the solver default'} "
              f"gives {site.rolling_threshold_m_s:g} m/s: this run simulates the fitted model "
              "(the calibration's value); refit to run at the site's")
    if road_x is None:
        road_x, label = site.station_x_m, site.station_label
        where = f"{site.path}: station_of_interest.x_m"
        if road_x is None:
            road_x, label, where = max(stations), "last station", "the last station"
            site_says = (f"the site file {site.path} gives no station_of_interest"
                         if site.path else
                         f"no site file {site_path(cal.profile_csv)} gives one")
            print(f"no station of interest (no --road-x-m, and {site_says}): the summary "
                  f"reports at the last station, x = {road_x:g} m")
    else:
        where = "--road-x-m"
    if not (math.isfinite(road_x) and lo < road_x <= hi):
        raise CliError(f"{where} {road_x:g}: the station of interest lies outside the "
                       f"profile ({lo:g}, {hi:g}] m")
    return road_x, label, where


def _release(args, cal, profile, road_x: float, where: str):
    """The release abscissa and the release zone (or None) of the options, checked
    against the profile and upslope of the station of interest (from ``where``)."""
    from calib.hazard import default_release_x_m

    lo, hi = profile.x_range_m
    release_x, release_where = args.release_x_m, "--release-x-m"
    zone = None
    if args.release_zone_m is not None:
        zone = _zone(args.release_zone_m, profile)
        release_x, release_where = zone.span_m[1], "--release-zone-m"
    elif release_x is None:
        release_x = default_release_x_m(cal, profile)
        release_where = (f"{cal.path}: release_x_m" if cal.release_x_m is not None
                         else "the profile's first vertex")
    if not (math.isfinite(release_x) and lo <= release_x < hi):
        raise CliError(f"{release_where} {release_x:g}: the release lies outside the "
                       f"profile [{lo:g}, {hi:g}) m")
    typed = args.release_x_m is not None or zone is not None
    if road_x <= release_x and typed and args.road_x_m is None:
        # the release was typed, the station was not: the flag is what to change
        raise CliError(f"{release_where} {release_x:g}: the release lies at or downslope "
                       f"of the station of interest at x = {road_x:g} m ({where}), so no "
                       f"block can pass it; the profile spans [{lo:g}, {hi:g}) m: release "
                       f"above x = {road_x:g} m, or give --road-x-m")
    if road_x <= release_x:
        raise CliError(f"{where} {road_x:g}: the station of interest lies at or above "
                       f"the release at x = {release_x:g} m ({release_where}): no block "
                       "can pass it")
    return release_x, zone


def _dem_run(args, cal):
    """The DEM numerics of the run: the fit's (``DEM_RUN`` for files without them)
    with the options' overrides; a note on stderr where a DEM run departs from the fit's."""
    from calib.hazard import DemRun

    fitted = DemRun(**cal.dem_run) if cal.dem_run else DEM_RUN
    dem_run = dataclasses.replace(fitted, **{
        k: v for k, v in (("stiffness_scale", args.dem_stiffness_scale),
                          ("max_time_s", args.dem_max_time_s)) if v is not None})
    if cal.model == "dem" and dem_run != fitted:
        print(f"note: the DEM runs with {dem_run}, not the fit's {fitted}: its alpha was "
              "calibrated with the fit's numerics", file=sys.stderr)
    return dem_run


def _simulate(args, run: _Run, sizes):
    """The Monte Carlo run (``run_hazard``) with a progress bar on stderr: its counts,
    the number of blocks simulated and the wall time, s."""
    import numpy as np
    from tqdm import tqdm

    from calib.hazard import run_hazard

    cal, cond = run.cal, run.cond
    dem_run = _dem_run(args, cal)
    n_sets = len(sizes) if cond.seeder is None else len(cond.seeder.classes)
    total = len(run.draws.values) * n_sets * run.n_blocks
    bar = tqdm(total=total, unit="block", disable=args.no_progress, file=sys.stderr,
               desc=f"hazard {cal.model}")
    t0 = time.perf_counter()
    counts = run_hazard(cal, run.draws, run.profile, sizes, np.asarray(run.stations),
                        run.n_blocks, args.seed, chunk_blocks=args.chunk_blocks, pool=args.pool,
                        settings=dataclasses.replace(HAZARD_SETTINGS, max_events=args.max_events),
                        dem_run=dem_run, release_x_m=run.release_x, release=cond.seeder,
                        barrier=cond.barrier, progress=bar.update, fragments=run.fragments,
                        shapes=cond.shapes if cond.seeder is None else None)
    wall = time.perf_counter() - t0
    bar.close()
    return counts, total, wall


def _outputs(prog: str, args, run: _Run, counts) -> tuple[str, dict]:
    """The summary text and the writers of the output files (``write_outputs``):
    hazard.nc, the tables, the figures (and the fragments' outputs), all from the
    results Dataset."""
    from calib.files.hazard_results import results_writer
    from calib.hazard import exceedance_table, hazard_table, summary_text
    from calib.hazard._figures import plot_envelopes, plot_exceedance
    from calib.hazard._fragment_tables import fragment_outputs
    from calib.hazard._results import calibration_record, hazard_dataset

    cal, cond, profile, road_x, label = run.cal, run.cond, run.profile, run.road_x, run.label
    rate = args.release_rate_per_year
    record = calibration_record(prog, args.seed, cal, args.calibration)
    record.update(cond.record)
    if cond.shapes is not None:  # the shapes the fit simulated, for the summary to compare
        from calib.files.calibration_file import fitted_block_shapes

        record["fitted_block_shapes"] = ", ".join(fitted_block_shapes(cal))
    results = hazard_dataset(counts, profile, seed=args.seed, road_x_m=road_x, road_label=label,
                             release_rate_per_year=rate, record=record,
                             fitted=cond.fitted)
    exc_df = exceedance_table(results)
    table = hazard_table(results)
    text = summary_text(results, table, road_x, rate, label, fitted=cond.fitted)
    title = (f"{cal.model.upper()}: {len(run.draws.values)} draw(s) ({run.draws.source}) x "
             f"{run.n_blocks} blocks per " + ("size" if cond.seeder is None or
                                               cond.seeder.law is None else "volume class"))
    writers = {
        "hazard.nc": results_writer(results),
        "exceedance.csv": _csv_writer(exc_df),
        "hazard_table.csv": _csv_writer(table),
        "exceedance.png": lambda p: plot_exceedance(exc_df, profile, road_x, p, title, label),
        "envelopes.png": lambda p: plot_envelopes(table, profile, road_x, p, title),
    }
    text = fragment_outputs(counts.fragments, results, writers, text, road_x, label)
    return text, writers


def _csv_writer(df):
    """A ``write_outputs`` writer of ``df`` as CSV without its index."""
    return lambda p: df.to_csv(p, index=False)


def _check_conditions(args) -> None:
    """The release and barrier options, checked for what needs no file."""
    dist = [o for o, v in (("--volumes-csv", args.volumes_csv),
                           ("--volume-law", args.volume_law)) if v is not None]
    if len(dist) > 1:
        raise CliError("--volumes-csv and --volume-law: give one volume distribution")
    if dist and args.block_sizes_m is not None:
        raise CliError(f"--block-sizes-m and {dist[0]}: give fixed sizes or a volume "
                       "distribution, not both")
    for opt, v in (("--volume-classes-m3", args.volume_classes_m3),
                   ("--return-period-yr", args.return_period_yr)):
        if v is not None and not dist:
            raise CliError(f"{opt}: needs a volume distribution (--volumes-csv or "
                           "--volume-law)")
    if args.return_period_yr is not None:
        if not (math.isfinite(args.return_period_yr) and args.return_period_yr > 0):
            raise CliError(f"--return-period-yr {args.return_period_yr:g}: expected a "
                           "positive number of years")
        if args.release_rate_per_year is None:
            raise CliError("--return-period-yr: needs --release-rate-per-year (blocks per "
                           "year of the whole distribution)")
    if args.release_zone_m is not None and args.release_x_m is not None:
        raise CliError("--release-zone-m and --release-x-m: give one of them")
    for opt, mean, sd in (("height", args.release_height_m, args.release_height_sd_m),
                          ("speed", args.release_speed_m_s, args.release_speed_sd_m_s)):
        unit = "m" if opt == "height" else "m-s"
        for name, v in ((f"--release-{opt}-{unit}", mean), (f"--release-{opt}-sd-{unit}", sd)):
            if v is not None and not (math.isfinite(v) and v >= 0):
                raise CliError(f"{name} {v:g}: expected a number >= 0")
        if (sd or 0.0) > 0 and mean is None:
            raise CliError(f"--release-{opt}-sd-{unit}: needs --release-{opt}-{unit} (the "
                           "mean)")
    if args.barrier_x_m is None:
        for name in ("height_m", "capacity_kJ"):
            if getattr(args, "barrier_" + name) is not None:
                raise CliError(f"--barrier-{name.replace('_', '-')}: needs --barrier-x-m")
        return
    if not math.isfinite(args.barrier_x_m):
        raise CliError(f"--barrier-x-m {args.barrier_x_m:g}: expected a finite abscissa, m")
    for name, unit in (("height_m", "m"), ("capacity_kJ", "kJ")):
        v = getattr(args, "barrier_" + name)
        if v is not None and not v >= 0:
            raise CliError(f"--barrier-{name.replace('_', '-')} {v:g}: expected a number >= "
                           f"0 {unit} (inf: unlimited)")


def _zone(text: str, profile):
    """``--release-zone-m`` as a ``ReleaseZone`` inside the profile."""
    from calib.model.release import parse_release_zone

    try:
        zone = parse_release_zone(text)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    lo, hi = profile.x_range_m
    a, b = zone.span_m
    if not (lo <= a and b < hi):
        raise CliError(f"--release-zone-m {text}: the zone spans x = {a:g}-{b:g} m, outside "
                       f"the profile [{lo:g}, {hi:g}) m")
    return zone


class _Conditions(NamedTuple):
    """What the release and barrier options make of a run: ``seeder`` (None: every
    block at one release, the solver's state), ``barrier`` (or None), ``fitted``
    (the calibration's fitted block sizes and their source, or None), ``record``
    (more hazard.nc attributes: the design block of a return period), ``shapes``
    (each size's or class's CRSP shape, or None: spheres)."""

    seeder: object
    barrier: object
    fitted: tuple | None
    record: dict
    shapes: tuple[str, ...] | None = None


def _shapes(args, cal, n: int) -> tuple[str, ...] | None:
    """``--block-shape``: one CRSP shape per size or class (``n``), or None."""
    from solvers.crsp import SHAPES

    if args.block_shape is None:
        return None
    names = [v.strip() for v in args.block_shape.split(",")]
    bad = [v for v in names if v not in SHAPES]
    if bad:
        raise CliError(f"--block-shape: expected {', '.join(SHAPES)}, got {bad[0]!r}")
    if len(names) not in (1, n):
        raise CliError(f"--block-shape: expected one shape or {n} (one per size or volume "
                       f"class), got {len(names)}")
    if cal.model != "crsp" and any(v != "sphere" for v in names):
        raise CliError("--block-shape: CRSP's shape classes; the DEM's blocks are squares "
                       "(use --model crsp)")
    return tuple(names * n if len(names) == 1 else names)


def _conditions(args, cal, profile, sizes, release_x: float, zone) -> _Conditions:
    """The run's ``_Conditions`` from its options, checked against the calibration
    and the profile (``CliError`` naming the option or the file)."""
    from calib.files.block_survey import BlockSurveyError, read_block_survey
    from calib.files.calibration_file import fitted_block_sizes_m
    from calib.hazard._run import Barrier
    from calib.model.release import (
        ReleaseState,
        ReleaseZone,
        Seeder,
        diameter_m,
        parse_volume_law,
        volume_classes,
    )

    used = [o for o, v in (("--volumes-csv", args.volumes_csv), ("--volume-law", args.volume_law),
                           ("--barrier-x-m", args.barrier_x_m)) if v is not None]
    if cal.model != "crsp" and used:
        raise CliError(f"{used[0]}: the DEM hazard run takes fixed sizes (a release zone, "
                       "height and speed allowed) without a barrier; use --model crsp")
    try:
        law = (read_block_survey(args.volumes_csv, cal.rock_density_kg_m3) if args.volumes_csv
               else parse_volume_law(args.volume_law) if args.volume_law else None)
        edges = (None if args.volume_classes_m3 is None
                 else parse_floats(args.volume_classes_m3, "--volume-classes-m3"))
        classes = None if law is None else volume_classes(law, edges)
    except (BlockSurveyError, ValueError) as exc:
        raise CliError(str(exc)) from None
    record = {}
    nan = math.nan
    # the errors of a given release height or speed: the option, else the
    # calibration's (the site's tracked-release errors its fit drew with)
    h_sd, v_sd = (given if given is not None else (fitted if mean is not None else 0.0)
                  for given, fitted, mean in (
                      (args.release_height_sd_m, cal.release_height_sd_m, args.release_height_m),
                      (args.release_speed_sd_m_s, cal.release_speed_sd_m_s,
                       args.release_speed_m_s)))
    state = ReleaseState(nan if args.release_height_m is None else args.release_height_m, h_sd,
                         nan if args.release_speed_m_s is None else args.release_speed_m_s, v_sd)
    shapes = _shapes(args, cal, len(sizes) if law is None else len(classes))
    seeder = None
    if law is not None or zone is not None or any(
            v is not None for v in (args.release_height_m, args.release_speed_m_s)):
        zone = zone or ReleaseZone("point", (float(release_x),))
        seeder = (Seeder(law, tuple(classes), zone, state, shapes) if law is not None
                  else Seeder.fixed_sizes(sizes, zone, state, shapes))
        if args.return_period_yr is not None:
            try:
                v_t = law.return_period_volume_m3(args.return_period_yr,
                                                  args.release_rate_per_year)
            except ValueError as exc:
                raise CliError(f"--return-period-yr: {exc}") from None
            t = next(i for i, c in enumerate(seeder.classes) if v_t < c.volume_max_m3
                     or i == len(seeder.classes) - 1)
            record["design_block_json"] = json_ready({
                "return_period_yr": args.return_period_yr,
                "rate_per_year": args.release_rate_per_year, "volume_m3": v_t,
                "block_size_m": float(diameter_m(v_t)), "volume_class": seeder.classes[t].label,
                "class_block_size_m": seeder.classes[t].size_m,
                "rule": "R (1 - F(V_T)) = 1 / T (calib.model.release; after De Biagi et al. "
                        "2017, NHESS 17:103)"})
    barrier = None
    if args.barrier_x_m is not None:
        lo, hi = profile.x_range_m
        x = args.barrier_x_m
        if not lo <= x <= hi:
            raise CliError(f"--barrier-x-m {x:g}: outside the profile [{lo:g}, {hi:g}] m")
        if x <= release_x:
            raise CliError(f"--barrier-x-m {x:g}: at or above the release at x = "
                           f"{release_x:g} m: blocks start below it")
        inf = math.inf
        barrier = Barrier(x, inf if args.barrier_height_m is None else args.barrier_height_m,
                          inf if args.barrier_capacity_kJ is None else args.barrier_capacity_kJ)
    return _Conditions(seeder, barrier, fitted_block_sizes_m(cal), record, shapes)


if __name__ == "__main__":
    sys.exit(main())
