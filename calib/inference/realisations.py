"""How far the log-likelihood GP's own uncertainty could move a CRSP posterior.

NUTS on the GP's expected log-likelihood (``calib.inference.loglik_emulator``)
samples ONE density: the posterior as if the GP's mean were the simulator's
log-likelihood. Where the GP is unsure, that posterior is narrower than what
the simulations support: on Tschamut (all 62 runs) two fits that differed only
in their seed gave 90 % intervals of Kt 0.960-0.964 and 0.973-0.978, which do
not overlap (measured 2026-11-25). This module measures that
(``realisation_weights``, ``spread_problems``) and says where to simulate to
reduce it (``realisation_draws``: one point from each realisation's
posterior; ``calib.inference.calibrate`` stage 1e adds them to the GP's
design and samples again, a few waves at most).

What the posterior would be under other functions the GP finds as plausible
as its mean: M realisations y_f of the GP (``LoglikEmulator.realisation_draw``,
pathwise conditioning), each giving p_f(theta) = prior(theta) exp(y_f(theta)) /
Z_f. Their mixture over f is the "expected posterior" (Roberts, Dietze &
Huggins 2026, "Propagating surrogate uncertainty in Bayesian inverse
problems", arXiv 2601.03532; "E-Post" in Reiser, Aguilar, Guthke & Buerkner
2023, arXiv 2312.05153).

Why not report that mixture (measured on 2026-11-25, default budget): each
realisation's posterior is rough, with narrow peaks wherever the GP is
unsure between its design points. One NUTS run on the product of 8
realisations' posteriors (2 chains, 500 draws each) left one realisation in
8 bimodal on the Tschamut seed-1 split (R-hat 1.8 between its chains), and on
the Postignano rows R-hat reached 1.55 in 3 to 6 of 8 realisations per
parameter; importance sampling that corrected those chains had Pareto k-hat
above 0.7 in 5 of 8 Tschamut realisations (3 of them with effective sample
sizes of 1-5 out of 8,192 points). A posterior whose sampler fails its own
diagnostics is not one to report.

What is reported instead (our rule): the posterior median of each of
``N_REALISATIONS`` realisations, estimated by self-normalised importance
sampling on one shared set of ``N_CANDIDATES`` points (half a Gaussian KDE of
the mean-GP posterior's draws with twice Scott's bandwidth, half uniform on
the box NUTS sampled; ``_candidates``). Where a realisation's posterior is
spiky its weighted median is its best candidate, where it is broad a stable
median; both say where that realisation puts the posterior. If the range of
these medians reaches outside the posterior's 90 % interval for a parameter,
the interval is narrower than the GP's own uncertainty allows, and the fit
says so loudly (``bayes.problems``): another seed, or more simulations, may
move the posterior that far.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import logsumexp

from calib.inference.importance import weighted_quantile
from calib.model.priors import Box

__all__ = ["N_CANDIDATES", "N_REALISATIONS", "realisation_check", "realisation_draws",
           "realisation_medians", "realisation_weights", "spread_problems", "weighted_medians"]

N_REALISATIONS = 32
N_CANDIDATES = 4096
_BANDWIDTH_FACTOR = 2.0  # x Scott's rule: the candidates reach past the mean-GP posterior
_KDE_CENTRES = 1024


def _candidates(draws: np.ndarray, box: Box, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray]:
    """``N_CANDIDATES`` points in the box and their log proposal density: half
    from a Gaussian KDE of ``draws`` (n, d) (twice Scott's bandwidth per
    coordinate, at least 1e-4 of the box width), half uniform on the box."""
    d = box.dim
    c = draws[rng.choice(len(draws), min(_KDE_CENTRES, len(draws)), replace=False)]
    h = np.maximum(_BANDWIDTH_FACTOR * c.std(axis=0) * len(c) ** (-1.0 / (d + 4)),
                   1e-4 * (box.hi - box.lo))
    n_kde = N_CANDIDATES // 2
    kde = c[rng.integers(0, len(c), n_kde)] + h * rng.standard_normal((n_kde, d))
    uni = box.lo + (box.hi - box.lo) * rng.random((N_CANDIDATES - n_kde, d))
    theta = np.concatenate([kde, uni])
    xs, cs = theta / h, c / h
    d2 = np.sum(xs * xs, 1)[:, None] - 2.0 * xs @ cs.T + np.sum(cs * cs, 1)[None]
    log_kde = (logsumexp(-0.5 * np.maximum(d2, 0.0), axis=1) - np.log(len(c))
               - np.sum(np.log(h)) - 0.5 * d * np.log(2 * np.pi))
    log_uni = np.full(len(theta), -np.sum(np.log(box.hi - box.lo)))
    log_q = np.logaddexp(np.log(0.5) + log_kde, np.log(0.5) + log_uni)
    return theta, log_q


def realisation_weights(emu, to_input, box: Box, draws: np.ndarray, key: jax.Array,
                        n_realisations: int = N_REALISATIONS) -> tuple[np.ndarray, np.ndarray]:
    """The candidate points (K, d) and each realisation's self-normalised
    importance weights on them (M, K), for M realisations of ``emu`` (a
    ``LoglikEmulator``; theta -> emulator coordinates by ``to_input``) in the
    prior ``box``, with the candidate set built around ``draws`` (n, d), the
    mean-GP posterior's (module docstring). Candidates outside the box have
    weight 0; a realisation no candidate reaches (all weights 0) is left out,
    so M may be smaller than ``n_realisations``."""
    k_f, k_c = jax.random.split(key)
    rng = np.random.default_rng(np.asarray(jax.random.randint(k_c, (), 0, 2**31 - 1)).item())
    theta, log_q = _candidates(np.asarray(draws), box, rng)
    x = jax.vmap(to_input)(jnp.asarray(theta))
    fdraws = jax.vmap(emu.realisation_draw)(jax.random.split(k_f, n_realisations))
    # one realisation at a time, candidates in batches: the features of all of
    # them at once would take 32 x 4,096 x 1,024 doubles (1.1 GB)
    y = jax.jit(lambda fs: jax.lax.map(lambda f: jax.lax.map(
        lambda xi: emu.realisation_value(f, xi), x, batch_size=1024), fs))(fdraws)
    inside = np.all((theta >= box.lo) & (theta <= box.hi), axis=1)  # the prior's support
    log_w = np.asarray(y) - log_q[None]
    log_w = np.where(np.isfinite(log_w) & inside[None], log_w, -np.inf)
    log_w = log_w[np.isfinite(log_w).any(axis=1)]  # a realisation with no finite weight: none
    return theta, np.exp(log_w - logsumexp(log_w, axis=1, keepdims=True))


def weighted_medians(theta: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(M, d) each realisation's posterior median from ``realisation_weights``."""
    return np.array([[weighted_quantile(col, wj, 0.5) for col in theta.T] for wj in weights])


