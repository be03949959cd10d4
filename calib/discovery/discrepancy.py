"""The discrepancy workflow: fit the baseline, locate where it fails, fit each
candidate effect, name the one that clearly predicts better, show the gap
shrink; then add it to the baseline and search again.

1. Every candidate (the baseline ``none`` and each effect of ``calib.model.effects``)
   is fitted the same way: a Bayesian fit by adaptive importance sampling over
   a simulated design. Every stage draws in the prior box's warped coordinates
   (``calib.model.warp``: log S, log(1 - Kt), tan(phi_r), scaled to the unit
   cube; ``calib.model.warp.unit_coordinates``), and each draw's density
   carries the change of variables back to the uniform prior in theta. Stage 0 is a scrambled Sobol
   design, one half uniform in theta, the other uniform in the warped cube
   (a defensive pair: the first covers a posterior the warp would thin out).
   For an effect, a warm stage follows: the baseline's parameters drawn from a
   Gaussian fitted to the baseline's posterior, the effect's uniformly over
   their box. Each later stage draws points from a Gaussian fitted to the
   weighted points so far (covariance inflated x4 plus (0.05)^2 in unit
   coordinates, truncated to the box). All stages are one deterministic-mixture proposal
   (Owen & Zhou 2000, "Safe and effective importance sampling", JASA 95,
   135-143), so the self-normalised weights ``w_k ~ L(theta_k) p(theta_k) /
   q_mix(theta_k)`` target the posterior under the uniform prior. Every set of
   weights (each stage's fit, the posterior, each fold's training weights of
   step 3) is Pareto-smoothed (``calib.inference.importance.psis_weights``); its k-hat
   is reported per candidate (``khat``) and per fold (``khat_by_fold``), and a
   fold above ``calib.inference.importance.KHAT_MAX`` = 0.7 is flagged
   (``psis_flagged_folds``): its held-out scores are unreliable. Runouts are
   simulated with common random numbers (``calib.model.forward``), and the
   likelihood is ``calib.inference.likelihood``'s, the one ``calib.fit`` uses (points:
   the tolerance as kernel; intervals: the Silverman width). Optional passage
   speeds at stations (``calib.files.observations.Velocities``) add rows scored by
   ``calib.inference.likelihood.velocity_log_likelihood`` from the same simulations.
2. The baseline's posterior predictive (``n_draws`` posterior draws re-simulated
   with fresh blocks) gives quantile residuals, tested against block size and
   stop position (``calib.discovery.residuals``): WHERE it fails, with p-values.
3. The candidates are compared by their K-fold held-out log predictive density
   (``calib.discovery.scores``); the best is named only when its gain over the
   baseline exceeds ``ELPD_MIN`` = 4 nats and z standard errors, else ``none``:
   z = ``Z_MIN`` = 2 at the first step (its false-positive rate over the whole
   candidate set measured on null data, ``docs/studies.md``), raised
   Bonferroni-style for the m candidates a later step compares
   (``calib.discovery.scores.naming_z``: 2.53 for four).
   Each effect's row of the table also gives ``effective_rows``, the number of
   rows that effectively carry its gain (the 2-se bar is a bar on it, see
   ``calib.discovery.scores.effective_rows``), and ``carrying_rows``, the indices of the
   rows that carry 90 % of it (runout rows in file order, then speed rows).
4. The gap metric (``GAP_METRIC``) is computed for every candidate from its own
   posterior predictive; gap_before is the baseline's, gap_after the final
   model's (re-fitted on all rows, which its design already is).
5. Discovery keeps going (``discover``'s ``combine``): once an effect is named,
   the model with it is the new baseline, and steps 1 and 3 run again with
   each remaining candidate added to it (baseline + named + candidate against
   baseline + named, whose fit is reused; its posterior seeds the warm
   stage). Stopping rule: a step that names none, no candidate left, or the
   step limit. Multiple testing: within a step the bar is Bonferroni's over the
   m candidates compared (3.), i.e. each step tests "no remaining candidate
   gains" at the one-sided level ALPHA = Phi(-2) = 2.3 % whatever the
   dependence of the candidates' gains; across steps nothing more is spent,
   because a step runs only after the one before rejected: once every real
   effect is in the model, the next step is the first whose candidates all
   lack a gain, and it names one with probability at most ALPHA, after which
   the loop stops or has already erred (the fixed-sequence argument: Westfall
   & Krishen 2001, "Optimally weighted, fixed sequence and gatekeeper multiple
   testing procedures", J. Statist. Plann. Inference 99, 25-40). Our choice
   over splitting a family-wise level across the steps (ALPHA / K each), which
   would make later steps needlessly blind. Two caveats: the sequence of
   hypotheses depends on what earlier steps named (an early wrong effect can
   change the later ones), and the level rests on the normal approximation of
   the score difference, which is optimistic with few rows (Sivula et al.
   2022); the levels are nominal.

Unfinished blocks (NaN runouts and speeds from the forward models,
``calib.model.unfinished``) are left out of the likelihood, the predictive and the
gap; each fit counts them (design, predictive and noise simulations,
``CandidateFit.unfinished``) and warns once (``UnfinishedBlocksWarning``) when
some (design point, size class) has more than 1 % of them.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import logsumexp
from scipy.stats import qmc

from calib.discovery.residuals import locate, point_view
from calib.discovery.scores import (
    best_effect,
    carrying_rows,
    crps_ensemble,
    cv_elpd,
    effective_rows,
    elpd_difference,
    folds,
    naming_threshold,
    naming_z,
)
from calib.files.inputs import own_profile
from calib.inference.budget import DiscoveryBudget
from calib.inference.importance import KHAT_MAX, ess, psis_weights, weighted_quantile
from calib.inference.likelihood import log_likelihood, observed_rows, velocity_log_likelihood
from calib.inference.predictive_check import pool_draws
from calib.model.entries import Entries
from calib.model.priors import Box
from calib.model.unfinished import UnfinishedTally, unfinished_record, warn_unfinished
from calib.model.warp import unit_coordinates

__all__ = [
    "GAP_METRIC",
    "MULTIPLE_TESTING",
    "STOPPING_RULE",
    "Candidate",
    "CandidateFit",
    "Discovery",
    "discover",
    "fit_candidate",
    "gap",
    "loglik_noise_sd",
    "model_label",
    "size_classes",
]

GAP_METRIC = ("mean CRPS (m) of the observed runouts under the model's posterior predictive "
              "(simulated runout + the row's measurement noise), averaged over the rows of "
              "each size class, then over the size classes")


@dataclasses.dataclass(frozen=True)
class Candidate:
    """A model to fit: its effect name, prior box and forward-model factory.

    ``forward(entries, n_blocks, key)`` returns an object whose ``runouts(theta)``
    maps (T, p) parameters to (T, S, n_blocks) runouts (``calib.model.forward``)
    of the S simulated ``calib.model.entries.Entries`` (block size, release,
    profile, density: a size class, or a (size class, release) group where the
    rows give their own releases);
    with passage velocities it gets ``stations_x_m=`` and the object's
    ``simulate(theta)`` must also give the speeds there (``CrspForward``).
    ``design`` (optional) replaces the adaptive design by a fixed one: a
    callable ``design() -> (N, p)`` (the DEM's grids). ``n_blocks`` (optional)
    overrides the budget's blocks per (design point, size) for this candidate.
    """

    effect: str
    box: Box
    forward: Callable
    design: Callable | None = None
    n_blocks: int | None = None


@dataclasses.dataclass
class CandidateFit:
    """A fitted candidate.

    Attributes:
        effect, names: the effect and its parameter names.
        theta: (N, p) design points; log_q: (N,) proposal / prior density.
        loglik: (N, n_rows) pointwise log-likelihood at the design points: the
            runout rows, then the passage-velocity rows (if any).
        weights: (N,) posterior weights (all rows), Pareto-smoothed.
        ess: effective sample size of the weights.
        elpd: (n_rows,) held-out log predictive density of each row (same order).
        khat: Pareto k-hat of the posterior weights; khat_folds: (K,) that of
            each fold's training weights (``calib.discovery.scores.cv_elpd``); NaN where
            not estimated (``calib.inference.importance``).
        estimate, q05, q95: weighted posterior mean and 90 % interval per parameter;
            best: the design point of highest weight.
        samples: (E, M) posterior-predictive runouts per simulated entry (a size
            class, or a (size class, release) group; fresh blocks).
        class_samples: (C, M') the same pooled per size class: each row of the
            class contributes its entry's samples (for figures).
        gap_by_class: (C,) mean CRPS per class, m; gap: their mean, m.
        loglik_noise_sd_nats: Monte Carlo sd of the summed log-likelihood at
            ``best`` over ``noise_reps`` independent block sets of the fit's size
            (nan if not measured); see ``loglik_noise_sd``.
        seconds: wall time of the fit.
        unfinished: counts of unfinished blocks per stage (design, predictive,
            noise) and the warning text (``calib.model.unfinished.unfinished_record``).
    """

    effect: str
    names: tuple[str, ...]
    theta: np.ndarray
    log_q: np.ndarray
    loglik: np.ndarray
    weights: np.ndarray
    ess: float
    elpd: np.ndarray
    estimate: np.ndarray
    q05: np.ndarray
    q95: np.ndarray
    best: np.ndarray
    samples: np.ndarray
    gap_by_class: np.ndarray
    gap: float
    loglik_noise_sd_nats: float
    seconds: float
    unfinished: dict | None = None
    khat: float = float("nan")
    khat_folds: np.ndarray | None = None
    class_samples: np.ndarray | None = None


def size_classes(sizes_m: np.ndarray, max_classes: int = 8):
    """Size classes of the rows: the distinct sizes, or (more than ``max_classes``)
    ``max_classes`` bins of equal width in log size, represented by their
    members' geometric mean (an approximation stated in the output).

    Returns:
        (class_sizes_m (C,), row_class (n_obs,)).
    """
    sizes = np.asarray(sizes_m, float)
    uniq = np.unique(sizes)
    if uniq.size <= max_classes:
        return uniq, np.searchsorted(uniq, sizes)
    edges = np.linspace(np.log(uniq[0]), np.log(uniq[-1]), max_classes + 1)
    idx = np.clip(np.searchsorted(edges, np.log(sizes), side="right") - 1, 0, max_classes - 1)
    used = np.unique(idx)
    reps = np.array([np.exp(np.mean(np.log(sizes[idx == u]))) for u in used])
    return reps, np.searchsorted(used, idx)


@jax.jit
def _loglik_design(runs, row_class, y, sd, lo, hi, is_interval):
    """(N, n_obs) log-likelihood of every row at every design point: the
    observation model of ``calib.fit`` (``calib.inference.likelihood``, no extra variance)."""
    return jax.vmap(lambda r: log_likelihood(r[row_class], y, sd, lo, hi, is_interval))(runs)


@dataclasses.dataclass(frozen=True)
class VelocityRows:
    """Passage-velocity rows prepared for the fits (``calib.files.observations.Velocities``).

    Attributes:
        stations_m: (K,) distinct station abscissae, m.
        station: (n_v,) station index of each row; size_class: (n_v,) its size class.
        v_m_s, sd_m_s: (n_v,) observed speed and tolerance, m/s.
    """

    stations_m: np.ndarray
    station: np.ndarray
    size_class: np.ndarray
    v_m_s: np.ndarray
    sd_m_s: np.ndarray

    @property
    def n_obs(self) -> int:
        return int(self.v_m_s.shape[0])


@jax.jit
def _vel_loglik_design(speeds, size_class, station, v, sd):
    """(N, n_v) log-likelihood of every velocity row at every design point,
    from speeds (N, C, K, n)."""
    return jax.vmap(lambda u: velocity_log_likelihood(u[size_class, station], v, sd))(speeds)


def _gaussian_fit(z, w, inflate=2.0, floor=0.05):
    """Mean and inflated covariance of unit-cube points with normalised weights w."""
    mean = w @ z
    cov = (z - mean).T @ ((z - mean) * w[:, None])
    return mean, inflate**2 * cov + floor**2 * np.eye(z.shape[1])


def _proposal(mean, cov, rng, n, dim):
    """n draws in the unit cube [0, 1]^dim: the first ``len(mean)`` coordinates from
    N(mean, cov) truncated to the cube, the others uniform. Returns (draws,
    log-density function relative to the uniform prior)."""
    k = mean.size
    chol = np.linalg.cholesky(cov)
    draws = np.empty((0, k))
    tried = accepted = 0
    while draws.shape[0] < n and tried < 1000 * n:
        pool = mean + rng.standard_normal((20 * n, k)) @ chol.T
        inside = np.all((pool >= 0) & (pool <= 1), axis=1)
        tried += pool.shape[0]
        accepted += int(inside.sum())
        draws = np.concatenate([draws, pool[inside]])
    p_in = max(accepted, 1) / tried
    if draws.shape[0] < n:  # the Gaussian lies almost wholly outside: pad from the prior
        draws = np.concatenate([draws, rng.uniform(size=(n - draws.shape[0], k))])
    draws = np.concatenate([draws[:n], rng.uniform(size=(n, dim - k))], axis=1)
    inv = np.linalg.inv(cov)
    logdet = np.linalg.slogdet(cov)[1]

    def logpdf(x):
        d = x[:, :k] - mean
        return (-0.5 * np.einsum("ij,jk,ik->i", d, inv, d) - 0.5 * logdet
                - 0.5 * k * np.log(2 * np.pi) - np.log(p_in))

    return draws, logpdf


def gap(samples: np.ndarray, obs, row_class: np.ndarray, rng: np.random.Generator,
        row_entry: np.ndarray | None = None):
    """The gap metric (``GAP_METRIC``): (per-class mean CRPS (C,), their mean), m,
    over the finished blocks (NaN samples left out; a class with none: NaN).

    ``samples``: (E, M) predictive runouts per entry; row i is scored against
    ``samples[row_entry[i]]`` (default: entries are the size classes, ``row_class``).
    C is E without ``row_entry``, else ``row_class.max() + 1``."""
    entry = row_class if row_entry is None else row_entry
    y, sd = point_view(obs)
    per_row = np.array([_crps_finished(samples[entry[i]] + sd[i] * rng.standard_normal(
        samples.shape[1]), y[i]) for i in range(obs.n_obs)])
    classes = np.unique(row_class)
    by_class = np.full(samples.shape[0] if row_entry is None else int(row_class.max()) + 1,
                       np.nan)
    for c in classes:
        by_class[c] = per_row[row_class == c].mean()
    return by_class, float(np.nanmean(by_class))


def class_samples(samples: np.ndarray, row_entry: np.ndarray, row_class: np.ndarray,
                  n_classes: int) -> np.ndarray:
    """(C, M') predictive runouts per size class from (E, M) per entry: each row
    of a class contributes its entry's M samples (the class's mixture over its
    rows' releases); M' = M times the largest class's row count, NaN-padded."""
    per = [np.concatenate([samples[row_entry[i]] for i in np.flatnonzero(row_class == c)])
           if np.any(row_class == c) else np.full(samples.shape[1], np.nan)
           for c in range(n_classes)]
    width = max(p.size for p in per)
    return np.stack([np.pad(p, (0, width - p.size), constant_values=np.nan) for p in per])


def _crps_finished(samples: np.ndarray, y: float) -> float:
    x = samples[np.isfinite(samples)]
    return crps_ensemble(x, y) if x.size else float("nan")


def fit_candidate(cand: Candidate, obs, class_sizes_m, row_class, key: jax.Array,
                  budget: DiscoveryBudget, fold: np.ndarray, progress=None,
                  warm: tuple[np.ndarray, np.ndarray] | None = None,
                  velocities: VelocityRows | None = None,
                  entries: Entries | None = None) -> CandidateFit:
    """Fit one candidate by adaptive importance sampling; score it (see module doc).

    ``warm``: (mean, cov) in unit coordinates of the first parameters (the
    baseline's posterior), used for the warm stage. ``velocities``: passage-
    velocity rows scored with the runout rows (``fold`` then covers both; their
    ``size_class`` indexes the entries). ``entries``: what the forward model
    simulates, (size, release) groups with the entry of each runout row
    (``index``); None: one entry per size class ``class_sizes_m``, released at
    the profile's first vertex (``calib.model.forward.as_entries``).
    """
    t0 = time.perf_counter()
    box = cand.box
    dim = box.dim
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel()[-1])
    vel = velocities if velocities is not None and velocities.n_obs else None
    st_kw = {} if vel is None else {"stations_x_m": tuple(map(float, vel.stations_m))}
    if entries is None:
        simulated, row_entry = np.asarray(class_sizes_m, float), row_class
    else:
        simulated, row_entry = entries, entries.index
    entry_sizes = np.asarray(getattr(simulated, "sizes_m", simulated), float)
    try:
        fw = cand.forward(simulated, cand.n_blocks or budget.n_blocks,
                          jax.random.fold_in(key, 1), **st_kw)
    except TypeError:
        if vel is None:
            raise
        raise ValueError(f"candidate {cand.effect!r}: its forward model cannot record "
                         f"passage speeds (CRSP candidates can)") from None
    y, sd, lo, hi, is_int = observed_rows(obs)
    rc = jnp.asarray(row_entry)

    vel_arrays = None if vel is None else tuple(
        jnp.asarray(a) for a in (vel.size_class, vel.station, vel.v_m_s, vel.sd_m_s))

    def loglik(runs, speeds):
        ll = np.asarray(_loglik_design(jnp.asarray(runs), rc, y, sd, lo, hi, is_int))
        if vel is None:
            return ll
        lv = _vel_loglik_design(jnp.asarray(speeds), *vel_arrays)
        return np.concatenate([ll, np.asarray(lv)], axis=1)

    tallies = {"design": UnfinishedTally(tuple(map(float, entry_sizes)))}

    def simulate(z):
        theta = to_theta(z)
        runs, speeds = fw.simulate(theta) if vel else (fw.runouts(theta), None)
        tallies["design"].add(runs, theta, box.names)
        return loglik(runs, speeds)

    if cand.design is None:  # proposals in the warped unit cube (calib.model.warp)
        to_z, to_theta, log_jac = unit_coordinates(box)
    else:  # a fixed design (grids): uniform over the box itself
        def to_theta(z):
            return box.from_unit(z)

        def log_jac(z):
            return np.zeros(np.shape(z)[0])

    if cand.design is not None:
        z = box.to_unit(np.atleast_2d(cand.design()))
        parts = []
        for i in range(0, z.shape[0], 8):  # in pieces, for the progress bar
            parts.append(simulate(z[i:i + 8]))
            if progress:
                progress(cand.effect, min(i + 8, z.shape[0]), z.shape[0])
        ll = np.concatenate(parts)
        log_q = np.zeros(z.shape[0])
    else:
        total = budget.n_design - (budget.n_warm if warm is None else 0)
        # stage 0, a defensive pair: one half uniform in theta, one half uniform in
        # the warped coordinates (density -log_jac and 0 relative to the latter)
        sob = qmc.Sobol(dim, scramble=True, seed=rng).random(budget.n_sobol)
        n_theta = budget.n_sobol // 2
        z = np.concatenate([to_z(box.from_unit(sob[:n_theta])), sob[n_theta:]])
        ll = simulate(z)
        if progress:
            progress(cand.effect, budget.n_sobol, total)
        logpdfs = [lambda z: -log_jac(z), lambda z: np.zeros(z.shape[0])]
        counts = [n_theta, budget.n_sobol - n_theta]
        stages = ([("warm", budget.n_warm)] if warm is not None and budget.n_warm else []) + \
            [("refine", n) for n in budget.n_refine]
        for kind, n_new in stages:
            log_q = _mixture_log_q(z, counts, logpdfs) + log_jac(z)
            if kind == "warm":
                new, logpdf = _proposal(warm[0], warm[1], rng, n_new, dim)
            else:
                mean, cov = _gaussian_fit(z, psis_weights(ll.sum(axis=1) - log_q)[0])
                new, logpdf = _proposal(mean, cov, rng, n_new, dim)
            logpdfs.append(logpdf)
            counts.append(n_new)
            z = np.concatenate([z, new])
            ll = np.concatenate([ll, simulate(new)])
            if progress:
                progress(cand.effect, sum(counts), total)
        log_q = _mixture_log_q(z, counts, logpdfs) + log_jac(z)
    w, khat = psis_weights(ll.sum(axis=1) - log_q)
    theta = to_theta(z)
    est = w @ theta
    q05 = np.array([weighted_quantile(theta[:, j], w, 0.05) for j in range(dim)])
    q95 = np.array([weighted_quantile(theta[:, j], w, 0.95) for j in range(dim)])
    elpd, khat_folds = cv_elpd(ll, log_q, fold)
    samples = _predictive(cand, fw, theta, w, simulated, key, budget, rng, tallies)
    if entries is None:
        gap_c, gap_m = gap(samples, obs, row_class, rng)
        per_class = samples
    else:
        gap_c, gap_m = gap(samples, obs, row_class, rng, row_entry)
        per_class = class_samples(samples, row_entry, row_class, len(class_sizes_m))
    best = theta[np.argmax(w)]
    noise = float("nan")
    if budget.noise_reps > 1 and hasattr(fw, "replicate_sims"):
        reps = fw.replicate_sims(best, budget.noise_reps, jax.random.fold_in(key, 3))
        tallies["noise"] = UnfinishedTally(tuple(map(float, entry_sizes)))
        tallies["noise"].add(reps[0], np.broadcast_to(best, (budget.noise_reps, dim)),
                             box.names)
        noise = loglik_noise_sd(loglik(*reps))
    record = unfinished_record(tallies, f"candidate {cand.effect!r}")
    warn_unfinished(record)
    return CandidateFit(cand.effect, box.names, theta, log_q, ll, w, ess(w),
                        elpd, est, q05, q95, best, samples, gap_c, gap_m, noise,
                        time.perf_counter() - t0, record, khat, khat_folds, per_class)


def loglik_noise_sd(loglik_reps: np.ndarray) -> float:
    """Monte Carlo sd (nats) of the summed log-likelihood, from (R, n_obs)
    pointwise values at one theta under R independent block sets.

    The likelihood is a simulation estimate (``calib.inference.likelihood``), so its
    logarithm carries noise that grows with the number of rows and falls
    roughly as 1 / sqrt(n_blocks) (measured on 180 rows of null data at the
    baseline's best point: 3.4 nats with 128 blocks, 1.7 with 512). With R = 8
    the sd itself is uncertain by about 1 / sqrt(2 (R - 1)) = 27 %.

    How large is too large, by analogy with pseudo-marginal MCMC (Doucet, Pitt,
    Deligiannidis & Kohn 2015, "Efficient implementation of Markov chain Monte
    Carlo when using an unbiased likelihood estimator", Biometrika 102,
    295-313): there the cost-optimal sd of the log-likelihood estimator is
    about 1.0-1.7 nats. Importance weights carrying independent log-normal noise
    of sd s lose a factor exp(s^2) of their ESS (E[w^2] / E[w]^2 = exp(s^2) for
    log-normal w). Within one fit the design points share their blocks (common
    random numbers), so what moves the weights is the noise of log-likelihood
    DIFFERENCES, small between close points and up to sqrt(2) times this sd
    between distant ones; the CRN surface is also rough (jumps of several nats between neighbouring
    roughness values were measured at 180 rows). Candidates are fitted with
    different block sets, so their score gains carry noise of this order that
    the data se of the gain does not include.
    """
    total = np.asarray(loglik_reps, float).sum(axis=1)
    return float(np.std(total, ddof=1))


def _mixture_log_q(z, counts, logpdfs):
    """log of the deterministic-mixture density at z, relative to the uniform
    on the unit cube: component k drew counts[k] points with log-density
    logpdfs[k] (relative to the same uniform)."""
    terms = [np.log(n) + f(z) for n, f in zip(counts, logpdfs, strict=True) if n]
    return logsumexp(np.stack(terms), axis=0) - np.log(sum(counts))


def _predictive(cand, fw, theta, w, simulated, key, budget, rng, tallies):
    """(E, M) posterior-predictive runouts per entry: ``n_draws`` systematic-
    resampled posterior draws, each simulated with fresh blocks (a key the fit
    never used; their unfinished blocks are counted in ``tallies["predictive"]``).
    With ``n_blocks_check`` = 0 the design's own simulations are resampled."""
    m = budget.n_draws
    u = (rng.uniform() + np.arange(m)) / m
    idx = np.minimum(np.searchsorted(np.cumsum(w), u), len(w) - 1)
    if budget.n_blocks_check > 0:
        fresh = cand.forward(simulated, budget.n_blocks_check, jax.random.fold_in(key, 2))
        runs = fresh.runouts(theta[idx])  # (M, E, n)
        tallies["predictive"] = UnfinishedTally(tuple(map(float, fresh.sizes_m)))
        tallies["predictive"].add(runs, theta[idx], cand.box.names)
    else:
        runs = fw.runouts(theta[idx])
    return pool_draws(runs)


@dataclasses.dataclass
class Discovery:
    """Outcome of the workflow (``discover``).

    Attributes:
        named_effect: the effect named at the first step, against the plain
            baseline ("none": none).
        fits: every fitted model by its label (``model_label``: "none", an
            effect, or the effects of each step joined by "+").
        table: the first step's ranked table (``steps[0]["candidates"]``).
        where_before: where the plain baseline disagrees (``residuals.locate``);
            where_after: the same for the final model (None: nothing named).
        class_sizes_m, row_class: the size classes and each row's class.
        gap_before: the plain baseline's gap; gap_after: the final model's.
        timings_s: seconds per fitted model.
        entries: the simulated (size class, release) groups, or None.
        steps: one record per step (``_step_record``): its baseline, the
            candidates compared, the naming bar, what it named and the gap.
        named_effects: the effects named, in order (the final model's effects).
    """

    named_effect: str
    fits: dict[str, CandidateFit]
    table: list[dict]
    where_before: dict
    where_after: dict | None
    class_sizes_m: np.ndarray
    row_class: np.ndarray
    gap_before: float
    gap_after: float
    timings_s: dict
    entries: Entries | None = None
    steps: list[dict] = dataclasses.field(default_factory=list)
    named_effects: tuple[str, ...] = ()

    @property
    def final_model(self) -> str:
        """The label of the model discovery ends with (``model_label``)."""
        return model_label(self.named_effects)


def model_label(effects) -> str:
    """A model's label: "none" (the baseline) or its effects joined by "+" in the
    order they were named (``calib.model.effects.model_label`` for CRSP's)."""
    return "+".join(effects) or "none"


STOPPING_RULE = ("after an effect is named, the model with it becomes the baseline and the "
                 "remaining candidates are fitted on top of it; discovery stops at the first "
                 "step that names none, when no candidate is left, or after --max-steps steps")
MULTIPLE_TESTING = ("step 1 names the best candidate only if its gain exceeds max(4 nats, "
                    "2 se), the bar whose false-positive rate over the whole candidate set "
                    "was measured on null data (docs/studies.md); each later step raises "
                    "it to z_m se with z_m = Phi^-1(1 - 0.023 / m) over the m candidates it "
                    "compares (Bonferroni at the one-sided level of the 2-se bar, 0.023; "
                    "z = 2.28, 2.43, 2.53 for m = 2-4); a step runs only after the one "
                    "before named an effect (a fixed-sequence procedure)")


def discover(candidates: list[Candidate], obs, profile, key: jax.Array, budget: DiscoveryBudget,
             progress=None, velocities=None, release_tolerance_m: float | None = None,
             release_errors: tuple[float, float] = (0.0, 0.0),
             combine: Callable[[tuple[str, ...]], Candidate] | None = None,
             max_steps: int | None = None) -> Discovery:
    """Run the whole workflow on observations ``obs`` (see module docstring).

    ``candidates[0]`` must be the baseline (effect ``none``). ``velocities``
    (optional, ``calib.files.observations.Velocities``): passage speeds at stations,
    scored with the runouts by every candidate (forward models with
    ``simulate``, i.e. CRSP); the gap metric and the residuals stay on runouts.

    Steps: the first step compares the candidates with the baseline. With
    ``combine`` (effects -> the ``Candidate`` of the baseline with those
    effects added in that order, e.g. ``calib.discovery.candidates.crsp_model``)
    discovery keeps going: a named effect joins the baseline, and the next step
    compares baseline + named + each remaining candidate with baseline +
    named (whose fit is reused), until a step names none, no candidate is
    left, or ``max_steps`` steps ran (None: no limit but those). Without
    ``combine`` (candidates that cannot be combined, the DEM's) there is one
    step. Stopping rule and multiple-testing control: ``STOPPING_RULE``,
    ``MULTIPLE_TESTING`` (module docstring, step 5).

    Releases: where the rows give ``release_x_m`` (and ``release_tolerance_m``
    is not None), every row is simulated from its own point, as ``calib.fit``
    does: rows of one size class whose releases lie within
    ``release_tolerance_m`` share one simulated (size class, release) group
    (``calib.model.entries.Entries.from_rows``; rows without a release start
    at the profile's first vertex), and stop positions for the residual tests
    are each row's release plus its runout. Velocity rows are simulated from the
    median of the rows' releases. Otherwise every block starts at the
    profile's first vertex. Both solvers release each group at its rows' mean
    speed and height where the rows give them; CRSP draws each block's height
    and speed about them with the sds ``release_errors`` (m, m/s: the site's,
    ``calib.files.site``; ``Entries.with_release_errors``). Rows on their own
    profiles (``Observations.profile``) are simulated on them; their stop
    positions enter the residual tests as abscissae of the command's profile
    (our choice: it assumes lines cut alike, e.g. the mean fall lines of
    nearby spots with one margin, as ``calib.field`` users cut them).
    """
    if candidates[0].effect != "none":
        raise ValueError("the first candidate must be the baseline (effect 'none')")
    if max_steps is not None and max_steps < 1:
        raise ValueError(f"max_steps: expected at least 1, got {max_steps}")
    n_run = obs.n_obs
    vel = None
    if velocities is not None and velocities.n_obs:
        class_sizes, all_class = size_classes(np.concatenate([obs.block_size_m,
                                                              velocities.block_size_m]))
        row_class = all_class[:n_run]
        vel_class = all_class[n_run:]
        # velocity rows are their own fold strata (after the runout rows' strata,
        # so the runout rows keep the folds they have without velocities)
        fold = folds(np.concatenate([all_class[:n_run], all_class[n_run:] + class_sizes.size]),
                     budget.k_folds, seed=0)
    else:
        class_sizes, row_class = size_classes(obs.block_size_m)
        vel_class = None
        fold = folds(row_class, budget.k_folds, seed=0)
    entries = _entries(obs, profile, class_sizes, row_class, vel_class, release_tolerance_m,
                       release_errors)
    row_release = None
    if entries is not None:
        row_release = entries.release_x_m[entries.index[:n_run]]
        if vel_class is not None:  # the velocity rows' entries follow the runout rows'
            vel_class = entries.index[n_run:]
        entries = dataclasses.replace(entries, index=entries.index[:n_run])
    if vel_class is not None:
        vel = VelocityRows(velocities.stations_m, velocities.station_index, vel_class,
                           velocities.velocity_m_s, velocities.velocity_sd_m_s)
    fits, timings = {}, {}

    def fit(cand, label, k, warm):
        fits[label] = fit_candidate(cand, obs, class_sizes, row_class, k, budget, fold,
                                    progress, warm=warm, velocities=vel, entries=entries)
        timings[label] = fits[label].seconds

    # step 1 keeps the keys it always had (candidate i: fold_in(key, i))
    fit(candidates[0], "none", jax.random.fold_in(key, 0), None)
    base_cand, named = candidates[0], ()
    remaining = {c.effect: c for c in candidates[1:]}
    steps = []
    while True:  # step 1 always (a baseline alone gets its table), later ones while named
        step = len(steps) + 1
        step_key = key if step == 1 else jax.random.fold_in(key, 1000 + step)
        base = fits[model_label(named)]
        warm = None  # the step's baseline posterior seeds its candidates (not for grids)
        if base_cand.design is None:
            warm = _gaussian_fit(unit_coordinates(base_cand.box)[0](base.theta), base.weights)
        cands = {e: c if step == 1 else combine(named + (e,)) for e, c in remaining.items()}
        for i, (e, c) in enumerate(cands.items(), start=1):
            fit(c, model_label(named + (e,)), jax.random.fold_in(step_key, i), warm)
        steps.append(_step_record(step, named, {e: fits[model_label(named + (e,))]
                                                for e in cands}, base, n_run, vel))
        new = steps[-1]["named"]
        if new == "none" or combine is None or (max_steps is not None and step >= max_steps):
            break
        named, base_cand = named + (new,), cands[new]
        del remaining[new]
        if not remaining:
            break
    if steps[-1]["named"] != "none" and steps[-1]["named"] not in named:
        named = named + (steps[-1]["named"],)  # the last step's, when the loop stopped on it
    base = fits["none"]
    final = fits[model_label(named)]
    rng = np.random.default_rng(0)
    row_entry = None if entries is None else entries.index
    where_before = locate(obs, row_class, class_sizes, base.samples, profile, rng, row_release,
                          row_entry)
    where_after = None if not named else locate(
        obs, row_class, class_sizes, final.samples, profile, np.random.default_rng(0),
        row_release, row_entry)
    return Discovery(steps[0]["named"], fits, steps[0]["candidates"], where_before, where_after,
                     class_sizes, row_class, base.gap, final.gap, timings, entries, steps, named)


def _step_record(step: int, named: tuple[str, ...], cand_fits: dict, base: CandidateFit,
                 n_run: int, vel) -> dict:
    """One step of ``discover``: its candidates scored against its baseline (the
    model with the effects ``named``) and its verdict.

    Keys: ``step``, ``baseline`` (label) and ``baseline_effects``;
    ``candidates``, the ranked table (row ``effect`` "none": the step's
    baseline; others the effect added, ``model`` the label of the model fitted;
    ``delta_vs_none``/``se_delta``: gain over the step's baseline);
    ``n_compared`` (m), ``z`` (``naming_z(m)``), ``threshold_nats`` (the best
    candidate's bar, ``naming_threshold``); ``named`` ("none" or the effect),
    ``gain_nats``, ``se_nats`` (the best candidate's), ``gap_before``,
    ``gap_after`` (the step's baseline, and the model after the step)."""
    table = []
    for eff, f in {"none": base, **cand_fits}.items():
        gains = f.elpd - base.elpd  # per row
        d, se = (0.0, 0.0) if eff == "none" else elpd_difference(f.elpd, base.elpd)
        table.append({"effect": eff, "model": model_label(named + (() if eff == "none"
                                                                   else (eff,))),
                      "score": float(f.elpd.sum()), "delta_vs_none": d,
                      "se_delta": se, "gap": f.gap, "n_params": len(f.names),
                      "ess": f.ess, "loglik_noise_sd_nats": f.loglik_noise_sd_nats,
                      "khat": f.khat, "khat_by_fold": [float(k) for k in f.khat_folds],
                      "psis_flagged_folds": [int(j) for j in
                                             np.flatnonzero(f.khat_folds > KHAT_MAX)]})
        if eff != "none":  # how many rows carry the gain (the se rule is a bar on it)
            table[-1]["effective_rows"] = effective_rows(gains)
            table[-1]["carrying_rows"] = [int(i) for i in carrying_rows(gains)]
        if vel is not None:  # the part of the gain that the speeds carry
            table[-1]["delta_velocity_rows"] = float(gains[n_run:].sum())
    table.sort(key=lambda r: -r["score"])
    m = len(cand_fits)
    # step 1 keeps the 2-se bar whose false-positive rate over the whole candidate
    # set was measured on null data (docs/studies.md); later steps, which no null
    # study covers, raise it Bonferroni-style over the candidates they compare
    m_bar = 1 if step == 1 else m
    best = best_effect(table)
    threshold = naming_threshold(None if best is None else best["se_delta"], m_bar)
    new = best["effect"] if best is not None and best["delta_vs_none"] > threshold else "none"
    for r in table:
        r["clear_gain"] = r["effect"] == new and new != "none"
    return {"step": step, "baseline": model_label(named), "baseline_effects": list(named),
            "n_compared": m, "z": naming_z(m_bar), "threshold_nats": threshold, "named": new,
            "best": None if best is None else best["effect"],
            "gain_nats": None if best is None else best["delta_vs_none"],
            "se_nats": None if best is None else best["se_delta"],
            "gap_before": base.gap,
            "gap_after": cand_fits[new].gap if new != "none" else base.gap,
            "candidates": table}


def _entries(obs, profile, class_sizes, row_class, vel_class, tol_m,
             release_errors=(0.0, 0.0)) -> Entries | None:
    """The simulated (size class, release) groups of ``discover``, None where every
    block starts at the profile's first vertex (no ``release_x_m`` in the rows,
    or ``tol_m`` None). Runout rows first in ``index``, then the velocity rows
    (``vel_class``), whose groups are their size classes at the median of the
    runout rows' releases, released at the solver's default speed and height.
    The rows' tracked heights and speeds carry the sds ``release_errors``."""
    rel = np.asarray(obs.release_x_m, float)
    if tol_m is None or not (np.any(np.isfinite(rel)) or any(obs.profile)):
        return None
    binned = dataclasses.replace(obs, block_size_m=np.asarray(class_sizes)[row_class])
    g = Entries.from_rows(binned, float(profile.x_m[0]), tol_m, profile_of=own_profile
                          ).with_release_errors(*release_errors)
    if vel_class is None:
        return g
    median = float(np.median(g.release_x_m[g.index]))
    used = np.unique(vel_class)
    speed = g.concat(Entries.at_sizes(np.asarray(class_sizes)[used], median,
                                      density_kg_m3=g.density_kg_m3))
    return dataclasses.replace(speed, index=np.concatenate(
        [g.index, g.n + np.searchsorted(used, vel_class)]))
