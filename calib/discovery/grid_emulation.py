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
point. The emulated mean is used as the row's log-likelihood in the
held-out scores.

The posterior carries the emulator's uncertainty of the SUM (our choice;
why: a DEM block's runout is chaotic in the parameters, so with the default
8 blocks per point and size the summed log-likelihood of 180 rows moves by
an sd of 23-51 nats from one block set to the next at one alpha, and
neighbouring grid points differ as if each had blocks of its own, far more
than the sum varies across the posterior; the emulated mean then puts a 90 %
interval at a fraction of the width the simulations support, and it missed
the truth in 3 of 4 block sets of one data set, docs/studies.md). The summed
values L(Z) = sum_i l_i(Z) get a GP of their own with the rows' trend basis
and length scales and an explicit basis under a vague prior (Rasmussen &
Williams 2006, Sect. 2.7, eqs. 2.42 and 2.45: the trend's coefficients
integrated out, the signal and noise sd fitted by that marginal
likelihood), since the rows share their blocks and their noise does not add
up independently. ``N_REALISATIONS`` joint draws of its posterior at
``N_SUBSET`` points of the cloud, extended to the whole cloud by their
conditional mean, are added to the emulated sum, and the posterior's weights
are the average of each realisation's (Pareto-smoothed) weights: the
expected posterior over the GP's uncertainty (Reiser, Aguilar, Guthke &
Buerkner 2023, arXiv 2312.05153, "E-Post"). The folds' training weights
and held-out scores keep the emulated mean.

