"""The NUTS diagnostics of ``calib.inference.bayes`` (rank-normalised R-hat, bulk and tail
ESS, computed by ArviZ) on synthetic chains whose answer is known."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from calib.inference.bayes import (
    CAREFUL_TARGET_ACCEPT,
    ESS_MIN,
    MAX_DRAW_FACTOR,
    RHAT_MAX,
    TARGET_ACCEPT,
    careful_run,
    chain_diagnostics,
    diagnosed,
    draw_factor,
    run_nuts,
)
from calib.model.priors import Box


def test_well_mixed_chains_pass_and_a_stuck_chain_fails():
    # 4 chains x 1000 independent N(0, 1) draws of 2 parameters: R-hat is 1 up to
    # its sampling error (about 1/(2 * 4000) ~ 1e-4 per parameter, far inside 1.01)
    rng = np.random.default_rng(0)
    good = rng.standard_normal((4, 1000, 2))
    rhat, bulk, tail = chain_diagnostics(good)
    assert rhat.shape == bulk.shape == tail.shape == (2,)
    assert np.all(np.abs(rhat - 1.0) < 0.005) and np.all(rhat < RHAT_MAX)
    # independent draws: ESS about the 4000 draws (its relative sd is a few %)
    assert np.all((bulk > 3000) & (bulk < 5000)) and np.all(tail > 2000)
    # one chain stuck in another mode (shifted by 3 sd, its own small spread)
    stuck = good.copy()
    stuck[0, :, 0] = 3.0 + 0.1 * stuck[0, :, 0]
    rhat, bulk, tail = chain_diagnostics(stuck)
    assert rhat[0] > 1.3 and rhat[1] < RHAT_MAX
    assert tail[0] < ESS_MIN < tail[1]


def test_a_chain_with_a_different_scale_fails_the_rank_statistic():
    # equal means, one chain 3x wider: the folded (tail) part of the rank-normalised
    # R-hat sees it; classic split R-hat on the draws themselves stays near 1
    rng = np.random.default_rng(1)
    x = rng.standard_normal((4, 1000, 1))
    x[0] *= 3.0
    rhat, _, _ = chain_diagnostics(x)
    assert rhat[0] > RHAT_MAX
    half = np.concatenate([x[:, :500, 0], x[:, 500:, 0]])  # split chains, untransformed
    n = half.shape[1]
    w = half.var(axis=1, ddof=1).mean()
    b = n * half.mean(axis=1).var(ddof=1)
    assert np.sqrt(((n - 1) / n * w + b / n) / w) < RHAT_MAX


def _ar1_chains(phi: float, n_chains: int, n: int, seed: int) -> np.ndarray:
    """(n_chains, n, 2) stationary AR(1) chains of unit variance with coefficient
    phi: integrated autocorrelation time (1 + phi) / (1 - phi), so ESS about
    n_chains n (1 - phi) / (1 + phi)."""
    rng = np.random.default_rng(seed)
    e = rng.standard_normal((n_chains, n, 2)) * np.sqrt(1.0 - phi**2)
    x = np.empty_like(e)
    x[:, 0] = rng.standard_normal((n_chains, 2))
    for t in range(1, n):
        x[:, t] = phi * x[:, t - 1] + e[:, t]
    return x


def _posterior(chains: np.ndarray, divergences: int = 0):
    c, n, _ = chains.shape
    stats = {"diverging": np.zeros((c, n), bool), "acceptance_rate": np.full((c, n), 0.9)}
    stats["diverging"][0, :divergences] = True
    return diagnosed(("a", "b"), chains, np.zeros(c * n), np.zeros((c * n, 1)), stats, "summed")


def test_chains_that_agree_but_are_short_get_the_draws_their_ess_asks_for():
    """AR(1) chains with an autocorrelation time of 15 (4 x 1,000 draws: ESS
    about 270) agree (R-hat < 1.01) and fail ESS alone; the factor is
    ceil(1.25 x 400 / ESS), and chains of the same sampler that many times
    longer pass every threshold."""
    phi = 7.0 / 8.0  # tau = 15
    post = _posterior(_ar1_chains(phi, 4, 1000, seed=3))
    ess = min(post.ess_bulk.min(), post.ess_tail.min())
    assert post.rhat.max() < RHAT_MAX and 125 < ess < ESS_MIN, (post.rhat, ess)
    k = draw_factor(post, 4)
    assert k == int(np.ceil(1.25 * ESS_MIN / ess)) and 1 < k <= MAX_DRAW_FACTOR
    longer = _posterior(_ar1_chains(phi, 4, 1000 * k, seed=4))
    assert longer.ok, longer.problems
    assert draw_factor(longer, 4) == 1  # nothing left to ask for


def test_no_longer_run_where_more_draws_are_not_the_repair():
    """Well-mixed chains need none; chains that disagree (one stuck elsewhere),
    a run with divergent transitions, a run that lost a chain to the screening,
    and chains so slow (ESS below 400 / 4 / 1.25) that four times the draws
    would not reach 400 get none either: 1 in every case."""
    rng = np.random.default_rng(5)
    assert draw_factor(_posterior(rng.standard_normal((4, 1000, 2))), 4) == 1
    short = _ar1_chains(7.0 / 8.0, 4, 1000, seed=3)
    assert draw_factor(_posterior(short), 4) > 1  # the cases below differ from it in one thing
    stuck = short.copy()
    stuck[0, :, 0] += 3.0
    assert _posterior(stuck).rhat[0] > RHAT_MAX and draw_factor(_posterior(stuck), 4) == 1
    assert draw_factor(_posterior(short, divergences=3), 4) == 1
    assert draw_factor(_posterior(short[:3]), 4) == 1  # 3 chains of the 4 the run had
    agreeing = dataclasses.replace(_posterior(short), rhat=np.array([1.001, 1.002]))
    assert draw_factor(dataclasses.replace(agreeing, ess_tail=np.array([130.0, 900.0])), 4) == 4
    assert draw_factor(dataclasses.replace(agreeing, ess_tail=np.array([120.0, 900.0])), 4) == 1


def test_divergences_in_chains_that_agree_ask_for_a_careful_run():
    """Well-mixed chains with divergent transitions are repaired by a smaller
    step; the same chains without divergences need nothing, and chains that
    disagree or lost one of the run's chains are repaired elsewhere."""
    rng = np.random.default_rng(6)
    good = rng.standard_normal((4, 1000, 2))
    assert careful_run(_posterior(good, divergences=4), 4)
    assert not careful_run(_posterior(good), 4)
    stuck = good.copy()
    stuck[0, :, 0] += 3.0
    assert not careful_run(_posterior(stuck, divergences=4), 4)
    assert not careful_run(_posterior(good[:3], divergences=4), 4)


