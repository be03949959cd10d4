"""One candidate of the discrepancy workflow, fitted and scored.

Every candidate (the baseline ``none`` and each effect of ``calib.model.effects``)
is fitted the same way: a Bayesian fit by adaptive importance sampling over
a simulated design. Every stage draws in the prior box's warped coordinates
(``calib.model.warp``: log S, log(1 - Kt), tan(phi_r), scaled to the unit
cube; ``calib.model.warp.unit_coordinates``), and each draw's density
carries the change of variables back to the uniform prior in theta. Stage 0 is a scrambled Sobol
design, one half uniform in theta, the other uniform in the warped cube
(a defensive pair: the first covers a posterior the warp would thin out).
For an effect, a warm stage follows: the baseline's parameters drawn from a
Gaussian fitted to the baseline's posterior, the effect's uniformly over
their box. Each later stage draws points fitted to the posterior so far,
truncated to the box: with the smoothed log-likelihood (below), from a
multivariate Student t of ``PROPOSAL_DF`` = 4 degrees of freedom centred and
scaled by the Gaussian fitted to the log-likelihood GP's posterior over a
cloud of ``SURROGATE_POINTS`` points (``_surrogate_gaussian``: covariance
inflated x4 plus (0.005)^2 in unit coordinates); otherwise from the Gaussian
fitted to the weighted design points (inflated x4 plus (0.05)^2). The t's
heavier tails are our choice (measured in docs/studies.md, "Student t
proposals for the adaptive stages"): the folds' training posteriors and the
posteriors one Gaussian does not describe (five and six parameters, a forest
belt's position) reach past a Gaussian stage's tails, where only the first,
broad stages put points, and a fold's weights there rested on a few of them
(Pareto k-hat above the bar in 25 of 120 folds at 180 rows, 2 of 120 with
the t). The simulated sums' path (the quick budgets) keeps the Gaussian: its
weights collapse onto a few points either way, and on the toy model of
tests/test_discovery_sequence.py the t's points spent away from the core
made a decoy effect's score +9.1 ± 2.3 nats instead of +2.4 ± 2.3. All
stages are one deterministic-mixture proposal
(Owen & Zhou 2000, "Safe and effective importance sampling", JASA 95,
135-143), so the self-normalised weights ``w_k ~ L(theta_k) p(theta_k) /
q_mix(theta_k)`` target the posterior under the uniform prior.

L(theta_k) is not the simulated likelihood itself but its GP-smoothed value
at the design point (``calib.inference.loglik_emulator.smoothed_at_design``:
the GP of the summed log-likelihood that ``calib.fit`` samples, fitted to
the design's points, with the Monte Carlo variance measured at the Sobol
stage's best point over ``noise_reps`` block sets as each point's noise),
for the sum over all rows and for each fold's training rows (our choice,
measured in docs/studies.md, "Smoothed weights for the discovery folds"):
the simulated sums carry 1-3 nats of noise, and weights that are their
exponential collapse onto a few lucky points (a fold's Pareto k-hat above
0.7 in half the folds at 60 rows, nearly all at 180) even where the design
covers the posterior. The held-out rows themselves are scored by their
simulated likelihoods. At the quick budgets
(``DiscoveryBudget.smooth_loglik``) the simulated sums are used. On a fixed
grid (the DEM's, a few dozen points) the weights and the scores are those of
``calib.discovery.grid_emulation``: every row's log-likelihood emulated
between the grid's points, the posterior and the folds weighted on a dense
cloud of emulated points, the held-out rows scored by their emulated values.
Every set of
weights (each stage's fit, the posterior, each fold's training weights of
step 3) is Pareto-smoothed (``calib.inference.importance.psis_weights``); its k-hat
is reported per candidate (``khat``) and per fold (``khat_by_fold``), and a
fold above the bar of the design's size S, min(0.7, 1 - 1/log10 S)
(``calib.inference.importance.khat_threshold``, Vehtari et al. 2024), is flagged
(``psis_flagged_folds``): its held-out scores are unreliable.

Fold stages (smoothed path): a fold above that bar gets a stage of its own,
``DiscoveryBudget.n_fold_refine`` points from the Student t fitted, as an
adaptive stage's is, to that fold's training posterior under the
log-likelihood GP (``_fold_stages``), joined to the same mixture; the
weights and scores are then recomputed, for up to
``DiscoveryBudget.fold_rounds`` rounds. Our choice among the routes to
held-out scores that do not rest on a few points: a fold's training
posterior is not the full posterior, and where one proposal for all of them
leaves a fold's posterior thinly covered, points drawn for that fold are the
cheapest cure (a stage costs one GP fit and 64 simulations; refitting the
fold costs a whole design of 512), and one mixture keeps every weight, the
posterior's too, valid. Measured in docs/studies.md, "Fold stages: points for
the folds above the bar".

Fresh draws (smoothed path): a fold still above the bar after those rounds
is scored on ``DiscoveryBudget.n_fold_draws`` simulated draws of its training
posterior under the log-likelihood GP instead of the design's weights
(``_fresh_draw_scores`` says how and why); the draws are not joined to the
design, so the posterior's weights and every other fold are unchanged.
Runouts are
simulated with common random numbers (``calib.model.forward``), and the
likelihood is ``calib.inference.likelihood``'s, the one ``calib.fit`` uses (points:
the tolerance as kernel; intervals: the Silverman width). Optional passage
speeds at stations (``calib.files.observations.Velocities``) add rows scored by
``calib.inference.likelihood.velocity_log_likelihood`` from the same simulations.
The workflow that compares the candidates and names one is
``calib.discovery.discrepancy``; the budgets are ``calib.inference.budget``.
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

from calib.discovery.grid_emulation import grid_scores
from calib.discovery.loglik_noise import loglik_noise_sd, measured_noise_var
from calib.discovery.proposals import PROPOSAL_DF, gaussian_fit, mixture_log_q, proposal
from calib.discovery.residuals import point_view
from calib.discovery.scores import crps_ensemble, cv_elpd, training_sums
from calib.inference.budget import DiscoveryBudget
from calib.inference.emulator import predict_batch
from calib.inference.importance import (
    KHAT_MAX,
    MIN_POINTS,
    ess,
    khat_threshold,
    psis_weights,
    weighted_quantile,
)
from calib.inference.likelihood import (
    VelocityRows,
    log_likelihood,
    observed_rows,
    velocity_rows_loglik,
)
from calib.inference.loglik_emulator import fit_loglik_emulator, smoothed_at_design
from calib.inference.predictive_check import pool_draws
from calib.model.entries import Entries
from calib.model.priors import Box
from calib.model.unfinished import UnfinishedTally, unfinished_record, warn_unfinished
from calib.model.warp import unit_coordinates

__all__ = ["GAP_METRIC", "Candidate", "CandidateFit", "class_samples",
           "fit_candidate", "gap"]

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
            On a fixed grid (the DEM's), the points of the cloud on which the
            rows are emulated between the grid's points
            (``calib.discovery.grid_emulation``), and their mixture density.
        loglik: (N, n_rows) pointwise log-likelihood at those points: the
            runout rows, then the passage-velocity rows (if any); simulated at
            design points, emulated on a fixed grid's cloud.
        weights: (N,) posterior weights (all rows), Pareto-smoothed.
        ess: effective sample size of the weights.
        elpd: (n_rows,) held-out log predictive density of each row (same order).
        khat: Pareto k-hat of the posterior weights; khat_folds: (K,) that of
            each fold's training weights (``calib.discovery.scores.cv_elpd``); NaN where
            not estimated (``calib.inference.importance``).
        estimate, q05, q95: weighted posterior mean and 90 % interval per parameter;
            best: the point of highest weight (a fixed grid: of its cloud).
        samples: (E, M) posterior-predictive runouts per simulated entry (a size
            class, or a (size class, release) group; fresh blocks).
        class_samples: (C, M') the same pooled per size class: each row of the
            class contributes its entry's samples (for figures).
        gap_by_class: (C,) mean CRPS per class, m; gap: their mean, m.
        loglik_noise_sd_nats: Monte Carlo sd of the summed log-likelihood at
            ``best`` over ``noise_reps`` independent block sets of the fit's size
            (nan if not measured); see
            ``calib.discovery.loglik_noise.loglik_noise_sd``.
        seconds: wall time of the fit.
        smoothing_noise_var_nats2: the Monte Carlo variance of the summed
            log-likelihood that the weights' GP smoothing assumed (measured at
            the Sobol stage's best point over ``noise_reps`` block sets); nan
            where the weights use the simulated sums (fixed grids,
            ``DiscoveryBudget.smooth_loglik`` off).
        unfinished: counts of unfinished blocks per stage (design, predictive,
            noise) and the warning text (``calib.model.unfinished.unfinished_record``).
        khat_bar: the k-hat bar of the design's size S, min(0.7, 1 - 1/log10 S)
            (``calib.inference.importance.khat_threshold``); a fold above it is
            flagged.
        n_fold_points: design points the fold stages added (module docstring).
        fresh_draw_folds: the folds scored on fresh draws of their training
            posterior (``_fresh_draw_scores``); their ``khat_folds`` are those
            draws' weights'.
        n_simulated: the points simulated (the design's, with the fold
            stages'; a fixed grid's points).
        grid_emulator: a fixed grid's row emulator (``calib.discovery.grid_emulation``):
            its trend's degree, the error of the rows' values at the grid's
            inner points left out of its fit (nats, root mean square), its
            kernel's length scales (unit coordinates), signal and noise sd
            (standardised); None on an adaptive design.
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
    smoothing_noise_var_nats2: float = float("nan")
    khat_bar: float = KHAT_MAX
    n_fold_points: int = 0
    fresh_draw_folds: tuple[int, ...] = ()
    n_simulated: int = 0
    grid_emulator: dict | None = None


@jax.jit
def _loglik_design(runs, row_class, y, sd, lo, hi, is_interval):
    """(N, n_obs) log-likelihood of every row at every design point: the
    observation model of ``calib.fit`` (``calib.inference.likelihood``, no extra variance)."""
    return jax.vmap(lambda r: log_likelihood(r[row_class], y, sd, lo, hi, is_interval))(runs)


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
    ``entry`` indexes the entries). ``entries``: what the forward model
    simulates, (size, release) groups with the entry of each runout row
    (``index``); None: one entry per size class ``class_sizes_m``, released at
    the profile's first vertex (``calib.model.forward.as_entries``).
    """
    t0 = time.perf_counter()
    box = cand.box
    dim = box.dim
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel()[-1])
    vel = velocities if velocities is not None and velocities.n_obs else None
    st_kw = {} if vel is None else {"stations_x_m": vel.stations_x_m}
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
    tallies = {"design": UnfinishedTally(tuple(map(float, entry_sizes)))}
    loglik = _row_loglik(obs, row_entry, vel)
    design = _design(cand, fw, loglik, budget, rng, warm, vel, tallies, progress, key)
    smoothed = budget.smooth_loglik and cand.design is None
    if cand.design is not None:  # fixed grids: the rows emulated between the points
        g = grid_scores(design.z, design.ll, fold, rng)
        z, ll, log_q, noise_var = g.z, g.ll, g.log_q, 0.0
        w, khat, elpd, khat_folds, fresh = g.weights, g.khat, g.elpd, g.khat_folds, ()
        emulator = g.record()
    else:
        w, khat, elpd, khat_folds, fresh = _scores_covering_folds(
            design, fold, budget.n_fold_refine, budget.fold_rounds if smoothed else 0,
            smoothed, rng, progress, cand.effect, budget.n_fold_draws)
        z, ll, log_q, noise_var = design.z, design.ll, design.log_q(), design.noise_var
        emulator = None
    theta = design.to_theta(z)
    est = w @ theta
    q05 = np.array([weighted_quantile(theta[:, j], w, 0.05) for j in range(dim)])
    q95 = np.array([weighted_quantile(theta[:, j], w, 0.95) for j in range(dim)])
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
        tallies.setdefault("noise", UnfinishedTally(tuple(map(float, entry_sizes))))
        tallies["noise"].add(reps[0], np.broadcast_to(best, (budget.noise_reps, dim)),
                             box.names)
        noise = loglik_noise_sd(loglik(*reps))
    record = unfinished_record(tallies, f"candidate {cand.effect!r}")
    warn_unfinished(record)
    return CandidateFit(cand.effect, box.names, theta, log_q, ll, w, ess(w),
                        elpd, est, q05, q95, best, samples, gap_c, gap_m, noise,
                        time.perf_counter() - t0, record, khat, khat_folds, per_class,
                        float(noise_var) if smoothed else float("nan"),
                        khat_threshold(z.shape[0]), int(sum(design.counts[design.n_main:])),
                        fresh, int(design.z.shape[0]), emulator)


