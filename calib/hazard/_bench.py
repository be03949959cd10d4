"""Hazard pipeline throughput vs the bare CRSP solver:
``python -m calib.hazard._bench --profile data/postignano_profile.csv [--n 16384]
[--draws 2]``.

Both runs use the same work: 4 block sizes (0.2, 0.5, 1, 2 m) x ``n`` blocks as
tasks of one CRSP lane pool (``--pool`` lanes), Kn 0.41, Kt 0.87, roughness 2 m
(the seed paper's set, Sect. 4.1), stations every 5 m along ``--profile``
(61 on the Postignano profile, 0 to 300 m, where the figures in README.md
were measured).

* solver: ``solvers.crsp.simulate_tasks`` returning per-block results;
* pipeline: ``calib.hazard.run_hazard`` with ``draws`` draws of the point
  estimate (chunks of ``n`` blocks per size: the same compiled pool plus the
  on-device reduction, device dispatch and host accumulation).

Each is timed after a warm-up call with the same shapes (compile excluded);
the load average is printed next to the figures, because other processes share
the CPU. A benchmark, not a test: it asserts nothing.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from calib.files.calibration_file import draw_parameters, load_calibration
from calib.hazard._run import run_hazard
from calib.model.entries import crsp_radius_m
from calib.model.forward import stack_trees
from solvers import ProfileError, crsp, load_profile
from solvers.cli import OneLineParser

SIZES_M = (0.2, 0.5, 1.0, 2.0)


def _calibration_file(folder: str, profile_csv: str) -> str:
    import json

    point = {"map": 0.0, "mean": 0.0, "q05": 0.0, "q95": 0.0}
    doc = {"schema": "rockfall-calibration/1", "profile_csv": os.path.abspath(profile_csv),
           "crsp": {"Kn": dict(point, map=0.41), "Kt": dict(point, map=0.87),
                    "roughness_m": dict(point, map=2.0), "posterior_csv": None}}
    path = os.path.join(folder, "calibration.json")
    with open(path, "w") as fh:
        json.dump(doc, fh)
    return path


def main(argv=None) -> int:
    p = OneLineParser(prog="python -m calib.hazard._bench", description=__doc__.split("\n\n")[0],
                      epilog="Example: python -m calib.hazard._bench "
                             "--profile data/postignano_profile.csv --n 4096")
    p.add_argument("--profile", required=True,
                   help="slope profile CSV (its materials CSV next to it), e.g. "
                        "data/postignano_profile.csv")
    p.add_argument("--n", type=int, default=16384, help="blocks per size and draw (default 16384)")
    p.add_argument("--draws", type=int, default=2, help="draws in the pipeline run (default 2)")
    p.add_argument("--pool", type=int, default=None,
                   help="CRSP lanes (default: solvers.crsp.default_pool(), 256 on a CPU)")
    args = p.parse_args(argv)
    if args.pool is None:
        args.pool = crsp.default_pool()
    try:
        profile = load_profile(args.profile)
    except ProfileError as e:
        p.error(str(e))
    lo, hi = profile.x_range_m
    stations = np.arange(lo, hi + 1e-9, 5.0)
    params = crsp.params_from_profile(profile, Kn=0.41, Kt=0.87, roughness_m=2.0)
    stack = stack_trees
    ps = stack([params] * len(SIZES_M))
    bs = stack([crsp.make_block(float(r)) for r in crsp_radius_m(SIZES_M)])
    st = jnp.asarray(stations)

    def solver(key):
        return jax.block_until_ready(crsp.simulate_tasks(ps, bs, key, profile, st,
                                                         n_per_task=args.n, pool=args.pool))

    print(f"pool {args.pool} lanes; load before: {os.getloadavg()[0]:.2f}", flush=True)
    solver(jax.random.key(1))
    t0 = time.perf_counter()
    res = solver(jax.random.key(2))
    t_solver = time.perf_counter() - t0
    n_solver = len(SIZES_M) * args.n
    mean_events = float(np.mean(res.n_events))
    print(f"solver (simulate_tasks, per-block output): {n_solver} blocks in {t_solver:.1f} s = "
          f"{n_solver / t_solver:,.0f} blocks/s; mean events/block {mean_events:.0f}; "
          f"load {os.getloadavg()[0]:.2f}", flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        cal = load_calibration(_calibration_file(tmp, args.profile), "crsp")

    def pipeline(n_draws, seed):
        draws = draw_parameters(cal, n_draws, seed)
        return run_hazard(cal, draws, profile, SIZES_M, stations, args.n, seed,
                          chunk_blocks=args.n, pool=args.pool)

    pipeline(1, 1)
    t0 = time.perf_counter()
    pipeline(args.draws, 2)
    t_pipe = time.perf_counter() - t0
    n_pipe = args.draws * len(SIZES_M) * args.n
    rate = n_pipe / t_pipe
    print(f"pipeline (run_hazard, {args.draws} draws): {n_pipe} blocks in {t_pipe:.1f} s = "
          f"{rate:,.0f} blocks/s ({rate / (n_solver / t_solver):.2f} x the solver's rate); "
          f"load {os.getloadavg()[0]:.2f}", flush=True)
    print(f"projected default CRSP run (100 draws x 4 sizes x 2e4 = 8e6 blocks): "
          f"{8e6 / rate / 60:.0f} min at this rate (target < 5 min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
