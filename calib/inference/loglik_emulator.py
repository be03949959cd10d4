"""Gaussian-process emulator of the summed simulated log-likelihood, the density
NUTS samples inside the focus region of a CRSP fit (``calib.inference.focus``).

Model (Wilkinson 2014, "Accelerating ABC methods using Gaussian processes",
AISTATS, JMLR W&CP 33: emulate the log-likelihood itself with a GP and
sample its mean; the cap and the noise model are our own choices):

    l(x) = sum_i log p(y_i | simulated runouts at x)
           (``calib.inference.likelihood`` with the design's blocks),
    y(x) = max(l(x), max_j l(x_j) - CAP_NATS_PER_ROW * n_rows)   (capped),
    y ~ GP(m, k) observed with noise v_j + sn^2,

with the squared-exponential kernel and hyperparameter fit of
``calib.inference.emulator`` (inputs: the emulator's coordinates scaled to the
focus box), m the mean of the capped values, and v_j the bootstrap variance of
l(x_j) over the design point's blocks (Efron 1979). NUTS samples the prior
times exp(mean of the GP).

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

What it costs: no per-row likelihood (the posterior's ``log_likelihood``
group holds the total only; PSIS-LOO over rows is not available from it),
and the GP's own uncertainty is not propagated (its hold-out error is
reported in nats).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from calib.inference.emulator import QuantileEmulator, fit_gps

__all__ = ["CAP_NATS_PER_ROW", "LoglikEmulator", "fit_loglik_emulator", "loglik_holdout",
           "loglik_noise_var"]

CAP_NATS_PER_ROW = 10.0


@dataclasses.dataclass(frozen=True)
class LoglikEmulator:
    """A fitted GP of the capped summed log-likelihood (module docstring): one
    GP of ``calib.inference.emulator`` (one "size", one "level") and its cap."""

    gp: QuantileEmulator
    cap: float

    def predict(self, x):
        """Mean and latent variance of the capped log-likelihood at x (d,)
        (emulator coordinates, unscaled), nats and nats^2."""
        mean, var = self.gp.predict(jnp.asarray(x)[None])
        return mean[0, 0], var[0, 0]


def loglik_noise_var(loglik_runs, runouts: np.ndarray, n_boot: int = 16, seed: int = 0
                     ) -> np.ndarray:
    """(D,) Monte Carlo variance of the summed log-likelihood at each of D design
    points: bootstrap over each point's blocks (runouts (D, S, n); ``loglik_runs``
    maps (T, S, n) to (T, n_obs)); 0 where it is not finite."""
    rng = np.random.default_rng(seed)
    n = runouts.shape[-1]
    boot = np.stack([np.asarray(loglik_runs(jnp.asarray(runouts[..., rng.integers(0, n, n)])))
                     .sum(1) for _ in range(n_boot)])
    var = np.var(np.where(np.isfinite(boot), boot, np.nan), axis=0)
    return np.where(np.isfinite(var), var, 0.0)


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
        noise_var: (D,) their Monte Carlo variances (``loglik_noise_var``).
        lo, hi: (d,) the box the inputs are scaled to (the focus box).
        n_rows: observation rows (the cap is ``CAP_NATS_PER_ROW`` per row).
        level_of: (D,) bool, the points whose mean is the GP's mean m (the level
            it reverts to away from its data); None: all. Points placed where
            an emulated posterior sat (``calib.inference.calibrate``'s
            refinement waves) are left out of it: they are the best points of
            the design, and a level raised by them would make every corner
            the design has not reached look as good as the posterior.
    """
    y, cap = _capped(np.asarray(ll, float), n_rows)
    lo, hi = jnp.asarray(lo, jnp.float64), jnp.asarray(hi, jnp.float64)
    xu = (jnp.asarray(x) - lo) / (hi - lo)
    level = y if level_of is None else y[np.asarray(level_of, bool)]
    mu, sd = float(level.mean()), float(max(y.std(), 1e-3))
    below = y <= cap  # a capped value carries no Monte Carlo noise of its own
    nv = np.where(below, 0.0, np.asarray(noise_var, float)) / sd**2
    hyp, chol, alpha = fit_gps(xu, jnp.asarray((y - mu) / sd)[None, None],
                               jnp.asarray(nv)[None, None])
    gp = QuantileEmulator(xu, lo, hi, alpha, chol, hyp, jnp.full((1, 1), mu),
                          jnp.full((1, 1), sd), np.full(1, np.nan))
    return LoglikEmulator(gp, cap)


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
    mean, var = jax.vmap(emu.predict)(jnp.asarray(x[test]))
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
