"""Throughput benchmarks: ``python -m solvers.bench [--json] [--quick]``.

CRSP: the Postignano profile, Kn 0.41, Kt 0.87, roughness S = 2 m,
spheres of diameter 0.2, 0.5, 1 and 2 m, N = 1e5 blocks each, without stations
and with 61 stations (every 5 m from 0 to 300 m): blocks per second (compiled,
steady state: a warm-up call on the same chunk shape first), mean and maximum
events per block, median runout, status counts and peak resident memory.
``--quick`` runs N = 1e4. Optionally a side-by-side run of PyRockfall 0.1.2 at
N = 1e3 (roughness 0, the setting where it is valid) from its own virtual
environment, never a project dependency: ``--pyrockfall-python
.bench-venv/bin/python``.

DEM: figures from ``solvers.dem.bench.run_benchmarks`` when the DEM is present.

A benchmark, not a test: it asserts nothing; compare runs of the same command.
Targets (the project's specification, 2 CPU cores): >= 100,000 blocks/s for
1 m blocks and >= 50,000 for 0.2 m blocks, with stations.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time

import jax
import numpy as np

from solvers import crsp, load_profile
from solvers.cli import CliError, OneLineParser, run_guarded
from solvers.parallel import default_workers
from solvers.status import status_counts

PROFILE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                       "data", "postignano_profile.csv")


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


BENCH_DIAMETERS_M = (0.2, 0.5, 1.0, 2.0)
BENCH_STATIONS_M = tuple(float(x) for x in np.arange(0.0, 300.0 + 1e-9, 5.0))  # 61


def crsp_throughput(n_blocks: int, roughness_m: float = 2.0, radius_m: float = 0.5,
                    seed: int = 0, stations_x_m=None, pool: int | None = None,
                    workers: int | None = None, repeat: int = 5) -> dict:
    """Compile time and steady-state blocks/s for one N: after two warm-up calls
    on the same chunk shape, the run is timed ``repeat`` times (the first keyed
    ``key(seed)``, run r > 0 ``fold_in(key(seed), r)``; the event and runout
    figures are the first's) and the median wall time gives ``blocks_per_s``,
    the fastest and slowest runs its range (one run of 1e5 blocks lasts about a
    second on 2 cores, and single runs differed by up to 30 %)."""
    prof = load_profile(PROFILE).with_materials(Kn=0.41, Kt=0.87, roughness_m=roughness_m)
    params = crsp.params_from_profile(prof)
    block = crsp.make_block(radius_m)
    key = jax.random.key(seed)
    workers = default_workers() if workers is None else workers
    chunk = 16384
    size, _ = crsp.chunk_plan(n_blocks, chunk, workers)
    kw = {} if pool is None else {"pool": pool}
    kw.update(chunk_size=chunk, workers=workers)
    # warm-up on the run's chunk shape (the same compiled program), twice
    n_warm = min(size * workers, n_blocks)
    t0 = time.perf_counter()
    crsp.run_blocks(params, block, jax.random.key(seed + 1), n_warm, prof,
                    stations_x_m=stations_x_m, **dict(kw, chunk_size=size))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    crsp.run_blocks(params, block, jax.random.key(seed + 1), n_warm, prof,
                    stations_x_m=stations_x_m, **dict(kw, chunk_size=size))
    second = time.perf_counter() - t0
    walls = []
    for r in range(repeat):
        t0 = time.perf_counter()
        res_r = crsp.run_blocks(params, block, jax.random.fold_in(key, r) if r else key,
                                n_blocks, prof, stations_x_m=stations_x_m, **kw)
        walls.append(time.perf_counter() - t0)
        if r == 0:
            res = res_r  # the figures of the run keyed ``seed`` (as before repeats)
    wall = float(np.median(walls))
    return {
        "n": n_blocks,
        "diameter_m": 2.0 * radius_m,
        "stations": 0 if stations_x_m is None else len(stations_x_m),
        "workers": workers,
        "chunk_blocks": size,
        "pool": min(crsp.default_pool() if pool is None else pool, size),
        "blocks_per_s": n_blocks / wall,
        "blocks_per_s_range": (n_blocks / max(walls), n_blocks / min(walls)),
        "repeat": repeat,
        "wall_s": wall,
        "compile_s": max(first - second, 0.0),
        "median_runout_m": float(np.median(res.runout_m)),
        "mean_events": float(res.n_events.mean()),
        "max_events": int(res.n_events.max()),
        "status": status_counts(res.status),
        "peak_rss_mb": _peak_rss_mb(),
    }


def pyrockfall_anchor(python: str, n_blocks: int = 1000) -> dict:
    script = os.path.join(os.path.dirname(PROFILE), "..", "scripts", "pyrockfall_anchor.py")
    cmd = [python, script, "--profile", PROFILE, "--n", str(n_blocks), "--block-size-m", "1.0",
           "--Kn", "0.41", "--Kt", "0.87", "--roughness-m", "0", "--seed", "0"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="python -m solvers.bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true", help="N = 1e4 instead of 1e5, quick DEM")
    p.add_argument("--pool", type=int, default=None,
                   help="lanes of the CRSP pool (default: run_blocks' default)")
    p.add_argument("--pyrockfall-python", help="python of a venv with pyrockfall 0.1.2 "
                   "(default: .bench-venv/bin/python if it exists)")
    p.add_argument("--workers", type=int, default=None,
                   help="threads running CRSP chunks side by side (default: the usable CPU "
                   "cores on the CPU backend, one per device elsewhere)")
    p.add_argument("--no-dem", action="store_true", help="skip the DEM benchmarks")
    p.add_argument("--repeat", type=int, default=5,
                   help="timed runs per CRSP row; blocks/s is their median, the range their "
                        "slowest and fastest (default 5)")
    return p


def main(argv=None) -> int:
    return run_guarded("python -m solvers.bench", _main, argv)


def _main(argv) -> int:
    args = build_parser().parse_args(argv)

    n = 10000 if args.quick else 100000
    if args.workers is not None and args.workers < 1:
        raise CliError(f"--workers: expected a positive number of threads, got {args.workers}")
    if args.repeat < 1:
        raise CliError(f"--repeat: expected a positive number of runs, got {args.repeat}")
    rows = [crsp_throughput(n, radius_m=0.5 * d, stations_x_m=st, pool=args.pool,
                            workers=args.workers, repeat=args.repeat)
            for st in (None, BENCH_STATIONS_M) for d in BENCH_DIAMETERS_M]
    out = {
        "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(),
        "crsp_runs": rows,
    }
    anchor_py = args.pyrockfall_python
    default_venv = os.path.join(os.path.dirname(os.path.dirname(PROFILE)), ".bench-venv",
                                "bin", "python")
    if anchor_py is None and os.path.exists(default_venv):
        anchor_py = default_venv
    if anchor_py:
        ours = crsp_throughput(1000, roughness_m=0.0)
        theirs = pyrockfall_anchor(anchor_py)
        out["pyrockfall_1e3_roughness0"] = theirs
        out["crsp_1e3_roughness0"] = ours
        if "rocks_per_s" in theirs:
            out["speedup_vs_pyrockfall_1e3"] = round(ours["blocks_per_s"] / theirs["rocks_per_s"],
                                                     1)
    if not args.no_dem:
        try:
            from solvers.dem.bench import run_benchmarks
        except ImportError as exc:
            out["dem"] = {"error": f"DEM benchmark unavailable: {exc}"}
        else:
            out["dem"] = run_benchmarks(quick=args.quick)

    if args.json:
        print(json.dumps(out, indent=1, default=float))
        return 0
    print(f"device: {out['device']}, {out['cpu_count']} CPU cores")
    print("CRSP, Postignano profile, Kn 0.41, Kt 0.87, S 2 m (steady state, compile excluded; "
          f"{rows[0]['pool']} lanes per chunk of {rows[0]['chunk_blocks']} blocks; blocks/s: "
          f"median of {rows[0]['repeat']} runs, range: slowest-fastest)")
    print(f"{'N':>7} {'diam m':>6} {'stations':>8} {'workers':>7} {'blocks/s':>10} "
          f"{'range':>17} {'wall s':>7} "
          f"{'compile s':>9} {'mean ev':>7} {'max ev':>6} {'median m':>8} {'unfinished':>10} "
          f"{'RSS MB':>7}")
    for r in rows:
        unfinished = r["status"]["budget"] + r["status"]["invalid"]
        print(f"{r['n']:>7} {r['diameter_m']:>6.1f} {r['stations']:>8} {r['workers']:>7} "
              f"{r['blocks_per_s']:>10,.0f} "
              f"{'{:,.0f}-{:,.0f}'.format(*r['blocks_per_s_range']):>17} "
              f"{r['wall_s']:>7.2f} {r['compile_s']:>9.2f} "
              f"{r['mean_events']:>7.1f} {r['max_events']:>6} {r['median_runout_m']:>8.1f} "
              f"{unfinished:>10} {r['peak_rss_mb']:>7.0f}")
    if "pyrockfall_1e3_roughness0" in out:
        t = out["pyrockfall_1e3_roughness0"]
        o = out["crsp_1e3_roughness0"]
        if "rocks_per_s" in t:
            print(f"PyRockfall 0.1.2, N=1e3, roughness 0: {t['rocks_per_s']:,.0f} rocks/s; "
                  f"this CRSP, same setting: {o['blocks_per_s']:,.0f} blocks/s "
                  f"({out['speedup_vs_pyrockfall_1e3']}x)")
        else:
            print(f"PyRockfall anchor failed: {t['error']}")
    if "dem" in out:
        print("DEM:", json.dumps(out["dem"], default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
