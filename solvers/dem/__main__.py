"""Command line: ``python -m solvers.dem --profile data/postignano_profile.csv
--block-size-m 0.9 --n-blocks 256 --alpha 0.43 --seed 0 --out dem.csv``.

The block size is the diameter d (``--block-size-m``); the DEM block is a
square of side L = d (split into n x n fragments with ``--fragments``).

Writes one row per fragment of each block, in the schema of ``python -m
solvers.crsp`` (``solvers.cli.RUN_COLUMNS``): block, fragment, block_size_m,
status (the fragment's), runout_m, stop_x_m, stop_z_m; then n_steps; then per
station x passed_<x>m, energy_kJ_per_m_<x>m (kJ per metre of block width: the
DEM is 2D, never to be mixed with the CRSP's kJ per block), velocity_m_s_<x>m,
bounce_height_m_<x>m (``solvers.cli.station_columns``); and prints one summary
line. Blocks run in batches of ``--batch-size`` (a progress bar on stderr,
``--no-progress`` to turn it off); block i uses the key fold_in(key(seed), i),
so results do not depend on the batch size. Bad arguments: one line on stderr,
exit status 2.

Deprecated names kept one release (``solvers.cli.deprecated_alias``):
``--stations`` (now ``--stations-m``) and ``--alpha-law`` (now
``--alpha-law-expr``: the DEM command takes the law as an expression of L,
where ``calib.fit --alpha-law`` chooses the form the fit calibrates).
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np
from tqdm import tqdm

from solvers.cli import (
    CliError,
    DefaultsHelpFormatter,
    OneLineParser,
    deprecated_alias,
    fail,
    parse_stations,
    run_columns,
    run_columns_help,
    station_columns,
    write_csv_atomic,
)
from solvers.dem._alpha_law import DEFAULT_ALPHA_LAW
from solvers.dem._params import DAMPING_MODES, RUN_STIFFNESS_SCALE, Params, check_run_numerics
from solvers.percentiles import few_blocks_warning
from solvers.status import INVALID, LEFT_PROFILE, STOPPED, finished

# the DEM's own columns of the output CSV, after solvers.cli.RUN_COLUMNS
OWN_COLUMNS = {"n_steps": "time steps the block ran (its fragments share them)"}


class _HelpFormatter(DefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults shown, the output schema of the epilog kept as laid out."""


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="python -m solvers.dem",
                      description="Rigid-block DEM rockfall runs (UDEC-style) on a 2D profile.",
                      formatter_class=_HelpFormatter,
                      epilog=run_columns_help(OWN_COLUMNS, energy_per_m=True))
    p.add_argument("--profile", required=True, help="profile CSV (x_m,z_m,zone)")
    p.add_argument("--materials", default=None,
                   help="materials CSV (default: <site>_materials.csv next to "
                        "<site>_profile.csv)")
    p.add_argument("--block-size-m", type=float, required=True,
                   help="block size d, the diameter, m; the DEM block is a square of side "
                        "L = d")
    p.add_argument("--n-blocks", type=int, default=256, help="blocks to release")
    p.add_argument("--batch-size", type=int, default=256,
                   help="blocks per vmapped batch (memory / progress granularity only)")
    p.add_argument("--alpha", type=float, default=None,
                   help="local damping for every fragment (default: from --alpha-law-expr)")
    p.add_argument("--alpha-law-expr", default=None, metavar="EXPR",
                   help="alpha as an expression of the fragment side L, m, e.g. "
                        "'0.9*L**-0.4' (numbers, L, + - * / **, exp, log, sqrt, minimum, "
                        "maximum; solvers.dem.parse_alpha_law). "
                        "Not calib.fit's --alpha-law, which chooses the form (power or "
                        f'constant) a fit calibrates (default: "{DEFAULT_ALPHA_LAW}")')
    deprecated_alias(p, "--alpha-law", "--alpha-law-expr")
    p.add_argument("--fragments", type=int, default=1, help="1, 4, 16, 64, ... (n x n)")
    p.add_argument("--damping", choices=list(DAMPING_MODES), default="unbalanced",
                   help="unbalanced: Cundall local damping of the whole unbalanced force, "
                        "gravity included (UDEC, the paper); contact: local damping of the "
                        "contact forces only; viscous: no local damping, a dashpot at every "
                        "contact set from --restitution")
    p.add_argument("--restitution", type=float, default=None,
                   help="viscous mode: target normal restitution e in (0, 1] of the "
                        "dashpots (default: e = sqrt((1 - alpha) / (1 + alpha)) per fragment)")
    p.add_argument("--stiffness-scale", type=float, default=RUN_STIFFNESS_SCALE,
                   help="multiply kn = ks = 50 GPa/m (the paper's UDEC stiffness) by this, in "
                        "(0, 1]; joint strengths are scaled by its square root. Default "
                        f"{RUN_STIFFNESS_SCALE:g}, the value the calibration and calib.hazard "
                        "run with (solvers.dem.RUN_STIFFNESS_SCALE), so that this command "
                        "simulates a calibrated alpha as the fit did: the time step is 10x the "
                        "paper's, and runouts matched the paper's stiffness within Monte Carlo "
                        "noise "
                        "(scripts/dem_reproduce.py). 1: the paper's stiffness")
    p.add_argument("--density-kg-m3", type=float, default=Params._field_defaults["rho"],
                   help="rock density, kg/m^3 (the seed paper's, Sect. 4.1)")
    p.add_argument("--smooth", action="store_true", help="softplus contact, tanh signs")
    p.add_argument("--max-time-s", type=float, default=200.0, help="simulated-time bound, s")
    p.add_argument("--stations-m", default=None,
                   help='station abscissae, m: "110,230" or a:b:step (default: none)')
    deprecated_alias(p, "--stations", "--stations-m")
    p.add_argument("--release-x-m", type=float, default=None,
                   help="release abscissa, m (default: the first profile vertex)")
    p.add_argument("--seed", type=int, default=0, help="seed of the release keys")
    p.add_argument("--out", required=True, help="output CSV")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _check(args) -> None:
    if not (math.isfinite(args.block_size_m) and args.block_size_m > 0):
        raise CliError(f"--block-size-m: expected a positive size in m, got {args.block_size_m}")
    if args.n_blocks < 1:
        raise CliError(f"--n-blocks: expected at least 1, got {args.n_blocks}")
    if args.batch_size < 1:
        raise CliError(f"--batch-size: expected at least 1, got {args.batch_size}")
    if args.restitution is not None:
        if args.damping != "viscous":
            raise CliError("--restitution: only used with --damping viscous")
        if not (math.isfinite(args.restitution) and 0.0 < args.restitution <= 1.0):
            raise CliError(f"--restitution: expected a value in (0, 1], got {args.restitution}")
    n = math.isqrt(max(args.fragments, 0))
    if args.fragments < 1 or n * n != args.fragments:
        raise CliError(f"--fragments: expected a perfect square (1, 4, 16, 64), got "
                       f"{args.fragments}")
    if args.alpha is not None and args.alpha_law_expr is not None:
        raise CliError("--alpha and --alpha-law-expr are exclusive; give one")
    if not (math.isfinite(args.density_kg_m3) and args.density_kg_m3 > 0):
        raise CliError(f"--density-kg-m3: expected a positive density, got "
                       f"{args.density_kg_m3:g}")
    if args.alpha is not None and not (0.0 <= args.alpha < 1.0):
        raise CliError(f"--alpha: local damping must lie in [0, 1), got {args.alpha}")
    try:
        check_run_numerics(args.stiffness_scale, args.max_time_s,
                           {"stiffness_scale": "--stiffness-scale", "max_time_s": "--max-time-s"})
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _fragment_status(block_status, exited, stopped):
    """(N F,) status of each fragment from the blocks' (N,) status and the
    fragments' (N, F) flags: INVALID for every fragment of an invalid block,
    else LEFT_PROFILE for a fragment that passed the profile's end, STOPPED for
    one at rest in a finished block, else the block's (BUDGET)."""
    block = np.broadcast_to(block_status[:, None], exited.shape)
    return np.where(block == INVALID, INVALID,
                    np.where(exited, LEFT_PROFILE, np.where(stopped, STOPPED, block))).ravel()


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    prog = parser.prog
    try:
        _check(args)
        import jax
        import pandas as pd

        from solvers.dem import (
            AlphaLawError,
            Options,
            make_block,
            make_params,
            max_steps_for,
            stable_dt,
        )
        from solvers.dem._integrate import simulate_batch
        from solvers.profile import ProfileError, load_profile

        try:
            profile = load_profile(args.profile, args.materials)
            stations = parse_stations(args.stations_m, profile.x_range_m)
            release = profile.x_range_m[0] if args.release_x_m is None else args.release_x_m
            block = make_block(args.block_size_m, alpha=args.alpha, alpha_law=args.alpha_law_expr,
                               n_fragments=args.fragments, release_x_m=release,
                               stations=stations)
        except (ProfileError, AlphaLawError, ValueError) as exc:
            raise CliError(str(exc)) from None
    except CliError as exc:
        fail(prog, str(exc))
    params = make_params(profile, damping=args.damping, restitution=args.restitution,
                         stiffness_scale=args.stiffness_scale, rho=args.density_kg_m3)
    dt = float(stable_dt(params, block))
    options = Options(max_steps=max_steps_for(args.max_time_s, params, block),
                      smooth=args.smooth)
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(args.seed), i))(
        np.arange(args.n_blocks))
    t0 = time.perf_counter()
    parts = []
    starts = range(0, args.n_blocks, args.batch_size)
    bar = tqdm(total=args.n_blocks, desc="DEM", unit="block", disable=args.no_progress,
               file=sys.stderr)
    for a in starts:
        parts.append(jax.block_until_ready(
            simulate_batch(params, block, keys[a:a + args.batch_size], options)))
        bar.update(len(keys[a:a + args.batch_size]))
    bar.close()
    res = jax.tree.map(lambda *x: np.concatenate([np.asarray(v) for v in x]), *parts)
    wall = time.perf_counter() - t0
    n_frag = block.n_fragments
    status = _fragment_status(np.asarray(res.status), np.asarray(res.exited),
                              np.asarray(res.stopped))
    rows = run_columns(args.block_size_m, status, res.runout_m, res.stop_x_m, res.stop_z_m,
                       n_fragments=n_frag)
    rows["n_steps"] = np.repeat(np.asarray(res.n_steps), n_frag)
    # the 2D DEM's energies are per metre of block width (plane strain)
    rows.update(station_columns(stations, res.stations, energy_per_m=True))
    df = pd.DataFrame(rows)
    write_csv_atomic(df, args.out)
    n_done = int(np.sum(finished(np.asarray(res.status))))  # blocks; fragments share one
    ro = df["runout_m"].to_numpy()[finished(np.repeat(np.asarray(res.status), n_frag))]
    stats = (f"runout median {np.median(ro):.1f} m (p5 {np.percentile(ro, 5):.1f}, "
             f"p95 {np.percentile(ro, 95):.1f}) of the {n_done} finished block(s)"
             if ro.size else "no block finished")
    steps = int(np.sum(res.n_steps))
    print(f"dem: {args.n_blocks} block(s) x {n_frag} fragment(s), L={args.block_size_m:g} m, "
          f"alpha={float(block.alpha[0]):.3f}, damping={args.damping}, dt={dt:.3g} s; "
          f"{stats}; fragments: stopped {int(np.sum(status == STOPPED))}/{len(df)}, "
          f"left profile {int(np.sum(status == LEFT_PROFILE))}, not finished "
          f"{int(np.sum(~finished(status)))}; {steps} block-steps in {wall:.1f} s "
          f"({steps / wall:.3g}/s) -> {args.out}")
    warning = few_blocks_warning([("runout", n_done)] if n_done else [])
    if warning:
        print(warning, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
