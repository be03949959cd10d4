#!/usr/bin/env python3
"""How noisy is the DEM's summed log-likelihood on `calib.discover`'s grids, and
what do the grid fit's intervals and held-out scores make of it?

`calib.discover --model dem` scores each candidate on a fixed grid (16 points of
one alpha, 8 x 8 of alpha(L) = a L^-b; ``calib.discovery.dem_candidates``) with
a few blocks per point and size, the same blocks (keys) at every point, and
emulates the rows between the points (``calib.discovery.grid_emulation``).
This script measures, on a data set made by ``python -m calib.synth --model
dem`` (its ``.truth.json`` beside it):

* ``--alphas A,B,...``: the baseline's summed log-likelihood at those alphas
  under each block set of ``--keys`` (the noise from one set to the next, and,
  with a second ``--n-blocks``, the bias of few blocks);
* otherwise: each candidate's grid simulated under each block set, then the
  90 % intervals from the emulated mean alone and from the posterior averaged
  over the summed log-likelihood's realisations (what ``grid_scores``
  returns), against the truth, and the held-out total (``elpd``).

Usage (the figures of docs/studies.md, "DEM discovery: the grid's noise in the
intervals")::

    python scripts/dem_grid_noise.py n180.csv --alphas 0.36,0.40,0.44 --keys 0-5
    python scripts/dem_grid_noise.py n180.csv --alphas 0.30,0.34,0.36,0.38,0.40,0.42,0.44,0.46 \\
        --keys 0-3 --n-blocks 32
    python scripts/dem_grid_noise.py n180.csv --effects none --keys 0-3
    python scripts/dem_grid_noise.py s180.csv --effects none,size_dissipation --keys 0-1

The blocks of key k are ``jax.random.key(k)``; ``calib.discover`` draws its own.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)


def _keys(text: str) -> list[int]:
    if "-" in text:
        lo, hi = map(int, text.split("-"))
        return list(range(lo, hi + 1))
    return [int(k) for k in text.split(",")]


def main(argv=None) -> int:
    from calib.discovery.candidate_fit import _row_loglik
    from calib.discovery.dem_candidates import DemEffectForward, dem_candidates
    from calib.discovery.grid_emulation import grid_scores
    from calib.discovery.scores import folds
    from calib.files.observations import load_observations
    from calib.inference.importance import psis_weights, weighted_quantile
    from calib.model.warp import unit_coordinates
    from solvers.profile import load_profile

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("data", help="observations made by calib.synth --model dem")
    p.add_argument("--profile", help="profile CSV (default: the data's <name>_profile.csv)")
    p.add_argument("--keys", default="0-3", help="block sets: 'a-b' or 'a,b,...'")
    p.add_argument("--n-blocks", type=int, default=8, help="blocks per point and size")
    p.add_argument("--alphas", help="baseline alphas to score (the noise study)")
    p.add_argument("--effects", default="none,size_dissipation",
                   help="candidates whose grids to fit (without --alphas)")
    a = p.parse_args(argv)

    data = Path(a.data)
    profile = load_profile(a.profile or str(data.with_name(data.stem + "_profile.csv")))
    truth_path = data.with_name(data.stem + ".truth.json")
    truth = json.loads(truth_path.read_text())["parameters"] if truth_path.exists() else {}
    obs = load_observations(str(data))
    sizes = np.unique(obs.block_size_m)
    row_class = np.searchsorted(sizes, obs.block_size_m)
    loglik = _row_loglik(obs, row_class, None)
    keys = _keys(a.keys)

    if a.alphas:
        alphas = np.array([float(v) for v in a.alphas.split(",")])
        totals = []
        for k in keys:
            fw = DemEffectForward(profile, sizes, a.n_blocks, jax.random.key(k), effect="none")
            totals.append(loglik(fw.runouts(alphas[:, None]), None).sum(axis=1))
            print(f"key {k}: " + "  ".join(f"{al:.3f} {t:.1f}"
                                           for al, t in zip(alphas, totals[-1])), flush=True)
        t = np.array(totals)
        print(f"{a.n_blocks} blocks, {len(keys)} sets: mean " + "  ".join(
            f"{al:.3f} {m:.1f} (sd {s:.1f})" for al, m, s in
            zip(alphas, t.mean(0), t.std(0, ddof=1) if len(keys) > 1 else np.zeros(t.shape[1]))))
        return 0

    fold = folds(row_class, 5, seed=0)
    wanted = a.effects.split(",")
    for cand in dem_candidates(profile, tuple(wanted)):
        if cand.effect not in wanted:
            continue
        theta = cand.design()
        to_z, to_theta, _ = unit_coordinates(cand.box)
        box = cand.box
        for k in keys:
            t0 = time.perf_counter()
            ll = loglik(cand.forward(sizes, a.n_blocks, jax.random.key(k)).runouts(theta), None)
            g = grid_scores(to_z(theta), ll, fold, np.random.default_rng(k))
            th = to_theta(g.z)
            w_mean = psis_weights(g.ll.sum(axis=1) - g.log_q)[0]
            parts = []
            for j, name in enumerate(box.names):
                m = [weighted_quantile(th[:, j], w_mean, q) for q in (0.05, 0.95)]
                r = [weighted_quantile(th[:, j], g.weights, q) for q in (0.05, 0.95)]
                tv = truth.get(name, truth.get("alpha") if name == "a" else
                               (0.0 if name == "b" and "alpha" in truth else None))
                mark = "" if tv is None else (" covers" if r[0] <= tv <= r[1] else " misses")
                parts.append(f"{name} (truth {tv}): mean {m[0]:.3f}-{m[1]:.3f}, "
                             f"realisations {r[0]:.3f}-{r[1]:.3f}{mark}")
            print(f"{cand.effect} key {k} ({time.perf_counter() - t0:.0f} s): held-out "
                  f"{g.elpd.sum():.1f}, sum's noise sd {g.sum_emulator.sn:.1f}; "
                  + "; ".join(parts), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