def _weights_and_scores(z, ll, log_q, fold, noise_var: float, smooth: bool = True):
    """The posterior weights, their k-hat, the held-out scores and the folds'
    k-hats (module docstring): with ``smooth``, on the adaptive design, from
    the log-likelihood GP's smoothed sums (all rows, and each fold's training
    rows, whose noise variance is ``noise_var`` scaled by their share of the
    rows; ``_smoothed``); otherwise (the quick budgets) from the simulated
    sums. A fixed grid's are ``calib.discovery.grid_emulation``'s."""
    if not smooth:
        w, khat = psis_weights(ll.sum(axis=1) - log_q)
        return (w, khat) + cv_elpd(ll, log_q, fold)
    sums = np.concatenate([ll.sum(axis=1)[None], training_sums(ll, fold)])
    n_rows = np.array([ll.shape[1]] + [int(np.sum(fold != f)) for f in np.unique(fold)])
    sums = _smoothed(z, sums, n_rows, noise_var)
    w, khat = psis_weights(sums[0] - log_q)
    elpd, khat_folds = cv_elpd(ll, log_q, fold, sums[1:])
    return w, khat, elpd, khat_folds


def _smoothed(z, sums, n_rows, noise_var: float) -> np.ndarray:
    """``sums`` (S, N) over ``n_rows`` (S,) rows each, smoothed over the design
    z by the log-likelihood GP (``calib.inference.loglik_emulator.smoothed_at_design``;
    each sum's noise variance ``noise_var`` times its share of the rows, the
    noise of a sum of rows growing with their number); as simulated where the
    design has too few points for it (``MIN_POINTS``)."""
    if z.shape[0] < MIN_POINTS:
        return sums
    nv = noise_var * n_rows / n_rows[0]
    return smoothed_at_design(z, sums, n_rows, nv[:, None])


