"""Throughput benchmarks: ``python -m solvers.bench [--json] [--quick]``.

CRSP: the Postignano scenario (sphere r = 0.5 m, Kn 0.41, Kt 0.87, roughness
2 m) at N = 1e3, 1e4, 1e5 blocks; blocks per second (compiled, steady state) and
the compile time, reported separately; peak resident memory after each N.
Optionally a side-by-side run of PyRockfall 0.1.2 at N = 1e3 (roughness 0, the
setting where it is valid) from its own virtual environment, never a project
dependency: ``--pyrockfall-python .bench-venv/bin/python``.

DEM: figures from ``solvers.dem._bench.run_benchmarks`` when the DEM is present.

A benchmark, not a test: it asserts nothing; compare runs of the same command.
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
from solvers._cli import OneLineParser

PROFILE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                       "data", "postignano_profile.csv")


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def crsp_throughput(n_blocks: int, roughness_m: float = 2.0, radius_m: float = 0.5,
                    seed: int = 0) -> dict:
    """Compile time and steady-state blocks/s for one N (the run is repeated
    after a warm-up call on the same chunk shape)."""
    prof = load_profile(PROFILE).with_materials(Kn=0.41, Kt=0.87, roughness_m=roughness_m)
    params = crsp.params_from_profile(prof)
    block = crsp.make_block(radius_m)
    key = jax.random.key(seed)
    chunk = min(16384, n_blocks)
    t0 = time.perf_counter()
    warm = crsp.run_blocks(params, block, jax.random.key(seed + 1), chunk, prof,
                           chunk_size=chunk)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    crsp.run_blocks(params, block, jax.random.key(seed + 1), chunk, prof, chunk_size=chunk)
    second = time.perf_counter() - t0
    del warm
    t0 = time.perf_counter()
    res = crsp.run_blocks(params, block, key, n_blocks, prof, chunk_size=chunk)
    wall = time.perf_counter() - t0
    return {
        "n": n_blocks,
        "blocks_per_s": n_blocks / wall,
        "wall_s": wall,
        "compile_s": max(first - second, 0.0),
        "median_runout_m": float(np.median(res.runout_m)),
        "mean_events": float(res.n_events.mean()),
        "max_events": int(res.n_events.max()),
        "stopped_fraction": float(res.stopped.mean()),
        "peak_rss_mb": _peak_rss_mb(),
    }


def pyrockfall_anchor(python: str, n_blocks: int = 1000) -> dict:
    script = os.path.join(os.path.dirname(PROFILE), "..", "scripts", "pyrockfall_anchor.py")
    cmd = [python, script, "--profile", PROFILE, "--n", str(n_blocks), "--radius-m", "0.5",
           "--Kn", "0.41", "--Kt", "0.87", "--roughness-m", "0", "--seed", "0"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = OneLineParser(prog="python -m solvers.bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true", help="N = 1e3 and 1e4 only, quick DEM")
    p.add_argument("--pyrockfall-python", help="python of a venv with pyrockfall 0.1.2 "
                   "(default: .bench-venv/bin/python if it exists)")
    p.add_argument("--no-dem", action="store_true", help="skip the DEM benchmarks")
    args = p.parse_args(argv)

    sizes = [1000, 10000] if args.quick else [1000, 10000, 100000]
    rows = [crsp_throughput(n) for n in sizes]
    out = {
        "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(),
        "crsp_blocks_per_s": {str(r["n"]): round(r["blocks_per_s"], 1) for r in rows},
        "crsp_compile_s": round(max(r["compile_s"] for r in rows), 3),
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
            from solvers.dem._bench import run_benchmarks
        except ImportError as exc:
            out["dem"] = {"error": f"DEM benchmark unavailable: {exc}"}
        else:
            out["dem"] = run_benchmarks(quick=args.quick)

    if args.json:
        print(json.dumps(out, indent=1, default=float))
        return 0
    print(f"device: {out['device']}, {out['cpu_count']} CPU cores")
    print(f"{'N':>8} {'blocks/s':>12} {'wall s':>8} {'compile s':>10} {'mean ev':>8} "
          f"{'max ev':>7} {'median m':>9} {'RSS MB':>8}")
    for r in rows:
        print(f"{r['n']:>8} {r['blocks_per_s']:>12,.0f} {r['wall_s']:>8.2f} "
              f"{r['compile_s']:>10.2f} {r['mean_events']:>8.1f} {r['max_events']:>7} "
              f"{r['median_runout_m']:>9.1f} {r['peak_rss_mb']:>8.0f}")
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
