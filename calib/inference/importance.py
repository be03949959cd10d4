"""Self-normalised importance weights, Pareto-smoothed (PSIS), with the k-hat
diagnostic. NumPy; the tail fit is ArviZ's (``arviz_stats``).

Given log importance ratios log r_k = log L(theta_k) + log p(theta_k) -
log q(theta_k) at N points, the self-normalised weights are w_k = r_k / sum_j
r_j. PSIS (Vehtari, Simpson, Gelman, Yao & Gabry 2024, "Pareto smoothed
importance sampling", JMLR 25(72), 1-58) replaces the M = min(N/5,
3 sqrt(N)) largest ratios by the expected order statistics of a generalized
Pareto distribution fitted to them (Zhang & Stephens 2009, with a weak prior),
truncated at the largest raw ratio, then normalises. Its shape estimate k-hat
says how far the estimate can be trusted (same paper): below 0.5
the raw weights have finite variance; up to 0.7 PSIS is reliable with a
practical number of points; above ``KHAT_MAX`` = 0.7 the weighted estimates
(here: the posterior summaries and the held-out scores built on them) are
unreliable, and the design needs more points where the posterior lives. With
S points the same paper's bar is lower, min(0.7, 1 - 1 / log10 S)
(``khat_threshold``; 0.631 at S = 512): above it the S points are too few for
the estimate's error to fall at its usual rate.

Not estimated (k-hat NaN, raw weights returned) with fewer than
``MIN_POINTS`` = 25 points of finite weight, since the tail fit needs at least
5 of them, or when all tail ratios are equal. When the M largest ratios span
more than the float range (exp underflows: one point carries all the weight),
k-hat is +inf and the raw weights are returned.
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

__all__ = ["KHAT_MAX", "MIN_POINTS", "ess", "khat_threshold", "psis_weights",
           "weighted_quantile"]

KHAT_MAX = 0.7
MIN_POINTS = 25
_EXP_RANGE = 700.0  # nats; exp(-745) underflows to 0 in float64


def khat_threshold(n_points: int) -> float:
    """The k-hat bar of a PSIS estimate from ``n_points`` draws: min(KHAT_MAX,
    1 - 1 / log10 S) (Vehtari et al. 2024, the module docstring's source; 0
    for S <= 10, where no k-hat is trusted)."""
    if n_points <= 10:
        return 0.0
    return float(min(KHAT_MAX, 1.0 - 1.0 / np.log10(n_points)))


def _tail_size(n: int) -> int:
    """M, the points in the fitted tail (r_eff = 1: independent points)."""
    return int(np.floor(3 * np.sqrt(n))) if n > 225 else n // 5


def psis_weights(log_ratios: np.ndarray) -> tuple[np.ndarray, float]:
    """Pareto-smoothed self-normalised importance weights and their k-hat.

    Args:
        log_ratios: (N,) log importance ratios, any additive constant; -inf
            (a point of zero likelihood) gets weight 0.

    Returns:
        (weights (N,) summing to 1, k-hat). See the module docstring for the
        cases where k-hat is NaN or +inf.
    """
    lr = np.asarray(log_ratios, dtype=np.float64)
    fin = np.isfinite(lr)
    if not fin.any():
        raise ValueError("no point has a finite importance ratio")
    raw = np.where(fin, np.exp(lr - logsumexp(lr[fin])), 0.0)
    n = int(fin.sum())
    if n < MIN_POINTS:
        return raw, float("nan")
    top = np.sort(lr[fin])[-(_tail_size(n) + 1):]
    if top[-1] - top[0] > _EXP_RANGE:
        return raw, float("inf")
    if top[-1] == top[1]:  # equal tail ratios: nothing to fit
        return raw, float("nan")
    from arviz_stats.base import array_stats

    with np.errstate(all="ignore"):
        # arviz_stats' psislw takes log-likelihoods: its log ratios are their negation
        smoothed, khat = array_stats.psislw(-lr[fin])
    w = np.zeros_like(raw)
    w[fin] = np.exp(smoothed)
    if not (np.all(np.isfinite(w)) and abs(w.sum() - 1.0) < 1e-6):
        return raw, float("inf")
    return w / w.sum(), float(khat)


def ess(weights: np.ndarray) -> float:
    """Effective sample size of normalised weights, ``1 / sum w^2`` (Kish)."""
    w = np.asarray(weights, dtype=np.float64)
    return float(1.0 / np.sum(w * w))


def weighted_quantile(x: np.ndarray, w: np.ndarray, q: float) -> float:
    """The q-quantile of points x (n,) under weights w (n,): the weighted
    empirical CDF, interpolated linearly between the sorted points."""
    order = np.argsort(x)
    cw = np.cumsum(np.asarray(w)[order])
    return float(np.interp(q, cw / cw[-1], np.asarray(x)[order]))