def _row_loglik(obs, row_entry, vel: VelocityRows | None):
    """(runouts (N, E, n), speeds) -> (N, n_rows) pointwise log-likelihood: the
    runout rows (each reads its entry), then the passage-velocity rows."""
    y, sd, lo, hi, is_int = observed_rows(obs)
    rc = jnp.asarray(row_entry)

    def loglik(runs, speeds):
        ll = np.asarray(_loglik_design(jnp.asarray(runs), rc, y, sd, lo, hi, is_int))
        if vel is None:
            return ll
        return np.concatenate([ll, np.asarray(velocity_rows_loglik(speeds, vel))], axis=1)

    return loglik


@dataclasses.dataclass
class _Design:
    """A candidate's simulated design, one deterministic mixture of stages.

    z: (N, p) unit coordinates; ll: (N, n_rows) pointwise log-likelihood;
    counts, logpdfs: each stage's number of points and log density relative to
    the uniform on the unit cube; log_jac: z -> log |d theta / d z| of the
    warped coordinates relative to the uniform prior in theta; to_theta: z ->
    theta; noise_var: the Monte Carlo variance of the summed log-likelihood,
    nats^2, measured at the Sobol stage's best point over ``noise_reps`` block
    sets (0 where not measured); simulate: z -> (len(z), n_rows) loglik;
    n_main: the stages of the main design (the fold stages come after them).
    """

    z: np.ndarray
    ll: np.ndarray
    counts: list
    logpdfs: list
    log_jac: Callable
    to_theta: Callable
    noise_var: float
    simulate: Callable
    n_main: int = 0

    def log_q(self) -> np.ndarray:
        """(N,) the mixture's log density relative to the prior."""
        return mixture_log_q(self.z, self.counts, self.logpdfs) + self.log_jac(self.z)

    def add(self, new: np.ndarray, logpdf: Callable) -> None:
        """Simulate the stage ``new`` drawn from ``logpdf`` and join it to the mixture."""
        self.ll = np.concatenate([self.ll, self.simulate(new)])
        self.z = np.concatenate([self.z, new])
        self.counts.append(new.shape[0])
        self.logpdfs.append(logpdf)


