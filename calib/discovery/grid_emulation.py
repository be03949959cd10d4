"""Posterior and held-out scores of a fixed-grid design (the DEM candidates'),
from each row's log-likelihood emulated between the grid's points.

Why (our choice; measured in docs/studies.md, "`calib.discover --model dem`
on DEM-made data" and "DEM discovery with the rows emulated between the
grid's points"): the DEM is too dear on two cores for adaptive designs, so
its candidates are simulated on grids of 12-64 points. With 60 rows the
posterior is narrower than a grid step, and importance weights on the
grid's simulated sums put all their mass on one point (ESS 1, the folds'
Pareto k-hat 9-35): the held-out scores then rest on one point's few
blocks. One row's log-likelihood, though, varies slowly over
the box (one runout says little about the parameters); only the sum over the
rows is sharp. So each row is emulated between the grid's points and the
sum of the emulated rows is evaluated where the posterior lives, on a dense
cloud that costs no simulation.

Emulator: a least-squares polynomial trend plus Gaussian-process regression
of its residuals (Rasmussen & Williams 2006, "Gaussian Processes for Machine
Learning", eqs. 2.25 and 2.30; the trend fitted first and held fixed, a
simplification of their Sect. 2.7), for every row over the grid's unit
coordinates z, one squared-exponential kernel for all rows:

    m_i(z) = h(z)^T b_i + s_i k(z, Z) (K + sn^2 I)^-1 r_i / s_i,
    k(z, z') = sf^2 exp(-1/2 sum_d (z_d - z'_d)^2 / ls_d^2),

with h(z) the monomials of z up to a degree of 0 (the constant), 1 (and
z_d) or 2 (and z_d z_e), among those the grid has at least twice as many
points as monomials for, the one whose emulator predicts the rows at the
grid's inner points best when each is left out of its fit (the squared
error summed over rows and points; Rasmussen & Williams Sect. 5.4.2; the
points on the grid's faces are left out of the sum, since predicting one
of them without it is an extrapolation the cloud, inside the grid's hull,
never asks for; all points where fewer than 3 are inner); b_i the
least-squares coefficients of row i's simulated log-likelihoods l_i(Z)
at the grid's points, r_i = l_i(Z) - H b_i its residuals and s_i their
sd; (ls, sf, sn) fitted by the marginal likelihood of the standardised
residuals summed over the rows (eq. 2.30). Our choices:
one kernel for all rows, since a row's values over a grid of a few dozen
points cannot fix a kernel of its own; a trend, because a row's
log-likelihood is near-quadratic in the parameters where its runouts are
spread around the observation, and a shared kernel alone smoothed the
peak; its degree chosen by the left-out points, because where a row's
log-likelihood is a narrow bump over a floor (the DEM's rows, a parameter
that moves the runouts along the profile) a quadratic fits it worse than a
constant. Measured on the toy simulator of tests/test_grid_emulation.py
(16 points, 64 blocks each, 60 rows, six seeds): the held-out total within
0.2-2.2 nats of a 64-times finer grid's simulated one, the posterior mean
within 0.014 of the fine grid's; with the kernel alone, 0.1-3.9 nats and
0.024. The nugget sn^2 takes the simulation noise of a few blocks per
point. The emulated mean is used as the row's log-likelihood; the GP's own
uncertainty between the points is not propagated (our simplification).

Cloud (our choice): ``CLOUD_POINTS`` scrambled Sobol points uniform on the
unit cube, weighted by exp(sum_i m_i(z)); then as many points from the
Student t of ``PROPOSAL_DF`` degrees of freedom fitted to those weights
(``gaussian_fit``: covariance inflated x2^2 plus ``CLOUD_FLOOR``^2),
truncated to the cube; both stages one deterministic mixture (Owen & Zhou
2000, JASA 95, 135-143), the prior uniform over the box. The posterior's
weights, every fold's training weights and the held-out scores are then
``calib.discovery.scores.cv_elpd`` on the cloud's emulated rows, each set
of weights Pareto-smoothed with its k-hat (Vehtari et al. 2024).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import minimize
from scipy.stats import qmc

from calib.discovery.proposals import PROPOSAL_DF, gaussian_fit, mixture_log_q, proposal
from calib.discovery.scores import cv_elpd
from calib.inference.emulator import se_kernel
from calib.inference.importance import psis_weights

__all__ = ["CLOUD_POINTS", "GridScores", "RowEmulator", "fit_row_emulator", "grid_scores",
           "trend_basis", "trend_degrees"]

CLOUD_POINTS = 4096
CLOUD_FLOOR = 0.005
# bounds of the kernel's log hyperparameters (unit coordinates; standardised rows)
_LOG_LS = (np.log(0.05), np.log(3.0))
_LOG_SF = (np.log(0.1), np.log(10.0))
_LOG_SN = (np.log(1e-3), np.log(3.0))
_JITTER = 1e-8


def _kernel(a: np.ndarray, b: np.ndarray, ls: np.ndarray, sf: float) -> np.ndarray:
    """The squared-exponential kernel of ``calib.inference.emulator``, as NumPy."""
    return np.asarray(se_kernel(a, b, np.log(ls), np.log(sf)))


def trend_basis(z: np.ndarray, degree: int) -> np.ndarray:
    """(M, T) the monomials of (M, d) unit coordinates up to ``degree`` (0, 1 or 2):
    1, then z_d, then z_d z_e (d <= e)."""
    z = np.atleast_2d(z)
    cols = [np.ones(z.shape[0])]
    if degree >= 1:
        cols += [z[:, j] for j in range(z.shape[1])]
    if degree >= 2:
        cols += [z[:, i] * z[:, j] for i in range(z.shape[1]) for j in range(i, z.shape[1])]
    return np.stack(cols, axis=1)


def trend_degrees(n_points: int, dim: int) -> tuple[int, ...]:
    """The trend's degrees (0, 1, 2) whose monomials number at most half the
    grid's points (module docstring)."""
    return tuple(k for k in (0, 1, 2)
                 if 2 * trend_basis(np.zeros((1, dim)), k).shape[1] <= max(n_points, 2))


