"""The proposal densities of a discovery candidate's adaptive design
(``calib.discovery.candidate_fit``): a Gaussian fitted to weighted points, a
Gaussian or multivariate Student t truncated to the unit cube, and the density
of the deterministic mixture of every stage drawn so far (Owen & Zhou 2000,
"Safe and effective importance sampling", JASA 95, 135-143: each point weighted
against the mixture of all stages, not against the stage that drew it).
Densities are relative to the uniform on the unit cube; the candidate fit adds
the warp's log-Jacobian (``calib.model.warp``).
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln, logsumexp

__all__ = ["PROPOSAL_DF", "gaussian_fit", "mixture_log_q", "proposal"]

# degrees of freedom of the adaptive stages' Student t proposals (our choice;
# calib.discovery.candidate_fit's module docstring and docs/studies.md)
PROPOSAL_DF = 4


def gaussian_fit(z, w, inflate=2.0, floor=0.05):
    """Mean and inflated covariance of unit-cube points with normalised weights w."""
    mean = w @ z
    cov = (z - mean).T @ ((z - mean) * w[:, None])
    return mean, inflate**2 * cov + floor**2 * np.eye(z.shape[1])


def proposal(mean, cov, rng, n, dim, df=None):
    """n draws in the unit cube [0, 1]^dim: the first ``len(mean)`` coordinates from
    N(mean, cov) truncated to the cube (with ``df``, the multivariate Student t of
    scale matrix cov and df degrees of freedom), the others uniform. Returns (draws,
    log-density function relative to the uniform prior).

    Where the distribution lies so far outside the cube that fewer than n of its
    draws land inside after 1000 n tries, the missing draws are uniform on the
    cube, and the density returned is that of the pair: m/n times the truncated
    distribution's plus (n - m)/n times the uniform's, m the draws inside."""
    k = mean.size
    chol = np.linalg.cholesky(cov)
    draws = np.empty((0, k))
    tried = accepted = 0
    while draws.shape[0] < n and tried < 1000 * n:
        step = rng.standard_normal((20 * n, k)) @ chol.T
        if df is not None:
            step = step * np.sqrt(df / rng.chisquare(df, size=(20 * n, 1)))
        pool = mean + step
        inside = np.all((pool >= 0) & (pool <= 1), axis=1)
        tried += pool.shape[0]
        accepted += int(inside.sum())
        draws = np.concatenate([draws, pool[inside]])
    p_in = max(accepted, 1) / tried
    n_in = min(draws.shape[0], n)
    if n_in < n:  # the proposal lies almost wholly outside: pad from the prior
        draws = np.concatenate([draws, rng.uniform(size=(n - n_in, k))])
    draws = np.concatenate([draws[:n], rng.uniform(size=(n, dim - k))], axis=1)
    inv = np.linalg.inv(cov)
    logdet = np.linalg.slogdet(cov)[1]

    def truncated(x):
        d = x[:, :k] - mean
        m2 = np.einsum("ij,jk,ik->i", d, inv, d)
        if df is None:
            return -0.5 * m2 - 0.5 * logdet - 0.5 * k * np.log(2 * np.pi) - np.log(p_in)
        return (gammaln(0.5 * (df + k)) - gammaln(0.5 * df) - 0.5 * k * np.log(df * np.pi)
                - 0.5 * logdet - 0.5 * (df + k) * np.log1p(m2 / df) - np.log(p_in))

    if n_in == n:
        return draws, truncated

    def padded(x):  # m/n truncated + (n - m)/n uniform (the uniform's log density is 0)
        with np.errstate(divide="ignore"):
            return np.logaddexp(np.log(n_in / n) + truncated(x), np.log((n - n_in) / n))

    return draws, padded


def mixture_log_q(z, counts, logpdfs):
    """log of the deterministic-mixture density at z, relative to the uniform
    on the unit cube: component k drew counts[k] points with log-density
    logpdfs[k] (relative to the same uniform)."""
    terms = [np.log(n) + f(z) for n, f in zip(counts, logpdfs, strict=True) if n]
    return logsumexp(np.stack(terms), axis=0) - np.log(sum(counts))