# two NUTS runs, 26 s on 2 cores (2026-12-06); the careful-run rule stays in the default run
@pytest.mark.slow
def test_a_larger_target_acceptance_adapts_a_smaller_step():
    """``run_nuts`` hands its target acceptance to NumPyro's step-size
    adaptation: on the same correlated Gaussian (correlation 0.99, inside a
    wide box), key and warm-up, the careful target ends with a smaller step
    and a higher mean acceptance than the default."""
    cov_inv = jnp.linalg.inv(jnp.array([[1.0, 0.99], [0.99, 1.0]]))

    def loglik(theta):
        return (-0.5 * theta @ cov_inv @ theta)[None]

    box = Box(("a", "b"), (-10.0, -10.0), (10.0, 10.0))
    step, acc = {}, {}
    for target in (TARGET_ACCEPT, CAREFUL_TARGET_ACCEPT):
        post = run_nuts(loglik, box, jax.random.key(0), num_warmup=300, num_samples=200,
                        num_chains=2, loglik_kind="summed", target_accept_prob=target)
        step[target] = float(np.mean(post.sample_stats["step_size"]))
        acc[target] = post.accept_prob
    assert step[CAREFUL_TARGET_ACCEPT] < 0.8 * step[TARGET_ACCEPT], step
    assert acc[CAREFUL_TARGET_ACCEPT] > acc[TARGET_ACCEPT], acc