def _scores_covering_folds(design: _Design, fold: np.ndarray, n_new: int, rounds: int,
                           smoothed: bool, rng, progress=None, effect: str = "",
                           n_draws: int = 0):
    """``_weights_and_scores`` of the design, after up to ``rounds`` rounds of
    fold stages (``_fold_stages``, ``n_new`` points per flagged fold) while some
    fold's k-hat lies above ``khat_threshold`` of the design's size; then, with
    ``smoothed`` and ``n_draws``, every fold still above it scored on
    ``n_draws`` fresh draws (``_fresh_draw_scores``: its rows' scores and its
    k-hat, that of the draws' weights, replaced).

    Returns (weights, k-hat, elpd, fold k-hats, the folds scored on fresh draws)."""
    scores = _weights_and_scores(design.z, design.ll, design.log_q(), fold, design.noise_var,
                                 smoothed)
    for _ in range(rounds):
        flagged = np.flatnonzero(scores[3] > khat_threshold(design.z.shape[0]))
        if not flagged.size:
            break
        _fold_stages(design, fold, flagged, n_new, rng, progress, effect)
        scores = _weights_and_scores(design.z, design.ll, design.log_q(), fold,
                                     design.noise_var, smoothed)
    w, khat, elpd, khat_folds = scores
    flagged = np.flatnonzero(khat_folds > khat_threshold(design.z.shape[0]))
    if not (smoothed and n_draws and flagged.size):
        return w, khat, elpd, khat_folds, ()
    elpd, khat_folds = elpd.copy(), khat_folds.copy()
    ids = np.unique(fold)
    for j, (held_elpd, khat_j) in zip(flagged, _fresh_draw_scores(design, fold, flagged,
                                                                  n_draws, rng), strict=True):
        elpd[fold == ids[j]] = held_elpd
        khat_folds[j] = khat_j
    return w, khat, elpd, khat_folds, tuple(int(j) for j in flagged)


