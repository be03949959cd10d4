"""Scores of a calibrated model against observations: held-out log predictive
density (model comparison) and CRPS (the gap metric). NumPy, no simulation.

Held-out predictive score: Pareto-smoothed importance-sampling leave-one-out
(PSIS-LOO; Vehtari, Gelman & Gabry 2017, "Practical Bayesian model evaluation
using leave-one-out cross-validation and WAIC", Stat. Comput. 27, 1413-1432,
eqs. 10-11). With S draws theta_s of the model's posterior, each carrying a
posterior weight v_s (1 for plain posterior draws; the importance weight of a
design point otherwise), row i's score is

    elpd_i = log p(y_i | y_(-i)) = log sum_s wbar_s^(-i) p(y_i | theta_s),

    wbar^(-i) = PSIS-smoothed, self-normalised ratios r_s^(-i) = v_s / p(y_i | theta_s)

(``calib.inference.importance.psis_weights``; Vehtari et al. 2024). Each row's
k-hat is returned with the scores; above ``khat_threshold(S)`` = min(0.7, 1 -
1/log10 S) that row's score is not reliable, and a candidate whose scores are
reliable in fewer than ``LOO_RELIABLE_SHARE`` = 90 % of its rows is flagged
(our bar). Where the draws come from is the caller's
(``calib.discovery.candidate_fit``: draws of each candidate's posterior,
re-simulated). Extra parameters are penalised automatically: a model that
over-fits predicts each left-out row worse.

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

from calib.inference.importance import khat_threshold, psis_weights

__all__ = [
    "ALPHA",
    "ELPD_MIN",
    "Z_MIN",
    "best_effect",
    "LOO_RELIABLE_SHARE",
    "carrying_rows",
    "crps_ensemble",
    "effective_rows",
    "elpd_difference",
    "loo_elpd",
    "loo_reliable_share",
    "naming_threshold",
    "naming_z",
    "rows_needed",
]

ELPD_MIN = 4.0
LOO_RELIABLE_SHARE = 0.9
Z_MIN = 2.0
ALPHA = float(norm.sf(Z_MIN))  # one-sided level of the Z_MIN bar for one candidate


def crps_ensemble(samples: np.ndarray, y: float) -> float:
    """CRPS of the ensemble ``samples`` (m,) at the observation ``y`` (same units)."""
    x = np.sort(np.asarray(samples, float).ravel())
    m = x.size
    k = np.arange(1, m + 1)
    spread = 2.0 * np.sum((2 * k - m - 1) * x) / (m * m)  # mean |X - X'|
    return float(np.mean(np.abs(x - y)) - 0.5 * spread)


def loo_elpd(loglik: np.ndarray, log_weights: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """PSIS leave-one-out log predictive density of each row, and each row's k-hat.

    Args:
        loglik: (S, n_obs) log p(y_i | theta_s) at S posterior draws.
        log_weights: (S,) log posterior weight of each draw, any additive
            constant (None: equal weights, plain posterior draws); -inf: weight 0.

    Returns:
        (elpd (n_obs,), khat (n_obs,)), module docstring. A draw at which row i
        has log p = -inf (no finished block of its size,
        ``calib.inference.likelihood``) has an infinite leave-one-out ratio that
        no finite set of draws estimates: row i's score then comes from its
        other draws and its k-hat is +inf (unreliable); with no finite draw the
        score is -inf.
    """
    ll = np.asarray(loglik, float)
    lw = np.zeros(ll.shape[0]) if log_weights is None else np.asarray(log_weights, float)
    elpd = np.empty(ll.shape[1])
    khat = np.empty(ll.shape[1])
    for i in range(ll.shape[1]):
        li = ll[:, i]
        ok = np.isfinite(li) & np.isfinite(lw)
        if not ok.any():
            elpd[i], khat[i] = -np.inf, np.inf
            continue
        w, khat[i] = psis_weights(np.where(ok, lw - li, -np.inf))
        if not np.isfinite(li[np.isfinite(lw)]).all():
            khat[i] = np.inf
        with np.errstate(divide="ignore"):  # weight 0: log 0 = -inf, as meant
            elpd[i] = logsumexp(np.log(w[ok]) + li[ok])
    return elpd, khat


def loo_reliable_share(khat: np.ndarray, n_draws: int) -> float:
    """Share of rows whose k-hat lies below ``khat_threshold(n_draws)`` (NaN, not
    estimated, counts as not reliable)."""
    k = np.asarray(khat, float)
    return float(np.mean(k < khat_threshold(n_draws))) if k.size else float("nan")


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
