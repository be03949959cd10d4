#!/usr/bin/env python3
"""``python -m calib.fit`` with tempered SMC in place of NUTS on the CRSP
log-likelihood GP: a measurement of the sampler, not a product path.

The main job samples the summed log-likelihood GP of a CRSP fit with NUTS, its
chains started at the best design points (``calib.inference.bayes_stage``). On
the Tschamut runs the seed decides which of two ridges those chains report
(``docs/studies.md``). This script runs the very same command with every
summed-log-likelihood sampling replaced by ``calib.inference.smc.run_smc``
(as many populations as the budget's chains, as many particles per population
as its draws per chain); the DEM's pointwise sampling keeps NUTS. Everything
else (designs, refinements, realisation waves, checks, outputs) is the main
job's.

Usage (the figures of docs/studies.md)::

    python scripts/fit_with_smc.py data/tschamut2014/observations.csv \\
        --model crsp --seed 3 --out results/tschamut-smc-3
"""

from __future__ import annotations

import runpy
import sys

import calib.inference.bayes_stage as bayes_stage
from calib.inference.bayes import run_nuts
from calib.inference.smc import run_smc


def sampler(target, box, key, num_warmup=500, num_samples=1000, num_chains=4,
            loglik_kind="pointwise", init=None):
    """``run_nuts``'s signature: SMC where the target is the summed GP."""
    if loglik_kind != "summed":
        return run_nuts(target, box, key, num_warmup, num_samples, num_chains, loglik_kind, init)
    return run_smc(target, box, key, n_particles=num_samples, n_runs=num_chains,
                   loglik_kind=loglik_kind)


if __name__ == "__main__":
    bayes_stage.run_nuts = sampler
    sys.argv = ["python -m calib.fit"] + sys.argv[1:]
    runpy.run_module("calib.fit", run_name="__main__")