FOLD_CLOUD_POINTS = 16384  # the GP-weighted cloud of ``_fresh_draw_scores``


def _fresh_draw_scores(design: _Design, fold: np.ndarray, flagged: np.ndarray,
                       n_draws: int, rng) -> list[tuple[np.ndarray, float]]:
    """Held-out scores of the ``flagged`` folds from fresh draws of each fold's
    training posterior, not from the design's importance weights.

    For fold f: the log-likelihood GP is fitted to the design's sums over the
    fold's training rows (``_surrogate_fit``: noise ``noise_var`` times their
    share of the rows); ``FOLD_CLOUD_POINTS`` points from the Student t
    (``PROPOSAL_DF``) fitted to that GP's posterior are weighted by exp(GP
    mean) times the prior over their density (Pareto-smoothed), ``n_draws``
    of them taken by systematic resampling and each simulated (the design's
    forward model and blocks); a held-out row i of f scores

        elpd_i = log (1/M) sum_m p(y_i | theta_m),  theta_m ~ p_GP(theta | y_(-f))

    with p(y_i | theta_m) simulated. Returns per fold (elpd of its rows, the
    k-hat of the cloud's weights).

    Why (our choice; measured in docs/studies.md, "Fresh draws for the folds
    the design cannot weight"): where the design's points do not cover a
    fold's training posterior, the importance weights of its score rest on a
    few points, and adding points near it (the fold stages) can move the
    weights' tail instead of filling it. The training posterior under the
    GP is the one the design's weights already use; drawing from it costs
    GP evaluations only, and the held-out rows are scored by simulation at
    the draws, with no importance weight on a simulated likelihood. A K-fold
    score of a predictive fitted to the training rows alone is proper
    whatever that fit's approximation; it shares with the full data where
    the design's points lie, not their values.
    """
    log_q = design.log_q()
    sums = training_sums(design.ll, fold)
    ids = np.unique(fold)
    n_rows = design.ll.shape[1]
    u = (rng.uniform() + np.arange(n_draws)) / n_draws
    out = []
    for j in flagged:
        held = fold == ids[j]
        n_train = int(np.sum(~held))
        mean, cov, mean_ll = _surrogate_fit(design.z, sums[j], log_q,
                                            design.noise_var * n_train / n_rows, n_train,
                                            rng, design.log_jac)
        cloud, logpdf = proposal(mean, cov, rng, FOLD_CLOUD_POINTS, design.z.shape[1],
                                 df=PROPOSAL_DF)
        w, khat = psis_weights(mean_ll(cloud) - logpdf(cloud) - design.log_jac(cloud))
        ll = design.simulate(cloud[_systematic(w, u)])
        out.append((logsumexp(ll[:, held], axis=0) - np.log(n_draws), float(khat)))
    return out


