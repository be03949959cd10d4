#!/usr/bin/env python3
"""How often do the DEM fit's 90 % intervals hold the truth on data the DEM made?

For each of ``--n`` data sets: a truth drawn uniformly in a 0.25-0.60, b 0.2-0.9
(alpha(L) = a L^-b; the truths by ``--seed``), 6 blocks of each of 5 sizes
(0.3-2.0 m) simulated on the Postignano profile with sd 3 m (the data keyed
``--data-key`` + i), then the Bayesian stage of ``calibrate`` at the default DEM
budget (the fit's blocks keyed ``--forward-key`` + i, or ``--forward-key`` for
every set with ``--same-design``). One JSON line per set (truth, intervals,
whether each holds the truth, the fit's problems and the expected posterior's
record), then the count. ``tests/test_calib_recovery.py``'s nominal-rate case
is ``--seed 31 --data-key 500 --forward-key 5 --same-design``.

Usage (the figures of docs/studies.md, "Coverage of the DEM posterior")::

    python scripts/dem_coverage.py --seed 32 --data-key 600 --forward-key 50
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

import calib  # noqa: F401  (x64)
from calib.discovery.synthetic import synthesize
from calib.inference.calibrate import calibrate, presets
from calib.model.forward import DemForward
from solvers.profile import load_profile

SIZES_M = np.array([0.3, 0.6, 1.0, 1.5, 2.0])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--n", type=int, default=6, help="data sets")
    p.add_argument("--seed", type=int, default=32, help="seed of the truths")
    p.add_argument("--data-key", type=int, default=600, help="key of data set 0's blocks")
    p.add_argument("--forward-key", type=int, default=50, help="key of fit 0's blocks")
    p.add_argument("--same-design", action="store_true",
                   help="every fit simulates its design with the same blocks")
    p.add_argument("--profile", default="data/postignano_profile.csv")
    args = p.parse_args(argv)
    profile = load_profile(args.profile)
    rng = np.random.default_rng(args.seed)
    budget = presets("dem", quick=False)
    covered = []
    for i in range(args.n):
        truth = np.array([0.25 + 0.35 * rng.random(), 0.2 + 0.7 * rng.random()])
        t0 = time.perf_counter()
        obs = synthesize(DemForward, profile, truth, SIZES_M, 6, 3.0,
                         jax.random.key(args.data_key + i))
        fk = args.forward_key + (0 if args.same_design else i)
        fw = DemForward(profile, obs.sizes_m, budget.n_blocks_design, jax.random.key(fk))
        fit = calibrate(fw, obs, jax.random.key(6), ("bayes",), budget)
        s = fit.posterior.summary()
        row = {"set": i, "truth": truth.round(3).tolist(), "ok": fit.posterior.ok,
               "problems": fit.posterior.problems,
               "expected_posterior": fit.emulator_check.get("expected_posterior"),
               "time_s": round(time.perf_counter() - t0)}
        for j, name in enumerate(fit.names):
            hit = bool(s[name]["q05"] <= truth[j] <= s[name]["q95"])
            row[name] = [round(s[name]["q05"], 3), round(s[name]["q95"], 3), hit]
            covered.append(hit)
        print(json.dumps(row), flush=True)
    print(f"{sum(covered)} of {len(covered)} intervals hold the truth")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
