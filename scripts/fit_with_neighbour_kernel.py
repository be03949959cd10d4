#!/usr/bin/env python3
"""``python -m calib.fit`` with each point row's kernel widened to the distance
to its k-th nearest simulated runout: a measurement of the observation model,
not a product path.

``calib.fit`` scores an observed runout against simulated ones with a Gaussian
kernel whose width is the row's tolerance (``calib.inference.likelihood``). On
the Tschamut runs that score is noisy where few simulated blocks come near a
row, and its ranking of the parameter points changes when the kernel reaches k
blocks instead (``scripts/loglik_noise.py --knn-k``, ``docs/studies.md``). This
script runs the very same command with every score of raw simulations (design
points, gradient, checks) made by ``nearest_neighbour_loglik`` of
``scripts/loglik_noise.py``; emulated quantiles (their predictive variance as the
kernel) keep the tolerance kernel. Everything else is the main job's, so the
held-out check of ``--holdout-fraction`` says whether the data support the
wider kernel.

Usage (the figures of docs/studies.md)::

    python scripts/fit_with_neighbour_kernel.py 16 data/tschamut2014/observations.csv \\
        --model crsp --holdout-fraction 0.3 --seed 1 --out results/tschamut-knn16
"""

from __future__ import annotations

import os
import runpy
import sys

import calib.inference.likelihood as likelihood

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from loglik_noise import nearest_neighbour_loglik  # noqa: E402

_tolerance_kernel = likelihood.log_likelihood


def widened(k: int):
    """``log_likelihood``'s signature: the k-th-neighbour kernel on raw simulations
    (no extra variance), the tolerance kernel on emulated quantiles."""
    def log_likelihood(samples, y_m, sd_m, lo_m, hi_m, is_interval, extra_var_m2=0.0):
        if isinstance(extra_var_m2, (int, float)) and extra_var_m2 == 0:
            return nearest_neighbour_loglik(samples, y_m, sd_m, lo_m, hi_m, is_interval, k)
        return _tolerance_kernel(samples, y_m, sd_m, lo_m, hi_m, is_interval, extra_var_m2)

    return log_likelihood


if __name__ == "__main__":
    if len(sys.argv) < 3 or not sys.argv[1].isdigit() or int(sys.argv[1]) < 1:
        print("usage: fit_with_neighbour_kernel.py K DATA [calib.fit options]; K >= 1",
              file=sys.stderr)
        sys.exit(2)
    likelihood.log_likelihood = widened(int(sys.argv[1]))
    sys.argv = ["python -m calib.fit"] + sys.argv[2:]
    runpy.run_module("calib.fit", run_name="__main__")