@dataclasses.dataclass(frozen=True)
class RowEmulator:
    """Every row's emulated log-likelihood (module docstring).

    z: (N, d) the grid's unit coordinates; degree: the trend's; beta: (T, R)
    each row's trend coefficients; coef: (N, R) (K + sn^2 I)^-1 times each
    row's standardised residuals; s: (R,) the residuals' sds; ls: (d,), sf,
    sn: the kernel's length scales, signal and noise sd (standardised units);
    loo_rmse_nats: the root-mean-square error of the rows' values at the
    grid's inner points, each predicted by the emulator fitted without it
    (the trend's degree chosen by it).
    """

    z: np.ndarray
    degree: int
    beta: np.ndarray
    coef: np.ndarray
    s: np.ndarray
    ls: np.ndarray
    sf: float
    sn: float
    loo_rmse_nats: float = float("nan")

    def record(self) -> dict:
        """The emulator's figures as a fit records them: the trend's degree, the
        left-out error (nats), the kernel's length scales, signal and noise sd."""
        return {"trend_degree": self.degree, "loo_rmse_nats": self.loo_rmse_nats,
                "length_scales": [float(v) for v in self.ls], "signal_sd": self.sf,
                "noise_sd": self.sn}

    def mean(self, x: np.ndarray, chunk: int = 4096) -> np.ndarray:
        """(M, R) the emulated log-likelihood of every row at (M, d) unit coordinates."""
        x = np.atleast_2d(np.asarray(x, float))
        out = np.empty((x.shape[0], self.coef.shape[1]))
        for i in range(0, x.shape[0], chunk):
            xi = x[i:i + chunk]
            out[i:i + chunk] = (trend_basis(xi, self.degree) @ self.beta
                                + self.s * (_kernel(xi, self.z, self.ls, self.sf) @ self.coef))
        return out


def fit_row_emulator(z: np.ndarray, ll: np.ndarray) -> RowEmulator:
    """The ``RowEmulator`` of (N, R) simulated log-likelihoods ``ll`` at the (N, d)
    unit coordinates ``z``: for each trend degree the grid allows, every
    inner point predicted by the emulator fitted without it; the degree of
    the smallest error kept and fitted to all the points (module docstring).

    Raises:
        ValueError: a value that is not finite (the likelihood's defensive floor
            keeps every simulated value finite), or fewer than 3 points.
    """
    z = np.atleast_2d(np.asarray(z, float))
    ll = np.asarray(ll, float)
    if z.shape[0] < 3 or ll.shape[0] != z.shape[0]:
        raise ValueError(f"expected at least 3 points with one value per row each, got "
                         f"{z.shape[0]} points and {ll.shape[0]} values")
    if not np.all(np.isfinite(ll)):
        raise ValueError("expected finite log-likelihoods at every grid point")
    n = z.shape[0]
    inner = np.flatnonzero(np.all((z > z.min(axis=0)) & (z < z.max(axis=0)), axis=1))
    checked = inner if inner.size >= 3 else np.arange(n)
    best = None
    for degree in trend_degrees(n - 1, z.shape[1]):
        err = np.stack([_fit(np.delete(z, j, 0), np.delete(ll, j, 0), degree).mean(z[j:j + 1])[0]
                        - ll[j] for j in checked])
        rmse = float(np.sqrt(np.mean(err * err)))
        if best is None or rmse < best[1]:
            best = (degree, rmse)
    return dataclasses.replace(_fit(z, ll, best[0]), loo_rmse_nats=best[1])


