"""Bayesian calibration: NumPyro NUTS on the emulated likelihood, with diagnostics.

Model (uniform priors from ``calib.priors``; likelihood from
``calib.likelihood`` with the emulated quantiles of ``calib.emulator`` as the
simulated sample and the emulator's variance added):

    theta ~ Uniform(box),
    log p(D | theta) = sum_i log p(y_i | Q_{s(i)}(theta), v_{s(i)}(theta)).

The emulator makes the log-density smooth, so NUTS (Hoffman & Gelman 2014)
applies; NUTS on the raw simulator would not (discontinuous, noisy).
Diagnostics (Vehtari et al. 2021 thresholds): split R-hat < 1.01 and effective
sample size > 400 for every parameter, no divergent transition. A run that
misses one is returned with ``ok = False`` and the reasons; the command prints
them loudly and records them in calibration.json; it never hides them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.diagnostics import effective_sample_size, split_gelman_rubin
from numpyro.infer import MCMC, NUTS

from calib.priors import Box

__all__ = ["Posterior", "RHAT_MAX", "ESS_MIN", "run_nuts"]

RHAT_MAX = 1.01
ESS_MIN = 400.0


@dataclasses.dataclass
class Posterior:
    """Posterior draws and diagnostics.

    Attributes:
        names: parameter names.
        samples: (n_chains * n_samples, d) draws.
        log_density: (n,) unnormalised log posterior of each draw.
        pointwise_loglik: (n, n_obs) log-likelihood of each row at each draw.
        rhat, ess: (d,) split R-hat and effective sample size.
        divergences: number of divergent transitions.
        accept_prob: mean acceptance probability.
        ok: all diagnostics pass; ``problems`` lists those that do not.
    """

    names: tuple[str, ...]
    samples: np.ndarray
    log_density: np.ndarray
    pointwise_loglik: np.ndarray
    rhat: np.ndarray
    ess: np.ndarray
    divergences: int
    accept_prob: float
    ok: bool
    problems: list[str]

    @property
    def map(self) -> np.ndarray:
        """Highest-posterior-density draw (a MAP approximation)."""
        return self.samples[int(np.argmax(self.log_density))]

    def summary(self) -> dict:
        q05, q50, q95 = np.quantile(self.samples, [0.05, 0.5, 0.95], axis=0)
        mean = self.samples.mean(axis=0)
        return {n: {"map": float(self.map[i]), "mean": float(mean[i]),
                    "median": float(q50[i]), "q05": float(q05[i]), "q95": float(q95[i]),
                    "rhat": float(self.rhat[i]), "ess": float(self.ess[i])}
                for i, n in enumerate(self.names)}


def run_nuts(pointwise_loglik: Callable[[jax.Array], jax.Array], box: Box, key: jax.Array,
             num_warmup: int = 500, num_samples: int = 1000, num_chains: int = 4
             ) -> Posterior:
    """Sample theta ~ p(theta | D) with NUTS.

    Args:
        pointwise_loglik: theta (d,) -> (n_obs,) log-likelihoods; must be smooth
            and jit-able (the emulated likelihood).
        box: uniform prior.
        key: PRNG key.
        num_warmup, num_samples, num_chains: NUTS settings (chains vectorised).
    """
    lo, hi = jnp.asarray(box.lo), jnp.asarray(box.hi)

    def model():
        theta = numpyro.sample("theta", dist.Uniform(lo, hi).to_event(1))
        numpyro.factor("loglik", jnp.sum(pointwise_loglik(theta)))

    mcmc = MCMC(NUTS(model, target_accept_prob=0.9), num_warmup=num_warmup,
                num_samples=num_samples, num_chains=num_chains, chain_method="vectorized",
                progress_bar=False)
    mcmc.run(key, extra_fields=("diverging", "accept_prob"))
    by_chain = np.asarray(mcmc.get_samples(group_by_chain=True)["theta"])  # (C, N, d)
    extra = mcmc.get_extra_fields()
    samples = by_chain.reshape(-1, box.dim)
    rhat = np.asarray(split_gelman_rubin(by_chain))
    ess = np.asarray(effective_sample_size(by_chain))
    div = int(np.sum(np.asarray(extra["diverging"])))
    acc = float(np.mean(np.asarray(extra["accept_prob"])))
    pw = np.asarray(jax.jit(jax.vmap(pointwise_loglik))(jnp.asarray(samples)))
    logd = pw.sum(axis=1)  # + log prior, constant inside the box
    problems = []
    for i, n in enumerate(box.names):
        if not np.isfinite(rhat[i]) or rhat[i] >= RHAT_MAX:
            problems.append(f"R-hat of {n} is {rhat[i]:.3f} (>= {RHAT_MAX})")
        if not np.isfinite(ess[i]) or ess[i] < ESS_MIN:
            problems.append(f"ESS of {n} is {ess[i]:.0f} (< {ESS_MIN:.0f})")
    if div:
        problems.append(f"{div} divergent transitions")
    return Posterior(tuple(box.names), samples, logd, pw, rhat, ess, div, acc,
                     not problems, problems)
