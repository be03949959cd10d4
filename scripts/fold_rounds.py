#!/usr/bin/env python3
"""``python -m calib.discover`` with its fold stages logged round by round: a
measurement of the held-out folds' importance weights, not a product path.

``calib.discover`` gives every fold whose Pareto k-hat lies above the
sample-size bar min(0.7, 1 - 1/log10 S) a stage of points of its own, for up
to ``DiscoveryBudget.fold_rounds`` rounds
(``calib.discovery.candidate_fit._scores_covering_folds``). This script runs
the very same command with that step replaced by one that, for the candidates
named in ``--log-effects``, runs ``--rounds`` rounds on a copy of the design
(the same fold stages, their own generator, seed 1) and prints after each:
the design's size S, the bar, every fold's k-hat, and how far the simulated
summed log-likelihood of the round's new points lies from the GP's smoothed
value there (sd, nats) against the noise the smoothing assumed. With
``--noise-points K`` it also measures, at the K design points of largest
posterior weight (before any fold stage), the sd of the summed
log-likelihood over the budget's ``noise_reps`` fresh block sets, beside each
point's simulated - smoothed difference: whether that difference is
simulation noise or a surface the GP does not follow. The command's
own fold stages and results (``discovery.json``, the summary) follow as usual,
on the design without those rounds' points.

Usage (the figures of docs/studies.md)::

    python scripts/fold_rounds.py --rounds 4 --log-effects size_dissipation -- \\
        data/tschamut2014/observations.csv --rolling-resistance fit \\
        --effects size_dissipation --out results/fold-rounds --no-progress
    python scripts/fold_rounds.py --rounds 0 --noise-points 8 --log-effects \
        none,size_dissipation -- data/tschamut2014/observations.csv \
        --rolling-resistance fit --effects size_dissipation --out results/fold-noise \
        --no-progress
"""

from __future__ import annotations

import argparse
import dataclasses
import runpy
import sys

import jax
import numpy as np

import calib.discovery.candidate_fit as candidate_fit
from calib.discovery.loglik_noise import loglik_noise_sd
from calib.inference.importance import khat_threshold

_command_scores = candidate_fit._scores_covering_folds
_command_noise_var = candidate_fit.measured_noise_var
_forward = {}  # the last fit's forward model, log-likelihood and budget (from measured_noise_var)


def _remembering_noise_var(fw, loglik, theta, budget, key, tallies, names):
    _forward.update(fw=fw, loglik=loglik, budget=budget, key=key)
    return _command_noise_var(fw, loglik, theta, budget, key, tallies, names)


def _copy(design):
    """The design with its own stage lists (``_Design.add`` appends to them)."""
    return dataclasses.replace(design, counts=list(design.counts),
                               logpdfs=list(design.logpdfs))


def _logged_rounds(design, fold, n_new, rounds, smoothed, effect):
    d, rng, start = _copy(design), np.random.default_rng(1), 0
    for i in range(rounds + 1):
        k = candidate_fit._weights_and_scores(d.z, d.ll, d.log_q(), fold, d.noise_var,
                                              smoothed)[3]
        total = d.ll.sum(axis=1)
        fitted = candidate_fit._smoothed(d.z, total[None], np.array([d.ll.shape[1]]),
                                         d.noise_var)[0]
        resid = total[start:] - fitted[start:]
        print(f"[fold rounds] {effect} round {i}: S {d.z.shape[0]}, bar "
              f"{khat_threshold(d.z.shape[0]):.3f}, fold k-hats {np.round(k, 2).tolist()}; "
              f"simulated - smoothed sum at the {'design' if i == 0 else 'new'} points: "
              f"sd {resid.std():.2f} nats (smoothing noise sd {np.sqrt(d.noise_var):.2f})",
              flush=True)
        flagged = np.flatnonzero(k > khat_threshold(d.z.shape[0]))
        if i == rounds or not flagged.size:
            return
        start = d.z.shape[0]
        candidate_fit._fold_stages(d, fold, flagged, n_new, rng, None, effect)


def _noise_at_heaviest(design, fold, smoothed, effect, k):
    w = candidate_fit._weights_and_scores(design.z, design.ll, design.log_q(), fold,
                                          design.noise_var, smoothed)[0]
    total = design.ll.sum(axis=1)
    fitted = candidate_fit._smoothed(design.z, total[None], np.array([design.ll.shape[1]]),
                                     design.noise_var)[0]
    fw, loglik, budget = _forward["fw"], _forward["loglik"], _forward["budget"]
    for rank, i in enumerate(np.argsort(w)[::-1][:k]):
        reps = fw.replicate_sims(design.to_theta(design.z[i][None])[0], budget.noise_reps,
                                 jax.random.fold_in(_forward["key"], 100 + rank))
        sd = loglik_noise_sd(loglik(*reps))
        print(f"[fold rounds] {effect} point {rank + 1} (weight {w[i]:.3f}): noise sd "
              f"{sd:.2f} nats over {budget.noise_reps} block sets; simulated - smoothed "
              f"{total[i] - fitted[i]:+.2f} nats (smoothing noise sd "
              f"{np.sqrt(design.noise_var):.2f})", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="Arguments after -- go to python -m calib.discover.")
    p.add_argument("--rounds", type=int, default=4, help="fold-stage rounds logged (default 4)")
    p.add_argument("--log-effects", default="size_dissipation",
                   help="comma-separated candidates whose rounds are logged "
                        "(default size_dissipation)")
    p.add_argument("--noise-points", type=int, default=0,
                   help="design points of largest weight at which to measure the noise "
                        "(default 0: none)")
    args, rest = p.parse_known_args()
    if args.rounds < 0:
        p.error(f"--rounds must be >= 0, got {args.rounds}")
    if args.noise_points < 0:
        p.error(f"--noise-points must be >= 0, got {args.noise_points}")
    logged = set(args.log_effects.split(","))

    def scores(design, fold, n_new, rounds, smoothed, rng, progress=None, effect="",
               n_draws=0):
        if effect in logged and smoothed:
            _logged_rounds(design, fold, n_new, args.rounds, smoothed, effect)
            if args.noise_points and "fw" in _forward:
                _noise_at_heaviest(design, fold, smoothed, effect, args.noise_points)
        return _command_scores(design, fold, n_new, rounds, smoothed, rng, progress, effect,
                               n_draws)

    candidate_fit._scores_covering_folds = scores
    candidate_fit.measured_noise_var = _remembering_noise_var
    sys.argv = ["python -m calib.discover"] + [a for a in rest if a != "--"]
    runpy.run_module("calib.discover", run_name="__main__")


if __name__ == "__main__":
    main()
