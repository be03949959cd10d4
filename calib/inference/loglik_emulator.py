"""Gaussian-process emulator of the summed simulated log-likelihood, the density
NUTS samples inside the focus region of a CRSP fit (``calib.inference.focus``).

Model (Wilkinson 2014, "Accelerating ABC methods using Gaussian processes",
AISTATS, JMLR W&CP 33: emulate the log-likelihood itself with a GP; the cap,
the log-deficit warp and the noise model are our own choices):

    l(x) = sum_i log p(y_i | simulated runouts at x)
           (``calib.inference.likelihood`` with the design's blocks),
    y(x) = max(l(x), max_j l(x_j) - CAP_NATS_PER_ROW * n_rows)   (capped),
    g(x) = log(T - y(x)),  T = max_j y_j + delta                  (log deficit),
    g ~ GP(m, k) observed with noise v_j / (T - y_j)^2 + sn^2,

with the squared-exponential kernel and hyperparameter fit of
``calib.inference.emulator`` (inputs: the emulator's coordinates scaled to the
focus box), m the mean of the warped values, v_j the bootstrap variance of
l(x_j) over the design point's blocks (Efron 1979; carried to g by the delta
method), and delta twice the Monte Carlo sd of the best points (at least 1
nat). NUTS samples the prior times exp(E[y]), with the GP's latent
uncertainty s^2 taken through the warp: E[y] = T - exp(m + s^2/2).

Why the warp (measured on the synthetic data set 3 of
``tests/test_calib_recovery``, default budget, 60 rows): a GP of y itself
fitted a ridge at -153 nats next to a 600-nat wall, and extrapolated the
wall's slope past the ridge to +73 nats at a corner of the box (Kn 0.150,
Kt 0.980) where the simulator gives -190; NUTS sampled the corner, with all
diagnostics passing, and its 90 % intervals excluded the truth (-154
simulated). Taught that corner, the GP rose to -63 at the opposite one. On
log(T - y), y can never exceed T, and where the GP knows little (large s^2)
the expected deficit grows, so an unexplored corner looks poor instead of
promising. Same data: the posterior follows the ridge (Kn 0.17-0.57, Kt
0.63-0.95, S 0.80-2.84 m) and covers the truth (0.255, 0.856, 1.37 m).
The shape is that of warped GPs for likelihoods (Gunter et al. 2014,
"Sampling for inference in probabilistic models with fast Bayesian
quadrature", NeurIPS: the square root of the likelihood); the log of the
deficit below a ceiling is ours.

Why the log-likelihood and not the runout quantiles (measured on the Tschamut
rows, seed 1): inside the focus region the quantile emulator put its best
emulated likelihood at a corner where the simulated log-likelihood was
-5,600 (-241 emulated) and scored the design's best point (-218 simulated)
at -556; NUTS sampled the corner. Forty-three rows, each read through ten
emulated quantiles of its group, each a GP that reverts to an average runout
away from its data, add up to a likelihood that is optimistic wherever the
design is thin. A GP of the summed log-likelihood reverts to the mean of
mostly poor values there instead. Its five best points on a 16,384-point
Sobol net of the same focus box simulated at -205 to -320.

Why the cap: the summed log-likelihood falls by thousands of nats within the
focus region (blocks that stall at their release); one stationary GP cannot
follow both that wall and the peak. Below the cap, a point is e^-(CAP x
n_rows) as likely as the best one and its exact value does not matter.

Where the posterior sits, the GP is checked against the simulator
(``at_posterior``): the draws that the chain screening re-simulates are
scored by it, and ``calib.inference.calibrate`` teaches the GP those points
and samples again while it is wrong there.

What it costs: no per-row likelihood (the posterior's ``log_likelihood``
group holds the total only; PSIS-LOO over rows is not available from it).
The GP's uncertainty enters the density only through E[y]: the posterior is
not averaged over GP realisations, so where the GP is unsure it is too
narrow; ``calib.inference.realisations`` measures by how much (with
``realisation_draw``) and flags it. Where the GP is confident and wrong,
``at_posterior`` is the check.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from calib.inference.emulator import QuantileEmulator, fit_gps, predict_batch, se_kernel

__all__ = ["CAP_NATS_PER_ROW", "Z_AT_POSTERIOR_MAX", "LoglikEmulator", "at_posterior",
           "fit_loglik_emulator", "loglik_holdout", "smoothed_at_design"]

CAP_NATS_PER_ROW = 10.0
N_FEATURES = 1024  # random Fourier features of a realisation (``realisation_draw``)
Z_AT_POSTERIOR_MAX = 3.0  # RMS standardised error at the posterior's draws (``at_posterior``)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LoglikEmulator:
    """A fitted GP of the log deficit of the capped summed log-likelihood
    (module docstring): one GP of ``calib.inference.emulator`` (one "size", one
    "level"), its cap and its ceiling T = max_j y_j + delta. A pytree, so that
    compiled functions take it as an argument (``predict_batch``)."""

    gp: QuantileEmulator
    cap: float
    ceiling: float

    def predict(self, x):
        """Mean and variance of the capped log-likelihood at x (d,) (emulator
        coordinates, unscaled), nats and nats^2: with g ~ N(m, s^2) the GP's
        latent prediction of log(T - y), y = T - exp(g) has mean
        T - exp(m + s^2/2) and variance (exp(s^2) - 1) exp(2m + s^2)."""
        m, s2 = self.gp.predict(jnp.asarray(x)[None])
        m, s2 = m[0, 0], s2[0, 0]
        return (self.ceiling - jnp.exp(m + 0.5 * s2),
                jnp.expm1(s2) * jnp.exp(2 * m + s2))

    def realisation_draw(self, key: jax.Array, n_features: int = N_FEATURES) -> tuple:
        """The arrays that fix one realisation of the GP's posterior (vmap over
        keys for several): (w (L,), omega (L, d), b (L,), coef (n,)).

        Pathwise conditioning (Wilson, Borovitskiy, Terenin, Mostowsky &
        Deisenroth 2020, "Efficiently sampling functions from Gaussian process
        posteriors", ICML: Matheron's rule):

            f(x) = f0(x) + k(x, X) (K + Sigma)^-1 (y - f0(X) - e),
            e ~ N(0, Sigma),

        with f0 a draw from the prior by random Fourier features (Rahimi &
        Recht 2007) of the squared-exponential kernel,
        f0(x) = sf sqrt(2/L) sum_l w_l cos(omega_l . (x / l) + b_l),
        w_l ~ N(0, 1), omega_l ~ N(0, I), b_l ~ U(0, 2 pi), L = ``n_features``;
        coef = (K + Sigma)^-1 (y - f0(X) - e). Sigma (the design's noise:
        nugget, Monte Carlo variance, jitter) is read off the stored Cholesky
        factor: diag(L L^T) - sf^2.
        """
        gp = self.gp
        log_sf = gp.hyp[1][0, 0]
        chol, alpha = gp.chol[0, 0], gp.alpha[0, 0]
        n, d = gp.x_unit.shape
        k_w, k_o, k_b, k_e = jax.random.split(key, 4)
        w = jax.random.normal(k_w, (n_features,))
        omega = jax.random.normal(k_o, (n_features, d))
        b = jax.random.uniform(k_b, (n_features,), maxval=2 * jnp.pi)
        sf = jnp.exp(log_sf)
        noise = jnp.maximum(jnp.sum(chol * chol, axis=1) - sf * sf, 0.0)
        e = jnp.sqrt(noise) * jax.random.normal(k_e, (n,))
        # (K + Sigma)^-1 (y - f0(X) - e) = alpha - (K + Sigma)^-1 (f0(X) + e)
        f0 = self._prior_features(w, omega, b, gp.x_unit)
        coef = alpha - jax.scipy.linalg.cho_solve((chol, True), f0 + e)
        return w, omega, b, coef

    def _prior_features(self, w, omega, b, xu):
        """f0 at xu (m, d) (unit coordinates): (m,)."""
        log_ls, log_sf = self.gp.hyp[0][0, 0], self.gp.hyp[1][0, 0]
        z = (xu / jnp.exp(log_ls)) @ omega.T + b
        return jnp.exp(log_sf) * jnp.sqrt(2.0 / w.shape[0]) * (jnp.cos(z) @ w)

    def realisation_value(self, draw: tuple, x) -> jax.Array:
        """y_f(x) = T - exp(mu + sd f(x)) of the realisation ``draw``
        (``realisation_draw``) at x (d,) (emulator coordinates, unscaled)."""
        gp = self.gp
        w, omega, b, coef = draw
        xu = ((jnp.asarray(x) - gp.lo) / (gp.hi - gp.lo))[None]
        f = (self._prior_features(w, omega, b, xu)[0]
             + se_kernel(xu, gp.x_unit, gp.hyp[0][0, 0], gp.hyp[1][0, 0])[0] @ coef)
        return self.ceiling - jnp.exp(gp.y_mean[0, 0] + gp.y_std[0, 0] * f)


def _capped(ll: np.ndarray, n_rows: int) -> tuple[np.ndarray, float]:
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    cap = float(np.max(ll) - CAP_NATS_PER_ROW * n_rows)
    return np.maximum(ll, cap), cap


def fit_loglik_emulator(x: np.ndarray, ll: np.ndarray, noise_var: np.ndarray, lo, hi,
                        n_rows: int, level_of: np.ndarray | None = None) -> LoglikEmulator:
    """Fit the GP of the module docstring.

    Args:
        x: (D, d) design points in the emulator's coordinates.
        ll: (D,) their summed simulated log-likelihoods (-inf: a row got no
            finished block; capped like any value below the cap).
        noise_var: (D,) their Monte Carlo variances
            (``calib.inference.likelihood.RowLikelihood.noise_var``).
        lo, hi: (d,) the box the inputs are scaled to (the focus box).
        n_rows: observation rows (the cap is ``CAP_NATS_PER_ROW`` per row).
        level_of: (D,) bool, the points whose mean is the GP's mean m (the level
            it reverts to away from its data); None: all. Points placed where
            an emulated posterior sat (``calib.inference.calibrate``'s
            refinement waves) are left out of it: they are the best points of
            the design, and a level raised by them would make every corner
            the design has not reached look as good as the posterior.
    """
    g, nv, cap, ceiling = _log_deficit(ll, noise_var, n_rows)
    lo, hi = jnp.asarray(lo, jnp.float64), jnp.asarray(hi, jnp.float64)
    xu = (jnp.asarray(x) - lo) / (hi - lo)
    level = g if level_of is None else g[np.asarray(level_of, bool)]
    mu, sd = float(level.mean()), float(max(g.std(), 1e-3))
    hyp, chol, alpha = fit_gps(xu, jnp.asarray((g - mu) / sd)[None, None],
                               jnp.asarray(nv / sd**2)[None, None])
    gp = QuantileEmulator(xu, lo, hi, alpha, chol, hyp, jnp.full((1, 1), mu),
                          jnp.full((1, 1), sd), np.full(1, np.nan))
    return LoglikEmulator(gp, cap, ceiling)


def _log_deficit(ll, noise_var, n_rows: int):
    """The module docstring's warp of summed log-likelihoods ll (D,) with
    Monte Carlo variances noise_var: (g = log(T - y) (D,), its variance by the
    delta method var y / (T - y)^2 (D,), the cap, the ceiling T)."""
    y, cap = _capped(np.asarray(ll, float), n_rows)
    nv_y = np.where(y <= cap, 0.0, np.asarray(noise_var, float))  # a capped value: no noise
    ceiling = float(np.max(y) + _headroom_nats(y, nv_y))
    deficit = ceiling - y
    return np.log(deficit), nv_y / deficit**2, cap, ceiling


def smoothed_at_design(x: np.ndarray, sums: np.ndarray, n_rows, noise_var=0.0) -> np.ndarray:
    """The GP's values at its own design points for several summed
    log-likelihoods over one design: the emulated E[y] of the module docstring
    at each x_j, with the simulation noise smoothed out.

    Used by the discovery workflow (``calib.discovery.candidate_fit``) for its
    importance weights: the summed log-likelihood of a design point carries
    Monte Carlo noise of 1-3 nats (``loglik_noise_sd``), which makes weights
    exp(l - log q) log-normally noisy and their Pareto k-hat high even where the
    design covers the posterior; the GP's mean through the same points does
    not carry it. ``sums[0]`` (the summed log-likelihood over all rows) fixes
    the hyperparameters (``fit_loglik_emulator``); every other row of ``sums``
    (e.g. the sums over each fold's training rows) gets its own cap, ceiling,
    warp, standardisation and noise, with the same kernel (our choice: one
    hyperparameter fit per design instead of one per fold, 5-10 s each on 2
    cores at 512 points). The noise variance matters: near the best points the
    warp log(T - y) turns a few nats of noise into large errors in g, which a
    nugget alone (``noise_var`` 0) lets the luckiest points pull the GP up to
    (measured in ``tests/test_loglik_emulator.py``).

    Args:
        x: (N, d) design points, scaled to the unit cube.
        sums: (S, N) summed log-likelihoods (-inf allowed: capped).
        n_rows: (S,) the rows in each sum (the cap is ``CAP_NATS_PER_ROW`` per row).
        noise_var: the Monte Carlo variance of each sum at each point, nats^2,
            broadcast to (S, N) (e.g. (S, 1): one per sum).

    Returns:
        (S, N) the emulated means, nats.
    """
    sums = np.atleast_2d(np.asarray(sums, float))
    n, d = np.shape(x)
    nv = np.broadcast_to(np.asarray(noise_var, float), sums.shape)
    emu = fit_loglik_emulator(x, sums[0], nv[0], np.zeros(d), np.ones(d), int(n_rows[0]))
    gp = emu.gp
    log_ls, log_sf, log_sn = (h[0, 0] for h in gp.hyp)
    k = se_kernel(gp.x_unit, gp.x_unit, log_ls, log_sf)
    out = np.empty_like(sums)
    for j, (total, rows) in enumerate(zip(sums, n_rows, strict=True)):
        g, nv_g, _, ceiling = _log_deficit(total, nv[j], int(rows))
        mu, sd = float(g.mean()), float(max(g.std(), 1e-3))
        nv_g = nv_g / sd**2  # standardised, as fit_loglik_emulator's
        chol = jnp.linalg.cholesky(k + jnp.diag(jnp.exp(2 * log_sn) + nv_g + 1e-8))
        alpha = jax.scipy.linalg.cho_solve((chol, True), jnp.asarray((g - mu) / sd))
        v = jax.scipy.linalg.solve_triangular(chol, k, lower=True)
        latent = np.maximum(np.exp(2 * float(log_sf)) - np.asarray(jnp.sum(v * v, axis=0)), 0.0)
        m = mu + sd * np.asarray(k @ alpha)
        out[j] = ceiling - np.exp(m + 0.5 * sd * sd * latent)
    return out


def _headroom_nats(y: np.ndarray, noise_var: np.ndarray, n_best: int = 10) -> float:
    """delta, the most the emulated log-likelihood may exceed the design's best
    value by: twice the median Monte Carlo sd of the ``n_best`` best points, at
    least 1 nat (our choice: the best point's value is itself an estimate)."""
    best = np.argsort(-y)[:n_best]
    return float(max(1.0, 2.0 * np.sqrt(np.median(noise_var[best]))))


def at_posterior(emu: LoglikEmulator, x: np.ndarray, ll: np.ndarray, noise_var: np.ndarray
                 ) -> dict:
    """Does the GP know the simulator where the posterior sits? Its predictions
    at T draws of the posterior against their summed SIMULATED log-likelihoods.

    z_t = (l_t - m(x_t)) / sqrt(s^2(x_t) + v_t)   (l_t capped like the design's),

    with m, s^2 the GP's mean and latent variance and v_t the draw's bootstrap
    Monte Carlo variance (``RowLikelihood.noise_var``). An honest GP gives z of order
    1; the rule (ours) calls it wrong there when the RMS of z exceeds
    ``Z_AT_POSTERIOR_MAX``. Why it is needed (measured on the synthetic data
    set 3 of ``tests/test_calib_recovery``, default budget): all four chains
    agreed (R-hat ok) on a corner (Kn 0.150, Kt 0.980) where the GP promised
    +73 +- 49 nats, 226 above the design's best point; the simulator gave
    -190 there and -154 at the truth, which the posterior excluded.

    Args:
        x: (T, d) the draws in the emulator's coordinates; ll: (T,) their
            simulated log-likelihoods (-inf: capped); noise_var: (T,).

    Returns:
        dict with ``z_rms``, ``z_median``, ``emulated_median_nats``,
        ``simulated_median_nats``, ``z_max`` (the bar) and ``ok``.
    """
    mean, var = predict_batch(emu, jnp.asarray(x))
    y = np.maximum(np.where(np.isfinite(ll), ll, -np.inf), emu.cap)
    z = (y - np.asarray(mean)) / np.sqrt(np.asarray(var) + np.asarray(noise_var) + 1e-9)
    z_rms = float(np.sqrt(np.mean(z**2)))
    return {"z_rms": z_rms, "z_median": float(np.median(z)),
            "emulated_median_nats": float(np.median(np.asarray(mean))),
            "simulated_median_nats": float(np.median(y)),
            "z_max": Z_AT_POSTERIOR_MAX, "ok": bool(z_rms <= Z_AT_POSTERIOR_MAX)}


def loglik_holdout(x: np.ndarray, ll: np.ndarray, noise_var: np.ndarray, lo, hi, n_rows: int,
                   frac: float = 0.2, level_of: np.ndarray | None = None) -> dict:
    """Fit on (1 - frac) of the design (every k-th point held out), predict the
    rest (``level_of`` as in ``fit_loglik_emulator``).

    Returns:
        dict with ``target`` ("summed log-likelihood, capped"), ``rmse_nats`` and
        ``median_abs_err_nats`` of the held-out capped values, ``rmse_above_cap_nats``
        (over held-out points above the cap, None if none), ``z_rms`` (error over
        the predictive sd with the Monte Carlo noise; about 1 when honest),
        ``cap_nats_per_row``, ``n_test``, ``n_train``.
    """
    n = len(ll)
    n_test = max(2, int(round(frac * n)))
    test = np.arange(n)[::max(1, n // n_test)][:n_test]
    train = np.setdiff1d(np.arange(n), test)
    emu = fit_loglik_emulator(x[train], ll[train], noise_var[train], lo, hi, n_rows,
                              None if level_of is None else np.asarray(level_of)[train])
    mean, var = predict_batch(emu, jnp.asarray(x[test]))
    y = np.maximum(np.where(np.isfinite(ll[test]), ll[test], -np.inf), emu.cap)
    err = np.asarray(mean) - y
    z = err / np.sqrt(np.asarray(var) + np.asarray(noise_var)[test] + 1e-9)
    above = y > emu.cap
    return {"target": "summed log-likelihood, capped",
            "rmse_nats": float(np.sqrt(np.mean(err**2))),
            "median_abs_err_nats": float(np.median(np.abs(err))),
            "rmse_above_cap_nats": (float(np.sqrt(np.mean(err[above]**2))) if above.any()
                                    else None),
            "z_rms": float(np.sqrt(np.mean(z**2))),
            "cap_nats_per_row": CAP_NATS_PER_ROW,
            "n_test": int(n_test), "n_train": int(len(train))}