def realisation_medians(emu, to_input, box: Box, draws: np.ndarray, key: jax.Array,
                        n_realisations: int = N_REALISATIONS) -> np.ndarray:
    """(M, d) the posterior median of each of M realisations (arguments as in
    ``realisation_weights``)."""
    return weighted_medians(*realisation_weights(emu, to_input, box, draws, key, n_realisations))


def realisation_draws(theta: np.ndarray, weights: np.ndarray, key: jax.Array) -> np.ndarray:
    """(M, d) one point from each realisation's posterior (a candidate drawn
    with that realisation's weights): where simulations would settle what the
    realisations disagree on (Thompson sampling of the GP's posterior over
    functions, one draw per realisation)."""
    idx = jax.vmap(lambda k, w: jax.random.choice(k, w.shape[0], p=w))(
        jax.random.split(key, weights.shape[0]), jnp.asarray(weights))
    return theta[np.asarray(idx)]


def realisation_check(emu, to_input, box: Box, samples: np.ndarray, names: tuple[str, ...],
                      key: jax.Array, n_realisations: int = N_REALISATIONS, draw: bool = False
                      ) -> tuple[dict, list[str], np.ndarray | None]:
    """The module's check on a posterior's ``samples`` (n, d): its record and
    problems (``spread_problems``), and, when ``draw`` and it flags, one point
    from each realisation's posterior (``realisation_draws``), where a fit
    simulates next; else (or when no realisation reached a candidate) None."""
    theta, weights = realisation_weights(emu, to_input, box, samples, key, n_realisations)
    record, problems = spread_problems(weighted_medians(theta, weights), samples, names)
    points = (realisation_draws(theta, weights, jax.random.fold_in(key, 1))
              if draw and problems and len(weights) else None)  # no realisation: no wave
    return record, problems, points


def spread_problems(medians: np.ndarray, samples: np.ndarray, names: tuple[str, ...]
                    ) -> tuple[dict, list[str]]:
    """The record and the problems of the module's rule: per parameter the
    range of the realisations' medians against the posterior's 90 % interval."""
    if len(medians) == 0:
        return ({"n_realisations": 0, "n_candidates": N_CANDIDATES, "outside": []},
                ["no realisation of the log-likelihood GP put weight on any candidate point "
                 "inside the box: the intervals could not be checked"])
    q05, q95 = np.quantile(samples, [0.05, 0.95], axis=0)
    lo, hi = medians.min(axis=0), medians.max(axis=0)
    record = {"n_realisations": int(len(medians)), "n_candidates": N_CANDIDATES,
              "median_range": {n: [float(lo[i]), float(hi[i])] for i, n in enumerate(names)},
              "posterior_90": {n: [float(q05[i]), float(q95[i])] for i, n in enumerate(names)}}
    wide = [i for i in range(len(names)) if lo[i] < q05[i] or hi[i] > q95[i]]
    record["outside"] = [names[i] for i in wide]
    problems = []
    if wide:
        problems.append(
            "the intervals are narrower than the log-likelihood GP's own uncertainty: the "
            f"posterior medians of {len(medians)} realisations of the GP span "
            + ", ".join(f"{names[i]} {lo[i]:.3g}-{hi[i]:.3g} (90 % interval "
                        f"{q05[i]:.3g}-{q95[i]:.3g})" for i in wide)
            + "; another seed or more simulations may move the posterior that far")
    return record, problems