def _fold_stages(design: _Design, fold: np.ndarray, flagged: np.ndarray, n_new: int, rng,
                 progress, effect: str) -> None:
    """One adaptive stage of ``n_new`` points per flagged fold, drawn from the
    Student t (``PROPOSAL_DF``) fitted to that fold's training posterior under
    the log-likelihood GP (``_surrogate_gaussian`` on the fold's training sums,
    noise ``noise_var`` times their share of the rows), joined to the mixture
    (module docstring)."""
    log_q = design.log_q()
    sums = training_sums(design.ll, fold)
    n_rows = design.ll.shape[1]
    stages = []  # every flagged fold's proposal from the same design, then simulated
    for j in flagged:
        n_train = int(np.sum(fold != np.unique(fold)[j]))
        mean, cov = _surrogate_gaussian(design.z, sums[j], log_q,
                                        design.noise_var * n_train / n_rows, n_train, rng,
                                        design.log_jac)
        stages.append(proposal(mean, cov, rng, n_new, design.z.shape[1], df=PROPOSAL_DF))
    for new, logpdf in stages:
        design.add(new, logpdf)
        if progress:
            progress(effect, design.z.shape[0], design.z.shape[0])


def _design(cand: Candidate, fw, loglik, budget: DiscoveryBudget, rng, warm, vel, tallies,
            progress, key) -> _Design:
    """The simulated design of one candidate (module docstring): a fixed grid, or
    the Sobol pair, the warm stage and the adaptive stages, one deterministic
    mixture (``_Design``)."""
    box, dim = cand.box, cand.box.dim

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
            return np.zeros(z.shape[0])

    if cand.design is not None:
        z = box.to_unit(np.atleast_2d(cand.design()))
        parts = []
        for i in range(0, z.shape[0], 8):  # in pieces, for the progress bar
            parts.append(simulate(z[i:i + 8]))
            if progress:
                progress(cand.effect, min(i + 8, z.shape[0]), z.shape[0])
        return _Design(z, np.concatenate(parts), [z.shape[0]], [log_jac], log_jac, to_theta,
                       0.0, simulate, 1)
    total = budget.n_design - (budget.n_warm if warm is None else 0)
    # stage 0, a defensive pair: one half uniform in theta, one half uniform in
    # the warped coordinates (density -log_jac and 0 relative to the latter)
    sob = qmc.Sobol(dim, scramble=True, seed=rng).random(budget.n_sobol)
    n_theta = budget.n_sobol // 2
    z = np.concatenate([to_z(box.from_unit(sob[:n_theta])), sob[n_theta:]])
    ll = simulate(z)
    if progress:
        progress(cand.effect, budget.n_sobol, total)
    noise_var = (measured_noise_var(fw, loglik, to_theta(z[np.argmax(ll.sum(axis=1))]), budget, key,
                            tallies, box.names) if budget.smooth_loglik else 0.0)
    logpdfs = [lambda z: -log_jac(z), lambda z: np.zeros(z.shape[0])]
    counts = [n_theta, budget.n_sobol - n_theta]
    stages = ([("warm", budget.n_warm)] if warm is not None and budget.n_warm else []) + \
        [("refine", n) for n in budget.n_refine]
    for kind, n_new in stages:
        log_q = mixture_log_q(z, counts, logpdfs) + log_jac(z)
        if kind == "warm":
            new, logpdf = proposal(warm[0], warm[1], rng, n_new, dim)
        else:
            total = ll.sum(axis=1)
            if budget.smooth_loglik and z.shape[0] >= MIN_POINTS:
                mean, cov = _surrogate_gaussian(z, total, log_q, noise_var, ll.shape[1], rng,
                                                log_jac)
                df = PROPOSAL_DF
            else:
                mean, cov = gaussian_fit(z, psis_weights(total - log_q)[0])
                df = None
            new, logpdf = proposal(mean, cov, rng, n_new, dim, df=df)
        logpdfs.append(logpdf)
        counts.append(n_new)
        z = np.concatenate([z, new])
        ll = np.concatenate([ll, simulate(new)])
        if progress:
            progress(cand.effect, sum(counts), total)
    return _Design(z, ll, counts, logpdfs, log_jac, to_theta, noise_var, simulate, len(counts))