def _fit(z: np.ndarray, ll: np.ndarray, degree: int) -> RowEmulator:
    """The emulator of one trend degree (module docstring)."""
    n, d = z.shape
    basis = trend_basis(z, degree)
    beta = np.linalg.lstsq(basis, ll, rcond=None)[0]
    resid = ll - basis @ beta
    s = np.maximum(resid.std(axis=0), 1e-6)
    g = resid / s
    r = g.shape[1]

    def unpack(p):
        return np.exp(p[:d]), float(np.exp(p[d])), float(np.exp(p[d + 1]))

    def neg_marginal(p):
        ls, sf, sn = unpack(p)
        a = _kernel(z, z, ls, sf) + (sn * sn + _JITTER) * np.eye(n)
        try:
            c = np.linalg.cholesky(a)
        except np.linalg.LinAlgError:
            return 1e12
        v = np.linalg.solve(c, g)
        return 0.5 * float(np.sum(v * v)) + r * float(np.sum(np.log(np.diag(c))))

    spacing = np.array([np.ptp(z[:, j]) / max(np.unique(z[:, j]).size - 1, 1)
                        for j in range(d)])
    start = np.concatenate([np.log(np.clip(2.0 * spacing, 0.06, 2.9)), [0.0, np.log(0.3)]])
    bounds = [_LOG_LS] * d + [_LOG_SF, _LOG_SN]
    res = minimize(neg_marginal, start, method="L-BFGS-B", bounds=bounds)
    ls, sf, sn = unpack(res.x if np.isfinite(res.fun) else start)
    a = _kernel(z, z, ls, sf) + (sn * sn + _JITTER) * np.eye(n)
    return RowEmulator(z, degree, beta, np.linalg.solve(a, g), s, ls, sf, sn)


@dataclasses.dataclass(frozen=True)
class GridScores:
    """A fixed grid's posterior and held-out scores on the emulator's cloud.

    z: (M, d) the cloud's unit coordinates; log_q: (M,) its mixture density
    relative to the prior; ll: (M, R) the emulated rows there; weights: (M,)
    the posterior's (Pareto-smoothed), khat theirs; elpd: (R,) held-out
    scores; khat_folds: (F,) each fold's training weights' k-hat;
    emulator: the ``RowEmulator``.
    """

    z: np.ndarray
    log_q: np.ndarray
    ll: np.ndarray
    weights: np.ndarray
    khat: float
    elpd: np.ndarray
    khat_folds: np.ndarray
    emulator: RowEmulator


def grid_scores(z: np.ndarray, ll: np.ndarray, fold: np.ndarray,
                rng: np.random.Generator, n_cloud: int = CLOUD_POINTS) -> GridScores:
    """The posterior and held-out scores of the grid (z (N, d) unit coordinates,
    ll (N, R) simulated log-likelihoods, ``fold`` (R,) each row's fold) from the
    rows emulated between its points, on a cloud of 2 ``n_cloud`` points
    (module docstring)."""
    emu = fit_row_emulator(z, ll)
    d = z.shape[1]
    first = qmc.Sobol(d, scramble=True, seed=rng).random(n_cloud)
    w0, _ = psis_weights(emu.mean(first).sum(axis=1))
    mean, cov = gaussian_fit(first, w0, floor=CLOUD_FLOOR)
    second, logpdf = proposal(mean, cov, rng, n_cloud, d, df=PROPOSAL_DF)
    cloud = np.concatenate([first, second])
    log_q = mixture_log_q(cloud, [n_cloud, n_cloud],
                          [lambda x: np.zeros(x.shape[0]), logpdf])
    rows = emu.mean(cloud)
    w, khat = psis_weights(rows.sum(axis=1) - log_q)
    elpd, khat_folds = cv_elpd(rows, log_q, fold)
    return GridScores(cloud, log_q, rows, w, float(khat), elpd, khat_folds, emu)
