"""The DEM posterior averaged over the joint realisations of its quantile emulator.

The DEM's fit emulates, for each block size s and level k, the runout quantile
Q_sk as a function of that size's damping alpha(L_s; theta) with one GP
(``calib.inference.emulator``; ``DemForward.emulator_inputs``: a one-dimensional
input per size). NUTS on the GPs' mean with their latent variance added to each
row's kernel (``RowLikelihood.emulated``) treats the emulator's error as
independent from row to row, while the rows of one size read the same
quantiles: the posterior is narrower than the design supports. Measured on six
data sets made by the DEM itself (docs/studies.md, "Coverage of the DEM
posterior"): its 90 % intervals of a and b held the truth in 8 of 12, every
fit passing its diagnostics.

What this module builds instead, the "expected posterior" (E-Post in Reiser,
Aguilar, Guthke & Buerkner 2023, arXiv 2312.05153; Roberts, Dietze & Huggins
2026, arXiv 2601.03532), the average of the posteriors under M realisations f_m
of the GPs:

    p_E(theta | y) = 1/M sum_m prior(theta) exp(l_m(theta)) / Z_m,
    l_m(theta) = sum_i log p(y_i | Q^(m)_{s_i .}(alpha(L_{s_i}; theta)))
                 (``calib.inference.likelihood.log_likelihood``, v_j = 0),
    Z_m = integral prior(theta) exp(l_m(theta)) dtheta.

Our choices. Each realisation is a joint draw of one GP's latent function on
``N_ALPHA`` points spanning the emulator's alpha range (pathwise: mean plus the
Cholesky factor of the latent posterior covariance times a standard normal),
with the latent covariance scaled by the emulator's variance inflation (the
factor the mean path puts on the latent variance, ``emulator.variance_inflation``),
read between the points by linear interpolation, and its K quantiles sorted at
each alpha (as ``QuantileEmulator.predict`` sorts the means). Inside a
realisation the emulator's error is drawn, not added to the kernel: the rows'
kernel is their measurement tolerance alone, as for simulated runouts. Z_m is
a midpoint sum over a regular grid of about ``N_THETA`` equal cells on the
prior box (the prior is uniform, so the cell volume is common to every m and
drops out), and p_E is sampled on that grid: a cell drawn with probability
p_E(centre) and a point uniform inside it (``sample_expected``), i.i.d. draws,
arranged as the chains NUTS would give so that the same diagnostics read them.
Not NUTS: log p_E is a mixture of M rough densities, read through linear
interpolation, and NUTS on it did not finish one 2-parameter fit in 15 minutes
on 2 cores (measured 2026-12-05; the grid takes seconds). The grid's
resolution is the approximation: a draw's quantiles are off by at most one
cell width, so a fit whose 90 % interval of some parameter spans fewer than
``MIN_CELLS_ACROSS`` cells lists that as a problem (our bar: quantiles to a
tenth of the interval). ``record["grid_ess"]``, the effective number of cells
under p_E, says how many cells carry the posterior.
With this construction the intervals held the truth in 12 of 12 on those six
data sets, and in 12 of 12 on six fresh ones (8 of 12 before), at the same
time per fit (docs/studies.md, same entry; ``scripts/dem_coverage.py``).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from calib.inference.bayes import diagnosed
from calib.inference.emulator import QuantileEmulator, se_kernel
from calib.inference.likelihood import log_likelihood
from calib.model.priors import Box

__all__ = ["MIN_CELLS_ACROSS", "N_ALPHA", "N_REALISATIONS", "N_THETA", "alpha_realisations",
           "expected_posterior", "sample_expected"]

N_REALISATIONS = 64
N_ALPHA = 401  # points of each realisation over the emulator's alpha range
N_THETA = 32768  # points (about) of the grid that normalises each realisation's posterior
MIN_CELLS_ACROSS = 10  # cells a 90 % interval must span (module docstring)
_JITTER = 1e-8  # relative to the GP's signal variance, on the Cholesky's diagonal


def alpha_realisations(emu: QuantileEmulator, alpha_grid: jax.Array, n: int, key: jax.Array,
                       inflation: float = 1.0) -> jax.Array:
    """Joint draws of every (size, level) GP's latent function on an alpha grid.

    Args:
        emu: the fitted quantile emulator, with a one-dimensional input.
        alpha_grid: (G,) input values (unscaled).
        n: realisations M.
        key: PRNG key.
        inflation: factor on the latent covariance (module docstring).

    Returns:
        (M, S, K, G) quantiles, m, sorted over K at each grid point.
    """
    if emu.x_unit.shape[1] != 1:
        raise ValueError(f"the realisations need a one-dimensional emulator input, "
                         f"not {emu.x_unit.shape[1]}")
    g = ((jnp.asarray(alpha_grid) - emu.lo[0]) / (emu.hi[0] - emu.lo[0]))[:, None]
    eye = jnp.eye(g.shape[0])

    def one(alpha, chol, log_ls, log_sf, mu, sd, k):
        ks = se_kernel(g, emu.x_unit, log_ls, log_sf)  # (G, n_design)
        v = jax.scipy.linalg.solve_triangular(chol, ks.T, lower=True)
        cov = se_kernel(g, g, log_ls, log_sf) - v.T @ v
        low = jnp.linalg.cholesky(cov + _JITTER * jnp.exp(2 * log_sf) * eye)
        z = jax.random.normal(k, (n, g.shape[0]))
        return mu + sd * (ks @ alpha + math.sqrt(inflation) * z @ low.T)  # (M, G)

    s, k = emu.alpha.shape[:2]
    keys = jax.random.split(key, s * k).reshape(s, k)
    f = jax.vmap(jax.vmap(one))(emu.alpha, emu.chol, emu.hyp[0], emu.hyp[1], emu.y_mean,
                                emu.y_std, keys)  # (S, K, M, G)
    return jnp.sort(jnp.moveaxis(f, 2, 0), axis=2)


def _grid(box: Box) -> tuple[np.ndarray, np.ndarray]:
    """The centres (P, d) of about ``N_THETA`` equal cells tiling ``box``, and the
    cells' widths (d,)."""
    per_dim = max(int(round(N_THETA ** (1.0 / box.dim))), 2)
    width = (np.asarray(box.hi, float) - np.asarray(box.lo, float)) / per_dim
    axes = [lo + (np.arange(per_dim) + 0.5) * w for lo, w in zip(box.lo, width)]
    centres = np.stack([a.ravel() for a in np.meshgrid(*axes, indexing="ij")], axis=1)
    return centres, width


