"""Adaptive tempered SMC on an emulated log-likelihood, for posteriors with
several modes.

Why: NUTS chains started at the best design points stay in the mode they start
in. On the Tschamut runs (all 62, CRSP with the rolling resistance fitted) the
simulated likelihood has two ridges, a low rolling resistance with a lower Kt
and a high one with Kt near its bound, and the seed decides which one NUTS
reports (measured in ``docs/studies.md``). Tempered SMC moves a population from
the prior to the posterior through p_l(theta) ~ prior(theta) L(theta)^l,
0 = l_0 < ... < l_K = 1, resampling and moving the particles at each step, so
particles that find either ridge early keep it in proportion to its mass
(Del Moral, Doucet & Jasra 2006, JRSS B 68:411; the adaptive schedule, each
l_k chosen so that the particles' effective sample size falls to a fixed
fraction, as in Jasra, Stephens, Doucet & Tsagaris 2011, Scand. J. Stat.
38:1). The sampler is BlackJAX's ``adaptive_tempered_smc`` (its kernel with
the move's parameters passed per step).

What it gave (``scripts/fit_with_smc.py``, Tschamut all 62 runs, seed 3,
2026-11-27; ``docs/studies.md``): its four populations agreed (R-hat 1.001,
bulk ESS 7,700-8,000) where NUTS's chains had split between the ridges
(R-hat 1.54), but on the GP of the final design they all put the posterior on
one ridge, the GP-realisation check still failed, and the sampler took 732 s
of a 20.5-minute fit (NUTS: 174 s of 11.9 min). The main job keeps NUTS; the
module stays for that measurement and the next one.

Our choices:

* the particles live in unconstrained coordinates z, theta = lo + (hi - lo)
  sigmoid(z), with the uniform prior's Jacobian as the log prior;
* the move: ``N_MCMC_STEPS`` HMC steps of ``N_LEAPFROG`` leapfrog steps, the
  inverse mass matrix the particles' covariance, the step size scaled after
  each tempering step by exp(acceptance - 0.65) (a common target for HMC);
* ``n_runs`` independent populations play the role of chains: the
  rank-normalised R-hat between them says whether they agree on the modes'
  weights, and the diagnostics of ``calib.inference.bayes`` apply unchanged.
  Each population ends with one step at l = 1 (resample, then move), so its
  particles are equally weighted.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import blackjax
import jax
import jax.numpy as jnp
import numpy as np
from blackjax.smc import resampling
from blackjax.smc import tempered as tempered_smc
from blackjax.smc.adaptive_tempered import build_kernel as adaptive_kernel

from calib.inference.bayes import Posterior, diagnosed
from calib.model.priors import Box

__all__ = ["N_LEAPFROG", "N_MCMC_STEPS", "TARGET_ESS", "run_smc"]

TARGET_ESS = 0.5  # each tempering step keeps half the particles' effective sample size
N_MCMC_STEPS = 10
N_LEAPFROG = 8
_MAX_STEPS = 200  # tempering steps; an unfinished population is a problem, not a loop
_ACCEPT_TARGET = 0.65


def _transform(box: Box):
    """theta = ``box.from_unit(sigmoid(z))``, the uniform prior's log density
    in z, and the inverse (``box.to_unit``, clipped inside the box)."""

    def theta_of(z):
        return box.from_unit(jax.nn.sigmoid(z))

    def log_prior(z):  # uniform on the box, in z: the sigmoid's Jacobian
        return jnp.sum(jax.nn.log_sigmoid(z) + jax.nn.log_sigmoid(-z))

    def z_of(theta):
        u = jnp.clip(box.to_unit(theta), 1e-9, 1 - 1e-9)
        return jnp.log(u) - jnp.log1p(-u)

    return theta_of, log_prior, z_of


def _population(loglik_z, log_prior, z0, key, n_leapfrog):
    """One tempered population from the particles ``z0`` (N, d): the final
    particles (N, d) and the per-particle acceptance of the last move."""
    hmc = blackjax.hmc.build_kernel()

    def step_fn(rng_key, state, logdensity_fn, step_size, inverse_mass_matrix):
        return hmc(rng_key, state, logdensity_fn, step_size, inverse_mass_matrix, n_leapfrog)

    ada = adaptive_kernel(log_prior, loglik_z, step_fn, blackjax.hmc.init,
                          resampling.systematic, TARGET_ESS)
    fixed = tempered_smc.build_kernel(log_prior, loglik_z, step_fn, blackjax.hmc.init,
                                      resampling.systematic)

    def params(z, step):
        cov = jnp.cov(z, rowvar=False) + 1e-9 * jnp.eye(z.shape[1])
        return {"step_size": step[None], "inverse_mass_matrix": cov[None]}

    def body(carry):
        state, k, step, n, _ = carry
        k, sub = jax.random.split(k)
        state, info = ada(sub, state, N_MCMC_STEPS, params(state.particles, step))
        acc = jnp.mean(info.update_info.acceptance_rate)
        return state, k, step * jnp.exp(acc - _ACCEPT_TARGET), n + 1, acc

    def cond(carry):
        return (carry[0].tempering_param < 1.0) & (carry[3] < _MAX_STEPS)

    d = z0.shape[1]
    state = tempered_smc.init(z0)
    state, key, step, n, _ = jax.lax.while_loop(
        cond, body, (state, key, jnp.asarray(1.0 / np.sqrt(d)), 0, jnp.asarray(0.0)))
    state, info = fixed(key, state, N_MCMC_STEPS, 1.0, params(state.particles, step))
    return state.particles, info.update_info.acceptance_rate, n, state.tempering_param


def run_smc(pointwise_loglik: Callable[[jax.Array], jax.Array], box: Box, key: jax.Array,
            n_particles: int = 1000, n_runs: int = 4, loglik_kind: str = "summed",
            n_leapfrog: int = N_LEAPFROG) -> Posterior:
    """Sample theta ~ p(theta | D) with ``n_runs`` independent adaptive tempered
    SMC populations of ``n_particles`` each (module docstring).

    Args:
        pointwise_loglik: theta (d,) -> (n_obs,) log-likelihoods, or (1,) the
            summed one (``loglik_kind``); smooth and jit-able (an emulator).
        box: the uniform prior.
        key: PRNG key.
        n_particles: particles per population.
        n_runs: populations (the chains of the diagnostics).
        loglik_kind: "pointwise" or "summed" (``Posterior.loglik_kind``).
        n_leapfrog: leapfrog steps per HMC move.
    Returns:
        A ``Posterior`` whose chains are the populations; a population that did
        not reach l = 1 within ``_MAX_STEPS`` tempering steps is a problem.
    """
    theta_of, log_prior, z_of = _transform(box)

    def loglik_z(z):
        return jnp.sum(pointwise_loglik(theta_of(z)))

    k_init, k_run = jax.random.split(key)
    u = jax.random.uniform(k_init, (n_runs, n_particles, box.dim))
    z0 = z_of(box.from_unit(u))
    run = jax.jit(jax.vmap(partial(_population, loglik_z, log_prior, n_leapfrog=n_leapfrog)))
    z, acc, n_steps, lam = run(z0, jax.random.split(k_run, n_runs))
    by_chain = np.asarray(jax.vmap(jax.vmap(theta_of))(z))  # (C, N, d)
    samples = by_chain.reshape(-1, box.dim)
    pw = np.asarray(jax.jit(jax.vmap(pointwise_loglik))(jnp.asarray(samples)))
    stats = {"diverging": np.zeros(by_chain.shape[:2], bool),
             "acceptance_rate": np.asarray(acc)}
    post = diagnosed(tuple(box.names), by_chain, pw.sum(axis=1), pw, stats, loglik_kind)
    post.sample_stats["tempering_steps"] = np.repeat(np.asarray(n_steps)[:, None],
                                                     by_chain.shape[1], axis=1)
    unfinished = int(np.sum(np.asarray(lam) < 1.0))
    if unfinished:
        post.problems.append(f"{unfinished} of {n_runs} SMC populations did not reach the "
                             f"posterior within {_MAX_STEPS} tempering steps")
        post.ok = False
    return post