Cloud (our choice): ``CLOUD_POINTS`` scrambled Sobol points uniform on the
unit cube, weighted by exp(sum_i m_i(z)); then as many points from the
Student t of ``PROPOSAL_DF`` degrees of freedom fitted to those weights
(``gaussian_fit``: covariance inflated x2^2 plus ``CLOUD_FLOOR``^2),
truncated to the cube, and as many again from the t fitted to the weights
averaged over the sum's realisations (below), which reach further; the
three stages one deterministic mixture (Owen & Zhou 2000, JASA 95,
135-143), the prior uniform over the box. (With the second t alone, one
fold's training weights on 180 DEM-made rows had a k-hat of 0.93.) Every fold's
training weights and the held-out scores are then
``calib.discovery.scores.cv_elpd`` on the cloud's emulated rows, each set
of weights Pareto-smoothed with its k-hat (Vehtari et al. 2024); the
posterior's weights are those averaged over the realisations.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from scipy.optimize import minimize
from scipy.stats import qmc

from calib.discovery.proposals import PROPOSAL_DF, gaussian_fit, mixture_log_q, proposal
from calib.discovery.scores import cv_elpd
from calib.inference.emulator import se_kernel
from calib.inference.importance import psis_weights

__all__ = ["CLOUD_POINTS", "GridScores", "N_REALISATIONS", "RowEmulator", "SumEmulator",
           "fit_row_emulator", "fit_sum_emulator", "grid_scores", "trend_basis", "trend_degrees"]

CLOUD_POINTS = 4096
CLOUD_FLOOR = 0.005
N_REALISATIONS = 64  # draws of the summed log-likelihood's GP (module docstring)
N_SUBSET = 1024      # cloud points the draws are joint at
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
class SumEmulator:
    """The summed log-likelihood's GP (module docstring): an explicit trend
    basis of ``degree`` with a vague prior on its coefficients plus
    sf^2 k_SE(z, z'; ls), observed at the grid's points z (N, d) with noise sd
    sn, nats. ``posterior_cov`` gives its posterior covariance."""

    z: np.ndarray
    degree: int
    ls: np.ndarray
    sf: float
    sn: float

    @functools.cached_property
    def _parts(self):
        """(H (T, N), Ky^-1, (H Ky^-1 H^T)^-1), fixed by the fit: computed once."""
        n = self.z.shape[0]
        ky = (self.sf ** 2 * _kernel(self.z, self.z, self.ls, 1.0)
              + (self.sn ** 2 + _JITTER) * np.eye(n))
        h = trend_basis(self.z, self.degree).T  # (T, N)
        ky_inv = np.linalg.inv(ky)
        return h, ky_inv, np.linalg.inv(h @ ky_inv @ h.T)

    def posterior_cov(self, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
        """(M1, M2) posterior covariance of the sum at unit coordinates x1, x2
        (Rasmussen & Williams eq. 2.42 with the vague prior's limit):
        k(x1, x2) - k1^T Ky^-1 k2 + R1^T (H Ky^-1 H^T)^-1 R2, R = H(x) - H Ky^-1 k."""
        h, ky_inv, a_inv = self._parts
        k1 = self.sf ** 2 * _kernel(self.z, x1, self.ls, 1.0)
        k2 = self.sf ** 2 * _kernel(self.z, x2, self.ls, 1.0)
        r1 = trend_basis(x1, self.degree).T - h @ ky_inv @ k1
        r2 = trend_basis(x2, self.degree).T - h @ ky_inv @ k2
        return (self.sf ** 2 * _kernel(x1, x2, self.ls, 1.0) - k1.T @ ky_inv @ k2
                + r1.T @ a_inv @ r2)

    def realisations(self, x: np.ndarray, rng: np.random.Generator,
                     n: int = N_REALISATIONS, n_subset: int = N_SUBSET) -> np.ndarray:
        """(n, M) draws of the sum's deviation from its posterior mean at the
        (M, d) points x: joint at every (M // n_subset)-th point (eigenvectors of
        their covariance, relative eigenvalues below 1e-10 dropped), extended
        to all M points by the conditional mean."""
        sub = x[::max(x.shape[0] // n_subset, 1)]
        lam, vec = np.linalg.eigh(self.posterior_cov(sub, sub))
        keep = lam > 1e-10 * max(lam.max(), 1e-300)
        xi = rng.standard_normal((int(keep.sum()), n))
        # C_xs C_ss^-1 (V sqrt(lam) xi) = C_xs V lam^-1/2 xi
        return (self.posterior_cov(x, sub) @ (vec[:, keep] / np.sqrt(lam[keep])) @ xi).T


def fit_sum_emulator(emu: RowEmulator, total: np.ndarray) -> SumEmulator:
    """The ``SumEmulator`` of the summed log-likelihoods ``total`` (N,) at the
    row emulator's grid, with its trend degree and length scales; sf and sn
    maximise the marginal likelihood with the trend integrated out (Rasmussen
    & Williams eq. 2.45), from a few starts about the values' sd."""
    z, n = emu.z, emu.z.shape[0]
    y = np.asarray(total, float) - np.mean(total)
    h = trend_basis(z, emu.degree).T
    k0 = _kernel(z, z, emu.ls, 1.0)

    def neg_restricted(p):
        sf, sn = np.exp(p)
        ky = sf * sf * k0 + (sn * sn + _JITTER) * np.eye(n)
        try:
            c = np.linalg.cholesky(ky)
            ky_inv_y = np.linalg.solve(ky, y)
            ky_inv_h = np.linalg.solve(ky, h.T)
            a = h @ ky_inv_h
            ca = np.linalg.cholesky(a)
        except np.linalg.LinAlgError:
            return 1e12
        hy = h @ ky_inv_y
        return float(0.5 * y @ ky_inv_y - 0.5 * hy @ np.linalg.solve(a, hy)
                     + np.sum(np.log(np.diag(c))) + np.sum(np.log(np.diag(ca))))

    scale = np.log(max(float(np.std(y)), 1e-6))
    bounds = [(scale - 8.0, scale + 4.0)] * 2
    best = min((minimize(neg_restricted, [scale + a, scale + b], method="L-BFGS-B", bounds=bounds)
                for a in (-2.0, 0.0, 1.0) for b in (-3.0, -1.0, 0.0)), key=lambda r: r.fun)
    sf, sn = np.exp(best.x)
    return SumEmulator(z, emu.degree, emu.ls, float(sf), float(sn))


@dataclasses.dataclass(frozen=True)
class GridScores:
    """A fixed grid's posterior and held-out scores on the emulator's cloud.

    z: (M, d) the cloud's unit coordinates; log_q: (M,) its mixture density
    relative to the prior; ll: (M, R) the emulated rows there; weights: (M,)
    the posterior's, averaged over the summed log-likelihood's realisations
    (module docstring); khat: their Pareto k-hat as importance ratios;
    elpd: (R,) held-out scores; khat_folds: (F,) each fold's
    training weights' k-hat; emulator: the ``RowEmulator``; sum_emulator:
    the ``SumEmulator``.
    """

    z: np.ndarray
    log_q: np.ndarray
    ll: np.ndarray
    weights: np.ndarray
    khat: float
    elpd: np.ndarray
    khat_folds: np.ndarray
    emulator: RowEmulator
    sum_emulator: SumEmulator

    def record(self) -> dict:
        """The fit's record of its emulators: the rows' (``RowEmulator.record``),
        the sum's signal and noise sd (nats) and the realisations averaged."""
        return {**self.emulator.record(), "sum_signal_sd_nats": self.sum_emulator.sf,
                "sum_noise_sd_nats": self.sum_emulator.sn, "n_realisations": N_REALISATIONS}


def grid_scores(z: np.ndarray, ll: np.ndarray, fold: np.ndarray,
                rng: np.random.Generator, n_cloud: int = CLOUD_POINTS) -> GridScores:
    """The posterior and held-out scores of the grid (z (N, d) unit coordinates,
    ll (N, R) simulated log-likelihoods, ``fold`` (R,) each row's fold) from the
    rows emulated between its points, on a cloud of 3 ``n_cloud`` points, the
    posterior averaged over the summed log-likelihood's realisations (module
    docstring)."""
    emu = fit_row_emulator(z, ll)
    emu_sum = fit_sum_emulator(emu, ll.sum(axis=1))
    d = z.shape[1]
    first = qmc.Sobol(d, scramble=True, seed=rng).random(n_cloud)
    rows_first = emu.mean(first)
    sums = rows_first.sum(axis=1)
    stages, logpdfs = [first], [lambda x: np.zeros(x.shape[0])]
    for w0 in (psis_weights(sums)[0],
               _expected_weights(sums, emu_sum.realisations(first, rng))):
        mean, cov = gaussian_fit(first, w0, floor=CLOUD_FLOOR)
        pts, logpdf = proposal(mean, cov, rng, n_cloud, d, df=PROPOSAL_DF)
        stages.append(pts)
        logpdfs.append(logpdf)
    cloud = np.concatenate(stages)
    log_q = mixture_log_q(cloud, [n_cloud] * len(stages), logpdfs)
    rows = np.concatenate([rows_first, emu.mean(cloud[n_cloud:])])
    w = _expected_weights(rows.sum(axis=1) - log_q, emu_sum.realisations(cloud, rng))
    khat = float(psis_weights(np.log(np.maximum(w, 1e-300)))[1])
    elpd, khat_folds = cv_elpd(rows, log_q, fold)
    return GridScores(cloud, log_q, rows, w, khat, elpd, khat_folds, emu, emu_sum)


def _expected_weights(log_w: np.ndarray, deviations: np.ndarray) -> np.ndarray:
    """(M,) the posterior's weights averaged over the realisations: each
    realisation's log weights ``log_w`` + its deviation (R, M), Pareto-smoothed
    and normalised, then averaged (module docstring)."""
    return np.mean([psis_weights(log_w + dev)[0] for dev in deviations], axis=0)