def expected_posterior(emu: QuantileEmulator, emulator_inputs, rows, box: Box,
                       key: jax.Array, inflation: float = 1.0):
    """p_E on the grid (module docstring) and log p_E less the log prior at any theta.

    Args:
        emu: the quantile emulator (one-dimensional input per size).
        emulator_inputs: theta (d,) -> (S, 1) each size's input
            (``DemForward.emulator_inputs``).
        rows: the rows' likelihood (``calib.inference.likelihood.RowLikelihood``),
            runout rows only.
        box: the prior box.
        key: PRNG key of the realisations.
        inflation: the emulator's variance inflation.

    Returns:
        (log_density, grid, record): log_density maps theta (d,) to a (1,)
        array; grid is (centres (P, d), widths (d,), weights (P,) summing to 1);
        record says how it was built (realisations, grid sizes, grid_ess).
    """
    if rows.velocities is not None:
        raise ValueError("the expected posterior scores runout rows only")
    lo, hi = float(emu.lo[0]), float(emu.hi[0])
    alpha_grid = jnp.linspace(lo, hi, N_ALPHA)
    f = alpha_realisations(emu, alpha_grid, N_REALISATIONS, key, inflation)
    data, idx = rows.rows, jnp.asarray(rows.index)

    def loglik(fm, theta):  # fm (S, K, G), theta (d,) -> the summed log-likelihood
        a = emulator_inputs(theta)[:, 0]
        q = jax.vmap(lambda fs, x: jax.vmap(lambda fk: jnp.interp(x, alpha_grid, fk))(fs))(fm, a)
        return jnp.sum(log_likelihood(q[idx], *data))

    on_grid = jax.jit(lambda fm, th: jax.vmap(lambda t: loglik(fm, t))(th))
    centres, widths = _grid(box)
    ll = jnp.stack([on_grid(f[m], jnp.asarray(centres)) for m in range(N_REALISATIONS)])
    log_z = logsumexp(ll, axis=1)  # (M,), the cell volume dropped
    w = np.asarray(jnp.mean(jnp.exp(ll - log_z[:, None]), axis=0))  # p_E per cell
    w = w / w.sum()
    record = {"n_realisations": N_REALISATIONS, "n_alpha_grid": N_ALPHA,
              "n_theta_grid": int(centres.shape[0]), "grid_ess": float(1.0 / np.sum(w * w))}

    @jax.jit
    def log_density(theta):
        lm = jax.vmap(lambda fm: loglik(fm, theta))(f)
        return (logsumexp(lm - log_z) - math.log(N_REALISATIONS))[None]

    return log_density, (centres, widths, w), record


def sample_expected(log_density, grid, names: tuple[str, ...], key: jax.Array,
                    n_chains: int, n_draws: int):
    """Draws of p_E from its grid (``expected_posterior``) as a ``Posterior``.

    Each draw: a cell with probability its weight, then a point uniform inside
    it. The draws are independent; they are arranged as ``n_chains`` chains of
    ``n_draws`` so that ``calib.inference.bayes.diagnosed`` reads them as it
    reads NUTS's. A parameter whose 90 % interval spans fewer than
    ``MIN_CELLS_ACROSS`` cells is a problem of the posterior (module docstring).

    Returns:
        ``calib.inference.bayes.Posterior`` with ``loglik_kind`` "expected".
    """
    centres, widths, w = grid
    k_cell, k_in = jax.random.split(key)
    n = n_chains * n_draws
    cell = np.asarray(jax.random.choice(k_cell, w.shape[0], (n,), p=jnp.asarray(w)))
    u = np.asarray(jax.random.uniform(k_in, (n, centres.shape[1]))) - 0.5
    samples = centres[cell] + u * widths
    dens = np.asarray(jax.vmap(log_density)(jnp.asarray(samples)))  # (n, 1)
    stats = {"diverging": np.zeros((n_chains, n_draws), bool),
             "acceptance_rate": np.ones((n_chains, n_draws))}
    post = diagnosed(names, samples.reshape(n_chains, n_draws, -1), dens[:, 0], dens, stats,
                     "expected")
    q05, q95 = np.quantile(samples, [0.05, 0.95], axis=0)
    for name, across in zip(names, (q95 - q05) / widths):
        if across < MIN_CELLS_ACROSS:
            post.problems.append(f"the 90 % interval of {name} spans {across:.1f} grid cells "
                                 f"(< {MIN_CELLS_ACROSS}): the grid is too coarse for it")
            post.ok = False
    return post
