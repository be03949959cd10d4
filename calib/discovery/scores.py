"""Scores of a calibrated model against observations: held-out log predictive
density (model comparison) and CRPS (the gap metric). NumPy, no simulation.

Held-out predictive score (Vehtari, Gelman & Gabry 2017, "Practical Bayesian
model evaluation using leave-one-out cross-validation and WAIC", Stat. Comput.
27, 1413-1432; K-fold when LOO is too costly, their Sect. 2.5): with the
observations split into K folds, row i's score is

    elpd_i = log p(y_i | y_(-fold(i))) = log sum_k wbar_k^(-f) p(y_i | theta_k)

where theta_k are the design points of the model's fit and wbar^(-f) their
self-normalised importance weights computed WITHOUT the rows of i's fold
(from the training rows' summed log-likelihood as given, ``cv_elpd``'s
``train``: the discovery fits smooth it over the design,
``calib.discovery.candidate_fit``), Pareto-smoothed
(``calib.inference.importance.psis_weights``; Vehtari et al. 2024): each
fold's k-hat is returned with the scores, and a fold above 0.7 has a held-out
score the design cannot be trusted to estimate.
Extra parameters are penalised automatically: a model that over-fits the
training folds predicts the held-out fold worse.

Comparison (same paper, Sect. 5; Sivula, Magnusson & Vehtari 2022, "Uncertainty
in Bayesian leave-one-out cross-validation based model comparison"): the
difference of two models is ``sum_i (elpd_i^A - elpd_i^B)`` with standard error
``sqrt(n var_i(elpd_i^A - elpd_i^B))``; Sivula et al. call differences below
about 4 small. The discrepancy workflow names an effect only when its gain over
the baseline exceeds both 4 and twice its standard error (``ELPD_MIN``,
``Z_MIN``), fixed before any workflow run, the 2 raised when several
candidates are compared (below). A z-se bar depends only on how many rows
carry the gain (``effective_rows``; ``rows_needed``), not on its size.

Several candidates at once (``naming_z``): the rule looks at the best of the m
candidates compared against one baseline, so the chance that one of m effects
without any real gain clears a z-se bar by chance is up to m times that of
one. The bar is raised Bonferroni-style: z_m = Phi^-1(1 - ALPHA / m) with
ALPHA = Phi(-Z_MIN) = 2.3 %, the one-sided level of the 2-se bar for one
candidate (z = 2.00 for one candidate, 2.28 for two, 2.43 for three, 2.53 for
four). Bonferroni's inequality holds whatever the dependence between the
candidates' gains, which share the baseline's scores and are strongly
dependent (Bonferroni bound; Holm 1979, Scand. J. Statist. 6, 65-70, whose
first step it is); the level is nominal, as the normal approximation behind
the se is (Sivula et al. 2022).

CRPS (Gneiting & Raftery 2007, "Strictly proper scoring rules, prediction, and
estimation", JASA 102, 359-378, eq. 21): for a predictive ensemble X_1..X_m and
an observation y, ``CRPS = mean|X - y| - (1/2) mean|X - X'|``, in metres; 0 for a
perfect point forecast.
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp
from scipy.stats import norm

from calib.inference.importance import psis_weights

__all__ = [
    "ALPHA",
    "ELPD_MIN",
    "Z_MIN",
    "best_effect",
    "carrying_rows",
    "crps_ensemble",
    "cv_elpd",
    "effective_rows",
    "elpd_difference",
    "folds",
    "naming_threshold",
    "naming_z",
    "rows_needed",
    "training_sums",
]

ELPD_MIN = 4.0
Z_MIN = 2.0
ALPHA = float(norm.sf(Z_MIN))  # one-sided level of the Z_MIN bar for one candidate


def crps_ensemble(samples: np.ndarray, y: float) -> float:
    """CRPS of the ensemble ``samples`` (m,) at the observation ``y`` (same units)."""
    x = np.sort(np.asarray(samples, float).ravel())
    m = x.size
    k = np.arange(1, m + 1)
    spread = 2.0 * np.sum((2 * k - m - 1) * x) / (m * m)  # mean |X - X'|
    return float(np.mean(np.abs(x - y)) - 0.5 * spread)


def folds(groups: np.ndarray, k: int, seed: int) -> np.ndarray:
    """Fold index of each row: K folds, balanced within each group (e.g. size class).

    With K >= the number of rows this is leave-one-out.
    """
    groups = np.asarray(groups)
    n = groups.size
    if k >= n:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    out = np.empty(n, int)
    start = 0
    for g in np.unique(groups):
        idx = np.flatnonzero(groups == g)
        rng.shuffle(idx)
        out[idx] = (start + np.arange(idx.size)) % k
        start += idx.size
    return out


def training_sums(loglik: np.ndarray, fold: np.ndarray) -> np.ndarray:
    """(F, N) the summed log-likelihood of each fold's training rows (the rows
    of the other folds) at the N design points, folds in the order of
    ``np.unique(fold)``; with (N, n_obs) ``loglik`` as in ``cv_elpd``."""
    loglik = np.asarray(loglik, float)
    return np.stack([loglik[:, fold != f].sum(axis=1) for f in np.unique(fold)])


def cv_elpd(loglik: np.ndarray, log_q: np.ndarray, fold: np.ndarray,
            train: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Held-out log predictive density of each row, and the k-hat of each fold.

    Args:
        loglik: (N, n_obs) log p(y_i | theta_k) at the N design points.
        log_q: (N,) log of the design's sampling density relative to the prior
            (importance weight = prior / proposal = exp(-log_q) times the likelihood).
        fold: (n_obs,) fold of each row.
        train: (F, N) the training log-likelihood of each fold that the weights
            use (e.g. ``training_sums`` smoothed over the design,
            ``calib.inference.loglik_emulator.smoothed_at_design``); None: the
            simulated sums themselves. The held-out rows are always scored by
            their simulated ``loglik``.

    Returns:
        (elpd (n_obs,), khat (F,)): elpd_i, and the Pareto k-hat of the training
        weights of each fold, in the order of ``np.unique(fold)``.

    A design point where some row has log p = -inf (no finished block of its
    size, ``calib.inference.likelihood``) gets its training weight from the training rows
    directly, so -inf on a held-out row does not make the weight undefined.
    """
    out = np.empty(loglik.shape[1])
    total = loglik.sum(axis=1)
    fin = np.isfinite(total)
    ids = np.unique(fold)
    khat = np.empty(ids.size)
    for j, f in enumerate(ids):
        held = fold == f
        if train is None:
            t = np.empty_like(total)
            t[fin] = total[fin] - loglik[fin][:, held].sum(axis=1)
            t[~fin] = loglik[~fin][:, ~held].sum(axis=1)
        else:
            t = np.asarray(train[j], float)
        w, khat[j] = psis_weights(t - log_q)
        with np.errstate(divide="ignore"):  # weight 0: log 0 = -inf, as meant
            logw = np.log(w)
        out[held] = logsumexp(logw[:, None] + loglik[:, held], axis=0)
    return out, khat


