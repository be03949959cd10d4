"""Tempered SMC (calib.inference.smc) on targets whose answer is known.

Slow (about 30 s together, mostly compiling the sampler): the module serves
a study script (``scripts/fit_with_smc.py``), not the default path of any
command.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from calib.inference.smc import run_smc
from calib.model.priors import Box

BOX = Box(("a", "b"), (0.0, 0.0), (1.0, 1.0))
W_LEFT = 0.3  # mass of the left mode


def two_thin_modes(t):
    """Two modes at a = 0.25 and 0.75 holding 0.3 and 0.7 of the mass, each with
    sd 0.02 in a and 0.005 in b (thin, as the CRSP posterior is in S)."""
    def mode(a0):
        return -0.5 * ((t[0] - a0) / 0.02) ** 2 - 0.5 * ((t[1] - 0.5) / 0.005) ** 2
    return jnp.logaddexp(jnp.log(W_LEFT) + mode(0.25), jnp.log(1 - W_LEFT) + mode(0.75))[None]


@pytest.mark.slow
def test_every_population_finds_both_modes_in_proportion():
    post = run_smc(two_thin_modes, BOX, jax.random.key(1), n_particles=800, n_runs=4)
    by_run = post.samples.reshape(4, -1, 2)
    left = (by_run[..., 0] < 0.5).mean(axis=1)
    # binomial sd of a fraction of 800 independent draws is 0.016; resampled
    # particles are not independent, so 4 sd of that
    assert np.all(np.abs(left - W_LEFT) < 0.065), left
    assert post.ok, post.problems
    s = post.samples
    for a0 in (0.25, 0.75):
        m = s[np.abs(s[:, 0] - a0) < 0.15]
        assert abs(m[:, 0].std() - 0.02) < 0.004 and abs(m[:, 1].std() - 0.005) < 0.001
    assert np.all((s >= 0.0) & (s <= 1.0))


@pytest.mark.slow
def test_a_flat_likelihood_returns_the_prior():
    post = run_smc(lambda t: jnp.zeros(1), BOX, jax.random.key(2), n_particles=500, n_runs=2)
    s = post.samples
    assert np.all(np.abs(s.mean(axis=0) - 0.5) < 0.05)
    assert np.all(np.abs(s.std(axis=0) - np.sqrt(1 / 12)) < 0.03)
    assert np.all(post.sample_stats["tempering_steps"] <= 1)
