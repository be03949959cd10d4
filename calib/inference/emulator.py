"""Gaussian-process emulator of runout quantiles as smooth functions of the parameters.

The simulators are stochastic and their runouts are not smooth in the
parameters, so Bayesian inference runs on an EMULATOR (Kennedy & O'Hagan 2001;
for mass flows: Zhao & Kowalski 2022). For each block size s and each of K
probability levels p_k = (k - 1/2)/K we estimate the runout quantile
Q_s(p_k; x) at design points x (simulations with common random numbers), and
fit one GP per (s, k):

    Q(x) ~ GP(m, k),  k(x, x') = sf^2 exp(-1/2 sum_d ((x_d - x'_d)/l_d)^2),
    observed with noise v_i + sn^2: v_i the Monte Carlo variance of the quantile
    estimate at design point i (bootstrap over its blocks), sn^2 a fitted nugget,

inputs scaled to [0, 1]^d and outputs standardised. Hyperparameters (l_d, sf,
sn) maximise the log marginal likelihood (Rasmussen & Williams 2006, eq. 2.30)
with Adam (optax), all GPs at once (vmap). Prediction gives the posterior mean
(eq. 2.25) and the latent variance (eq. 2.26), which the likelihood adds to the
measurement variance, so a poorly emulated region is not over-trusted.

``holdout_error`` fits on part of the design and reports the error on the rest.

Unfinished blocks (NaN runouts, ``calib.model.unfinished``) are left out of every
quantile and of its bootstrap; a design point where some size has no finished
block at all has no quantiles and is left out of the fit.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax

from calib.model.unfinished import nan_quantile

__all__ = ["QuantileEmulator", "fit_emulator", "fit_gps", "holdout_error", "quantile_levels",
           "se_kernel", "variance_inflation"]


def quantile_levels(k: int) -> np.ndarray:
    """p_k = (k - 1/2) / K, k = 1..K."""
    return (np.arange(k) + 0.5) / k


def se_kernel(x1, x2, log_ls, log_sf):
    """Squared-exponential kernel sf^2 exp(-1/2 sum_d ((x_d - x'_d)/l_d)^2), (n1, n2)."""
    d = (x1[:, None, :] - x2[None, :, :]) / jnp.exp(log_ls)
    return jnp.exp(2 * log_sf - 0.5 * jnp.sum(d * d, -1))


def _nlml(h, x, y, nv):
    log_ls, log_sf, log_sn = h
    k = se_kernel(x, x, log_ls, log_sf) + jnp.diag(jnp.exp(2 * log_sn) + nv + 1e-8)
    chol = jnp.linalg.cholesky(k)
    a = jax.scipy.linalg.cho_solve((chol, True), y)
    return 0.5 * y @ a + jnp.sum(jnp.log(jnp.diag(chol))) + 0.5 * y.shape[0] * jnp.log(2 * jnp.pi)


def _clip(h):
    log_ls, log_sf, log_sn = h
    return (jnp.clip(log_ls, jnp.log(0.03), jnp.log(5.0)), jnp.clip(log_sf, -3.0, 2.0),
            jnp.clip(log_sn, jnp.log(1e-3), jnp.log(1.0)))


def _fit_one(x, y, nv):
    d = x.shape[1]
    h = (jnp.full((d,), jnp.log(0.3)), jnp.asarray(0.0), jnp.asarray(jnp.log(0.1)))
    opt = optax.adam(0.08)
    state = opt.init(h)

    def step(carry, _):
        h, state = carry
        g = jax.grad(_nlml)(h, x, y, nv)
        upd, state = opt.update(g, state)
        return (_clip(optax.apply_updates(h, upd)), state), None

    (h, _), _ = jax.lax.scan(step, (h, state), None, length=200)
    return h


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class QuantileEmulator:
    """Fitted GPs: outputs (S, K) at per-size inputs x (S, d).

    Attributes:
        x_unit: (n, d) design inputs scaled to [0, 1].
        lo, hi: (d,) input scaling box.
        alpha: (S, K, n) K^-1 y of each GP.
        chol: (S, K, n, n) Cholesky factors.
        hyp: (log_ls (S,K,d), log_sf (S,K), log_sn (S,K)).
        y_mean, y_std: (S, K) output standardisation, m.
        levels: (K,) probability levels (NaN where the GPs emulate something
            else: ``calib.inference.loglik_emulator``).

    A pytree (every field an array leaf), so that compiled functions take it as
    an argument (``predict_batch``).
    """

    x_unit: jax.Array
    lo: jax.Array
    hi: jax.Array
    alpha: jax.Array
    chol: jax.Array
    hyp: tuple
    y_mean: jax.Array
    y_std: jax.Array
    levels: np.ndarray

    def predict(self, x):
        """Mean and latent variance of the quantiles, (S, K) each, m and m^2.

        Args:
            x: (S, d) the emulator input of each size (unscaled).
        """
        xu = (jnp.asarray(x) - self.lo) / (self.hi - self.lo)

        def one(xs, alpha, chol, log_ls, log_sf, mu, sd):
            ks = se_kernel(xs[None, :], self.x_unit, log_ls, log_sf)[0]
            mean = ks @ alpha
            v = jax.scipy.linalg.solve_triangular(chol, ks, lower=True)
            var = jnp.maximum(jnp.exp(2 * log_sf) - v @ v, 1e-12)
            return mu + sd * mean, sd * sd * var

        per_k = jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0, 0))
        per_s = jax.vmap(per_k, in_axes=(0, 0, 0, 0, 0, 0, 0))
        mean, var = per_s(xu, self.alpha, self.chol, self.hyp[0], self.hyp[1], self.y_mean,
                          self.y_std)
        # quantiles must not cross: sort the means (a permutation, continuous in x)
        return jnp.sort(mean, axis=-1), var


@jax.jit
def predict_batch(emu, x: jax.Array):
    """``emu.predict`` over a leading batch axis of x, for either emulator
    pytree: a ``QuantileEmulator``, x (B, S, d) -> means and latent variances
    (B, S, K) each; a ``calib.inference.loglik_emulator.LoglikEmulator``, x
    (n, d) -> means (n,) and variances (n,), nats and nats^2.

    Compiled with the emulator as an argument, not a constant: a closure over
    ``emu`` folds its arrays (the Cholesky factors: n^2 per GP) into the program,
    which is then compiled anew for every fitted emulator and never found in the
    compilation cache; as an argument, one program serves every emulator of the
    same array shapes."""
    return jax.vmap(emu.predict)(x)


def _bootstrap_var(runouts: np.ndarray, levels: np.ndarray, n_boot: int = 64) -> np.ndarray:
    """Monte Carlo variance of each quantile estimate, (n, S, K): bootstrap over the
    blocks of each design point (Efron 1979); the GP takes it as known noise."""
    rng = np.random.default_rng(0)
    n_blocks = runouts.shape[-1]
    idx = rng.integers(0, n_blocks, (n_boot, n_blocks))
    boot = nan_quantile(runouts[..., idx], levels, axis=-1)  # (K, n, S, n_boot)
    # a resample that drew no finished block has no quantile: the variance is
    # over the resamples that have one
    return np.moveaxis(_nanvar(boot), 0, -1)


def _nanvar(a: np.ndarray) -> np.ndarray:
    """Variance over the last axis of the finite values (0 with fewer than 2)."""
    ok = np.isfinite(a)
    if ok.all():
        return a.var(axis=-1)
    n = ok.sum(axis=-1)
    mean = np.where(ok, a, 0.0).sum(axis=-1) / np.maximum(n, 1)
    ss = np.where(ok, (np.where(ok, a, 0.0) - mean[..., None]) ** 2, 0.0).sum(axis=-1)
    return np.where(n >= 2, ss / np.maximum(n, 1), 0.0)


def _quantiles(runouts: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """(n, S, n_blocks) -> (n, S, K), over the finished blocks (NaN: none)."""
    return np.moveaxis(nan_quantile(runouts, levels, axis=-1), 0, -1)


def _usable(x: np.ndarray, runouts: np.ndarray):
    """The design points whose every size has a finished block."""
    keep = np.all(np.any(np.isfinite(runouts), axis=-1), axis=-1)
    return np.asarray(x)[keep], np.asarray(runouts)[keep]


def fit_emulator(x: np.ndarray, runouts: np.ndarray, lo, hi, n_levels: int = 10
                 ) -> QuantileEmulator:
    """Fit one GP per (size, quantile level) to a design.

    Args:
        x: (n, d) design inputs.
        runouts: (n, S, n_blocks) simulated runouts at the design, m (NaN: an
            unfinished block, left out).
        lo, hi: (d,) input box (for scaling).
        n_levels: K quantile levels.
    """
    levels = quantile_levels(n_levels)
    x, runouts = _usable(x, runouts)
    q = _quantiles(runouts, levels)  # (n, S, K)
    lo, hi = jnp.asarray(lo, jnp.float64), jnp.asarray(hi, jnp.float64)
    xu = (jnp.asarray(x) - lo) / (hi - lo)
    mu = q.mean(axis=0)
    sd = np.maximum(q.std(axis=0), 1e-3)
    y_sk = jnp.moveaxis(jnp.asarray((q - mu) / sd), 0, -1)  # (S, K, n) standardised
    nv_sk = jnp.moveaxis(jnp.asarray(_bootstrap_var(runouts, levels) / sd**2), 0, -1)
    hyp, chol, alpha = fit_gps(xu, y_sk, nv_sk)
    return QuantileEmulator(xu, lo, hi, alpha, chol, hyp, jnp.asarray(mu), jnp.asarray(sd),
                            levels)


@jax.jit
def fit_gps(xu, y_sk, nv_sk):
    """Hyperparameters, Cholesky factors and K^-1 y of a set of GPs on the same
    inputs: xu (n, d) scaled to [0, 1], standardised outputs y_sk (S, K, n) and
    their known noise variances nv_sk (S, K, n) (here: every (size, level)).
    Returns (log_ls (S,K,d), log_sf (S,K), log_sn (S,K)), chol (S,K,n,n) and
    alpha (S,K,n)."""
    hyp = jax.vmap(jax.vmap(_fit_one, in_axes=(None, 0, 0)), in_axes=(None, 0, 0))(
        xu, y_sk, nv_sk)

    def factor(log_ls, log_sf, log_sn, y, nv):
        k = se_kernel(xu, xu, log_ls, log_sf) + jnp.diag(jnp.exp(2 * log_sn) + nv + 1e-8)
        chol = jnp.linalg.cholesky(k)
        return chol, jax.scipy.linalg.cho_solve((chol, True), y)

    chol, alpha = jax.vmap(jax.vmap(factor))(hyp[0], hyp[1], hyp[2], y_sk, nv_sk)
    return hyp, chol, alpha


def variance_inflation(err_m: np.ndarray, latent_var_m2: np.ndarray, noise_var_m2: np.ndarray,
                       kernel_var_m2: float) -> float:
    """The factor c >= 1 on the emulator's latent variance that makes it account
    for the held-out errors, weighted by the variance the likelihood gives each
    emulated quantile:

        mean_i (e_i^2 - n_i - c v_i) / (s^2 + n_i + c v_i) = 0,

    with e_i the held-out error, n_i the Monte Carlo noise of the held-out
    quantile (part of e_i^2 that is not the emulator's), v_i the latent variance
    and s^2 the likelihood's kernel variance (the rows' measurement tolerance,
    ``calib.inference.likelihood``). Solved, c v_i matches e_i^2 - n_i on average, so the
    likelihood's variance s^2 + c v_i adds the emulator's error to the
    measurement's. The left side falls monotonically in c (its derivative is
    -v_i (e_i^2 + s^2) / (s^2 + n_i + c v_i)^2); c = 1 when it is <= 0 at c = 1.
    Our own choice, and why the weights: where many blocks stop at one point
    (e.g. the foot of a talus) n_i and v_i are ~1e-6 m^2; an unweighted z-score
    mean(e^2 / (n + v)) then scores a 0.2 m error as z = 80 and one global factor
    inflates every other output by thousands. Here such an output asks only for
    c v_i ~ e_i^2 (harmless next to s^2) and weighs 1/s^2 in the balance.
    """
    e2 = np.asarray(err_m, float) ** 2
    v = np.asarray(latent_var_m2, float)
    n = np.asarray(noise_var_m2, float)
    base = kernel_var_m2 + n + 1e-9

    def balance(c):
        return float(np.mean((e2 - n - c * v) / (base + c * v)))

    if balance(1.0) <= 0.0:
        return 1.0
    lo, hi = 1.0, 2.0
    while balance(hi) > 0.0 and hi < 1e15:
        lo, hi = hi, hi * 4.0
    for _ in range(200):  # bisection in log c
        mid = float(np.sqrt(lo * hi))
        lo, hi = (mid, hi) if balance(mid) > 0.0 else (lo, mid)
    return hi


def holdout_error(x: np.ndarray, runouts: np.ndarray, lo, hi, n_levels: int = 10,
                  frac: float = 0.2, per_size_inputs=None, kernel_var_m2: float = 0.0) -> dict:
    """Fit on (1 - frac) of the design, predict the rest.

    Args:
        per_size_inputs: callable x_row -> (S, d) inputs (default: the row for every size).
        kernel_var_m2: the likelihood's kernel variance s^2 (``variance_inflation``).

    Returns:
        dict with ``rmse_m`` (root-mean-square error of the held-out quantiles),
        ``noise_sd_m`` (the fitted Monte Carlo noise of a quantile estimate, RMS
        over outputs), ``z_rms`` (RMS of error / predictive sd including that
        noise; about 1 when the GP's uncertainty is honest), ``median_abs_err_m``,
        ``variance_inflation`` (``variance_inflation`` at ``kernel_var_m2``),
        ``n_test``, ``n_train``.
    """
    x, runouts = _usable(x, runouts)
    n = x.shape[0]
    n_test = max(2, int(round(frac * n)))
    idx = np.arange(n)
    test = idx[::max(1, n // n_test)][:n_test]
    train = np.setdiff1d(idx, test)
    emu = fit_emulator(x[train], runouts[train], lo, hi, n_levels)
    q = _quantiles(runouts[test], emu.levels)
    n_s = runouts.shape[1]
    noise = _bootstrap_var(runouts[test], emu.levels)  # (n_test, S, K)
    xt = np.stack([per_size_inputs(row) if per_size_inputs
                   else np.broadcast_to(row, (n_s, len(row))) for row in x[test]])
    mean, var = predict_batch(emu, jnp.asarray(xt))
    errs = np.asarray(mean) - q
    zs = errs / np.sqrt(np.asarray(var) + noise + 1e-6)
    return {"rmse_m": float(np.sqrt(np.mean(errs**2))),
            "noise_sd_m": float(np.sqrt(np.mean(noise))),
            "z_rms": float(np.sqrt(np.mean(zs**2))),
            "median_abs_err_m": float(np.median(np.abs(errs))),
            "variance_inflation": variance_inflation(errs, np.asarray(var), noise,
                                                     kernel_var_m2),
            "n_test": int(n_test),
            "n_train": int(len(train))}