def elpd_difference(elpd_a: np.ndarray, elpd_b: np.ndarray) -> tuple[float, float]:
    """(sum of A - B, its standard error sqrt(n var(A_i - B_i)))."""
    d = np.asarray(elpd_a) - np.asarray(elpd_b)
    n = d.size
    se = float(np.sqrt(n * np.var(d, ddof=1))) if n > 1 else float("nan")
    return float(d.sum()), se


def effective_rows(diff: np.ndarray) -> float:
    """Effective number of rows carrying a score difference: ``(sum d)^2 / sum d^2``.

    n for n equal gains, 1 when one row carries everything, small too when the
    rows disagree and cancel; nan for an all-zero difference. The 2-se rule is a
    rule on this number alone: with ``se = sqrt(n var(d))`` (ddof 1) one has
    ``(sum d / se)^2 = (n - 1) n_eff / (n - n_eff)``, so a positive gain exceeds
    z standard errors exactly when ``n_eff > rows_needed(n, z)``, whatever its
    size in nats.
    """
    d = np.asarray(diff, float)
    ss = float(np.sum(d * d))
    return float(d.sum() ** 2 / ss) if ss > 0 else float("nan")


def rows_needed(n: int, z: float = Z_MIN) -> float:
    """The effective rows (``effective_rows``) a positive gain over n rows needs to
    exceed z standard errors: ``z^2 n / (n - 1 + z^2)`` (3.8 for n = 60, z = 2)."""
    return z * z * n / (n - 1 + z * z)


def carrying_rows(diff: np.ndarray, share: float = 0.9) -> np.ndarray:
    """Indices of the fewest rows, largest difference first, whose differences sum
    to at least ``share`` of the total; empty when the total is not positive."""
    d = np.asarray(diff, float)
    total = d.sum()
    if not total > 0:
        return np.zeros(0, int)
    order = np.argsort(-d, kind="stable")
    k = int(np.searchsorted(np.cumsum(d[order]), share * total)) + 1
    return order[:min(k, d.size)]


def naming_z(n_compared: int = 1) -> float:
    """The se multiple of the naming bar when the best of ``n_compared``
    candidates is named: ``Z_MIN`` for one, else Phi^-1(1 - ALPHA / n_compared)
    (Bonferroni; module docstring)."""
    if n_compared <= 1:
        return Z_MIN
    return float(norm.isf(ALPHA / n_compared))


def naming_threshold(se_delta: float | None, n_compared: int = 1) -> float:
    """The gain (nats) an effect must exceed to be named, the best of
    ``n_compared`` candidates: max(``ELPD_MIN``, ``naming_z(n_compared)`` se), or
    ``ELPD_MIN`` when the se is unknown (None or not finite)."""
    if se_delta is None or not np.isfinite(se_delta):
        return ELPD_MIN
    return max(ELPD_MIN, naming_z(n_compared) * se_delta)


def best_effect(table: list[dict]) -> dict | None:
    """The row the naming rule looks at: the effect (not ``none``) with the
    largest ``delta_vs_none``; None if there is no effect."""
    return max((r for r in table if r["effect"] != "none"), key=lambda r: r["delta_vs_none"],
               default=None)
