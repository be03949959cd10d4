#!/usr/bin/env python3
"""Anchor measurement: PyRockfall's CRSP-type model on one of our 2D profiles.

PyRockfall (GPL-3.0, https://github.com/gbarros92/PyRockfall) is a vectorised
NumPy rockfall code. It is NOT a dependency of this project: this standalone
script drives it through its public classes only, and is meant to be run with
the separate benchmark virtual environment::

    python3 -m venv .bench-venv && .bench-venv/bin/pip install pyrockfall==0.1.2
    .bench-venv/bin/python scripts/pyrockfall_anchor.py \\
        --profile data/postignano_profile.csv --n 1000 --block-size-m 1.0 \\
        --Kn 0.41 --Kt 0.87 --roughness-m 0 --seed 0

It prints ONE line of JSON on stdout::

    {"tool": "pyrockfall", "version": ..., "n": ..., "wall_s": ...,
     "rocks_per_s": ..., "median_runout_m": ..., "n_not_stopped": ...}

Set-up, mapped onto our conventions (solvers.crsp):

* Slope: the profile CSV (``x_m,z_m,zone``; the zone on row i names the segment
  from vertex i to i+1). One PyRockfall Material per zone, but every zone gets
  the CLI's Kn (normalRestitution), Kt (tangentialRestitution), roughness and
  ``--friction-deg`` (PyRockfall's Coulomb angle for its sliding phase).
* Model: ``considerRotationalVelocity = True`` (CRSP friction function and
  scaling factor with 6.096 and 76.2 m/s) and ``scaleByVelocity = True`` (CRSP
  normal scaling with K = 9.144 m/s). ``maxIter`` is raised (``--max-iter``,
  default 10000) so that rocks can come to rest; everything else (0.1 m/s
  normal-velocity threshold, 0.01 s sliding step, point contact) is PyRockfall's
  default.
* Rock: a sphere of diameter ``--block-size-m`` (radius r = d/2); PyRockfall
  derives r from mass and density, so mass = density * 4/3 pi r^3 (only r
  enters the impact law).
* Release: one point seeder at the first profile vertex (x = 0 m on Postignano),
  on the ground, velocity (``--release-vx-m-s``, 0) m/s, no spin.
* Roughness: PyRockfall tilts the impact normal by an angle (degrees) drawn from
  the material's roughness distribution. CRSP roughness S (m) is mapped to
  Uniform(0, degrees(arctan(S / r))), i.e. our ``roughness_tilt`` range; a
  positive angle turns the normal counter-clockwise, which faces a rock moving
  towards +x (our model picks the side from the rock's direction).
* Runout: final x minus release x, over all N rocks (as ``Result.runout_m``).
  A rock counts as not stopped when it ends faster than ``--stop-speed-m-s`` m/s
  (iteration bound hit, or PyRockfall dropped it when it found no next
  impact) or outside the profile's x range (flew off an end onto PyRockfall's
  floor) or more than one radius below the ground (passed through the slope).
* Timing: wall time of PyRockfall's preprocess + process + postprocess (what
  ``Analysis.run`` calls: sampling, the event loop, and packing of the stored
  trajectories); imports and object set-up are not timed.

PyRockfall keeps every iteration of every rock in memory (8 float64 per rock
per iteration), so memory grows as N x iterations.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time

PROG = "pyrockfall_anchor"


def fail(message: str) -> None:
    sys.stderr.write(f"{PROG}: error: {' '.join(str(message).split())}\n")
    raise SystemExit(2)


class OneLineParser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse API
        fail(message)


def parse_args(argv=None) -> argparse.Namespace:
    p = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--profile", required=True, help="profile CSV with columns x_m,z_m,zone")
    p.add_argument("--n", type=int, required=True, help="number of rocks")
    p.add_argument("--block-size-m", type=float, required=True,
                   help="block size d, the sphere's diameter, m (radius d/2)")
    p.add_argument("--Kn", type=float, required=True, help="normal restitution (all segments)")
    p.add_argument("--Kt", type=float, required=True, help="tangential restitution (all segments)")
    p.add_argument("--roughness-m", type=float, default=0.0,
                   help="CRSP roughness S, m (all segments); mapped to a tilt in "
                        "Uniform(0, arctan(S/r))")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--friction-deg", type=float, default=30.0,
                   help="PyRockfall sliding friction angle, degrees (default 30, the "
                        "rolling_friction_deg of data/postignano_materials.csv)")
    p.add_argument("--density-kg-m3", type=float, default=2350.0,
                   help="rock density, kg/m^3 (default 2350)")
    p.add_argument("--release-vx-m-s", type=float, default=1.0,
                   help="initial horizontal velocity, m/s (default 1)")
    p.add_argument("--max-iter", type=int, default=10000,
                   help="PyRockfall Analysis.maxIter (its own default, 1000, is too few: a "
                        "rock sliding in 0.01 s steps needs ~1100 on Postignano). The loop "
                        "ends when all rocks are done; memory grows with the iterations run")
    p.add_argument("--mem-limit-gb", type=float, default=5.0,
                   help="refuse to start if the worst-case trajectory storage "
                        "(~128 B x N x max-iter) exceeds this, GB")
    p.add_argument("--stop-speed-m-s", type=float, default=1e-3,
                   help="final speed above which a rock counts as not stopped, m/s")
    p.add_argument("--verbose", action="store_true",
                   help="print a diagnostic line (iterations, peak memory) on stderr")
    a = p.parse_args(argv)
    checks = [
        (a.n > 0, f"--n must be positive, got {a.n}"),
        (a.block_size_m > 0 and math.isfinite(a.block_size_m), "--block-size-m must be positive"),
        (0 < a.Kn <= 1, f"--Kn must be in (0, 1], got {a.Kn}"),
        (0 < a.Kt <= 1, f"--Kt must be in (0, 1], got {a.Kt}"),
        (a.roughness_m >= 0 and math.isfinite(a.roughness_m), "--roughness-m must be >= 0"),
        (0 <= a.friction_deg < 90, "--friction-deg must be in [0, 90)"),
        (a.density_kg_m3 > 0, "--density-kg-m3 must be positive"),
        (math.isfinite(a.release_vx_m_s), "--release-vx-m-s must be finite"),
        (a.max_iter > 0, "--max-iter must be positive"),
        (a.stop_speed_m_s > 0, "--stop-speed-m-s must be positive"),
        (a.mem_limit_gb > 0, "--mem-limit-gb must be positive"),
    ]
    for ok, msg in checks:
        if not ok:
            fail(msg)
    # PyRockfall stores 8 float64 per rock per iteration, and its postprocess
    # stacks the lists into arrays (a second copy): ~128 B per rock-iteration.
    worst_gb = 128.0 * a.n * a.max_iter / 1e9
    if worst_gb > a.mem_limit_gb:
        fail(f"--n {a.n} with --max-iter {a.max_iter} may need up to {worst_gb:.1f} GB of "
             f"trajectory storage (> --mem-limit-gb {a.mem_limit_gb:g}); lower --max-iter "
             f"or --n, or raise --mem-limit-gb")
    return a


def read_profile(path: str):
    """Return (x list, z list, zone-per-segment list); errors name file and line."""
    if not os.path.isfile(path):
        fail(f"{path}: no such file")
    xs, zs, zones = [], [], []
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        need = ("x_m", "z_m", "zone")
        if reader.fieldnames is None or any(c not in reader.fieldnames for c in need):
            fail(f"{path}: header must contain columns {','.join(need)}, got {reader.fieldnames}")
        for row in reader:
            line = reader.line_num
            try:
                x, z = float(row["x_m"]), float(row["z_m"])
            except (TypeError, ValueError):
                fail(f"{path}:{line}: x_m and z_m must be numbers")
            if not (math.isfinite(x) and math.isfinite(z)):
                fail(f"{path}:{line}: x_m and z_m must be finite")
            if xs and x <= xs[-1]:
                fail(f"{path}:{line}: x_m must increase strictly")
            xs.append(x)
            zs.append(z)
            zones.append((row["zone"] or "").strip())
    if len(xs) < 2:
        fail(f"{path}: need at least two vertices")
    seg_zones = zones[:-1]  # last row's zone names no segment
    for i, name in enumerate(seg_zones):
        if not name:
            fail(f"{path}:{i + 2}: empty zone for the segment starting on this row")
    return xs, zs, seg_zones


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        import numpy as np
        import pyrockfall as prf
    except ImportError as exc:  # incl. a broken install of one of its dependencies
        fail(f"pyrockfall is not importable ({exc}); run this script with the bench venv "
             f"(python3 -m venv .bench-venv && .bench-venv/bin/pip install pyrockfall==0.1.2)")
    try:
        from importlib.metadata import version
        prf_version = version("pyrockfall")
    except Exception:
        prf_version = getattr(prf, "__version__", "unknown")

    xs, zs, seg_zones = read_profile(args.profile)
    np.random.seed(args.seed)  # roughness draws use NumPy's global generator

    # ---- slope: one material per zone, all with the CLI's constants ----
    if args.roughness_m > 0:
        tilt_max_deg = math.degrees(math.atan2(args.roughness_m, 0.5 * args.block_size_m))
        roughness = prf.stats.Uniform(0.0, tilt_max_deg)
    else:
        tilt_max_deg = 0.0
        roughness = 0.0
    zone_names = list(dict.fromkeys(seg_zones))
    materials = [prf.Material(name, normalRestitution=args.Kn, tangentialRestitution=args.Kt,
                              frictionAngle=args.friction_deg, roughness=roughness)
                 for name in zone_names]
    material_ids = [zone_names.index(z) for z in seg_zones]
    nodes = np.column_stack([np.asarray(xs, float), np.asarray(zs, float)])
    slope = prf.Slope(prf.Geometry(nodes), materials, materialIDs=material_ids)

    # ---- rock and release ----
    mass = args.density_kg_m3 * 4.0 / 3.0 * math.pi * (0.5 * args.block_size_m) ** 3
    rock = prf.Rock("sphere", mass=mass, density=args.density_kg_m3)
    x0, z0 = xs[0], zs[0]
    seeder = prf.Seeder(np.array([x0, z0]), [rock], name="cliff top")
    seeder.numberOfRocks = args.n
    seeder.translationalVelocity = [args.release_vx_m_s, 0.0]
    seeder.angularVelocity = 0.0

    # ---- analysis: CRSP-type impacts ----
    an = prf.Analysis()
    an.slope = slope
    an.seeders = [seeder]
    an.rockThrowMode = prf.AnalysisRocksThrown.IndividuallyPerSeeder
    an.useSpecificSeed = True
    an.specificSeed = args.seed
    an.considerRotationalVelocity = True  # A = 6.096, B = 76.2 m/s
    an.scaleByVelocity = True  # K = 9.144 m/s
    an.maxIter = args.max_iter
    if not (an.A == 6.096 and an.B == 76.2 and an.K == 9.144):
        fail(f"unexpected PyRockfall constants A={an.A} B={an.B} K={an.K}")

    t0 = time.perf_counter()
    state = an.preprocess()
    state = an.process(*state)
    an.postprocess(state[3])
    wall_s = time.perf_counter() - t0

    position, velocity = state[0], state[1]
    x_end = position[0]
    if x_end.shape[0] != args.n:
        fail(f"PyRockfall simulated {x_end.shape[0]} rocks, expected {args.n}")
    speed = np.hypot(velocity[0], velocity[1])
    moving = ~(speed <= args.stop_speed_m_s)  # NaN counts as moving
    off_profile = (x_end < xs[0] - 1e-6) | (x_end > xs[-1] + 1e-6) | ~np.isfinite(x_end)
    # rocks that ended well below the ground passed through the slope (seen with
    # large roughness tilts): not a stop either
    z_ground = np.interp(x_end, xs, zs)
    tunnelled = ~off_profile & (position[1] < z_ground - 0.5 * args.block_size_m)
    not_stopped = moving | off_profile | tunnelled
    runout = x_end - x0

    out = {
        "tool": "pyrockfall",
        "version": prf_version,
        "n": int(args.n),
        "wall_s": round(wall_s, 4),
        "rocks_per_s": round(args.n / wall_s, 2) if wall_s > 0 else None,
        "median_runout_m": round(float(np.nanmedian(runout)), 3),
        "n_not_stopped": int(np.count_nonzero(not_stopped)),
    }
    print(json.dumps(out), flush=True)

    if args.verbose:
        import resource
        n_iter = an.trajectories.timeHistory.shape[0]
        rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        sys.stderr.write(
            f"{PROG}: iterations={n_iter} max_iter={args.max_iter} "
            f"moving_at_end={int(np.count_nonzero(moving))} "
            f"off_profile={int(np.count_nonzero(off_profile))} "
            f"below_ground={int(np.count_nonzero(tunnelled))} "
            f"tilt_max_deg={tilt_max_deg:.2f} mass_kg={mass:.1f} "
            f"runout_p10/p50/p90_m={np.nanpercentile(runout, 10):.2f}/"
            f"{np.nanpercentile(runout, 50):.2f}/{np.nanpercentile(runout, 90):.2f} "
            f"peak_rss_mb={rss_mb:.0f}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