# the cloud on which an adaptive stage's proposal is fitted to the log-likelihood
# GP's posterior (``_surrogate_gaussian``), and its fit's inflation and floor
SURROGATE_POINTS = 4096
SURROGATE_ROUNDS = 2
SURROGATE_INFLATE, SURROGATE_FLOOR = 2.0, 0.005


def _surrogate_gaussian(z, total, log_q, noise_var: float, n_rows: int, rng, log_jac):
    """``_surrogate_fit``'s (mean, covariance)."""
    return _surrogate_fit(z, total, log_q, noise_var, n_rows, rng, log_jac)[:2]


def _surrogate_fit(z, total, log_q, noise_var: float, n_rows: int, rng, log_jac):
    """The next adaptive stage's Gaussian (mean, covariance in unit coordinates),
    fitted to the posterior under the log-likelihood GP instead of to the
    design's few weighted points.

    The GP of the summed log-likelihood (``calib.inference.loglik_emulator``,
    the one ``calib.fit`` samples; each point's noise ``noise_var``) is fitted
    to the design (z, ``total``). A first Gaussian is the design's, weighted by
    the GP's mean at its points (``gaussian_fit``: inflated x4 plus
    (0.05)^2); then, ``SURROGATE_ROUNDS`` times, ``SURROGATE_POINTS`` points
    are drawn from the current Gaussian (truncated to the cube), weighted by
    exp(GP mean) times the prior over their density (Pareto-smoothed,
    ``psis_weights``), and the Gaussian refitted to them with covariance
    inflated by ``SURROGATE_INFLATE``^2 plus ``SURROGATE_FLOOR``^2.

    Why (our choice, measured in docs/studies.md, "Proposals fitted to the
    log-likelihood GP"): with 180 rows a posterior's sd in unit coordinates
    (0.008-0.03) lies below the 0.05 floor a fit to the design's points
    needs (their weights rest on a few points, ESS 5-8 of 384, and a smaller
    floor made the folds' k-hat worse), so the design's points missed it; the
    GP's mean costs nothing per point, and a cloud of thousands of points
    measures the posterior's spread that the design alone cannot.

    Returns (mean, covariance, the GP's mean log-likelihood as a function of
    (n, p) unit coordinates).
    """
    d = z.shape[1]
    emu = fit_loglik_emulator(z, total, np.full(z.shape[0], noise_var), np.zeros(d),
                              np.ones(d), n_rows)

    def mean_ll(x):
        return np.asarray(predict_batch(emu, jnp.asarray(x))[0])

    mean, cov = gaussian_fit(z, psis_weights(mean_ll(z) - log_q)[0])
    for _ in range(SURROGATE_ROUNDS):
        cloud, logpdf = proposal(mean, cov, rng, SURROGATE_POINTS, d)
        log_w = mean_ll(cloud) - logpdf(cloud) - log_jac(cloud)
        mean, cov = gaussian_fit(cloud, psis_weights(log_w)[0], inflate=SURROGATE_INFLATE,
                                 floor=SURROGATE_FLOOR)
    return mean, cov, mean_ll


def _systematic(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Systematic resampling: indices of weights ``w`` at positions ``u`` in [0, 1)."""
    return np.minimum(np.searchsorted(np.cumsum(w), u), len(w) - 1)


def _predictive(cand, fw, theta, w, simulated, key, budget, rng, tallies):
    """(E, M) posterior-predictive runouts per entry: ``n_draws`` systematic-
    resampled posterior draws, each simulated with fresh blocks (a key the fit
    never used; their unfinished blocks are counted in ``tallies["predictive"]``).
    With ``n_blocks_check`` = 0 the design's own simulations are resampled."""
    m = budget.n_draws
    idx = _systematic(w, (rng.uniform() + np.arange(m)) / m)
    if budget.n_blocks_check > 0:
        fresh = cand.forward(simulated, budget.n_blocks_check, jax.random.fold_in(key, 2))
        runs = fresh.runouts(theta[idx])  # (M, E, n)
        tallies["predictive"] = UnfinishedTally(tuple(map(float, fresh.sizes_m)))
        tallies["predictive"].add(runs, theta[idx], cand.box.names)
    else:
        runs = fw.runouts(theta[idx])
    return pool_draws(runs)


