"""The DEM posterior averaged over its quantile emulator's realisations
(``calib.inference.quantile_realisations``; the case: the DEM's 90 % intervals
held the truth in 8 of 12 on its own data, ``tests/test_calib_recovery.py``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from calib.inference.emulator import fit_emulator
from calib.inference.quantile_realisations import alpha_realisations, sample_expected


def _emulator(seed=0, n_design=12, n_blocks=12, n_levels=10):
    """One size, runouts N(100 + 60 alpha, 10^2) at alpha in [0, 0.95]."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 0.95, n_design)[:, None]
    runs = 100.0 + 60.0 * x[:, :, None] + 10.0 * rng.standard_normal((n_design, 1, n_blocks))
    return fit_emulator(x, runs, np.zeros(1), np.array([0.95]), n_levels=n_levels)


# inflation 1 in -m slow (25 s on 2 cores, 2026-12-06): the default run keeps the inflated case
@pytest.mark.parametrize("inflation", [pytest.param(1.0, marks=pytest.mark.slow), 4.0])
def test_realisations_have_the_gps_mean_and_inflated_variance(inflation):
    """400 joint draws on the alpha grid: at five alphas (design and between) the
    mean lies within 4 standard errors of the emulator's mean and the variance
    within 25 % of ``inflation`` times its latent variance (one level, the
    median, so that the sorting of levels plays no part)."""
    emu = _emulator(n_levels=1)
    grid = jnp.linspace(0.0, 0.95, 96)
    f = np.asarray(alpha_realisations(emu, grid, 400, jax.random.key(3), inflation))
    assert f.shape == (400, 1, 1, 96)
    at = [0, 20, 47, 70, 95]
    mean, var = jax.vmap(lambda a: emu.predict(jnp.array([[a]])))(grid[jnp.array(at)])
    mean, var = np.asarray(mean)[:, 0], np.asarray(var)[:, 0]  # (5, 1)
    draws = np.moveaxis(f[:, 0][..., at], -1, 1)  # (400, 5, K)
    se = np.sqrt(inflation * var / 400)
    assert np.all(np.abs(draws.mean(0) - mean) < 4 * se + 1e-6)
    ratio = draws.var(0) / (inflation * var)
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio


def test_realisations_keep_the_levels_in_order():
    f = np.asarray(alpha_realisations(_emulator(), jnp.linspace(0.0, 0.95, 64), 50,
                                      jax.random.key(1)))
    assert np.all(np.diff(f, axis=2) >= 0.0)


def test_realisations_need_a_one_dimensional_input():
    rng = np.random.default_rng(1)
    x = rng.random((10, 2))
    emu = fit_emulator(x, 100.0 + rng.standard_normal((10, 1, 8)), np.zeros(2), np.ones(2), 4)
    with pytest.raises(ValueError, match="one-dimensional"):
        alpha_realisations(emu, jnp.linspace(0, 1, 5), 2, jax.random.key(0))


def _grid(weights):
    """Four equal cells on [0, 2] x [0, 1]."""
    centres = np.array([[0.5, 0.25], [0.5, 0.75], [1.5, 0.25], [1.5, 0.75]])
    return centres, np.array([1.0, 0.5]), np.asarray(weights, float)


def test_draws_follow_the_grid_and_stay_in_their_cells():
    """Each cell is drawn at its weight (4000 draws: within 4 binomial standard
    errors) and every draw lies inside the cell it came from, hence in the box."""
    w = np.array([0.1, 0.2, 0.3, 0.4])
    post = sample_expected(lambda t: -jnp.sum(t)[None], _grid(w), ("a", "b"), jax.random.key(5),
                           4, 1000)
    s = post.samples
    assert s.shape == (4000, 2) and post.loglik_kind == "expected"
    assert post.pointwise_loglik.shape == (4000, 1)
    np.testing.assert_allclose(post.log_density, -s.sum(1))
    assert np.all((s >= 0) & (s <= [2.0, 1.0]))
    cell = (s[:, 0] > 1.0) * 2 + (s[:, 1] > 0.5)
    freq = np.bincount(cell, minlength=4) / len(s)
    assert np.all(np.abs(freq - w) < 4 * np.sqrt(w * (1 - w) / len(s))), freq
    # independent draws pass the chains' diagnostics; two cells per axis do not
    # resolve the 90 % intervals
    assert not post.ok and post.problems == [
        f"the 90 % interval of {n} spans {x:.1f} grid cells (< 10): the grid is too coarse "
        "for it" for n, x in zip("ab", (np.quantile(s, 0.95, 0) - np.quantile(s, 0.05, 0))
                                 / [1.0, 0.5])]


def test_a_posterior_resolved_by_the_grid_passes():
    """Forty cells per axis under a broad bump: the intervals span well over ten
    cells each and the independent draws pass every diagnostic."""
    n = 40
    ax = (np.arange(n) + 0.5) / n
    centres = np.stack([a.ravel() for a in np.meshgrid(ax, ax, indexing="ij")], 1)
    w = np.exp(-0.5 * np.sum(((centres - 0.5) / 0.15) ** 2, 1))
    post = sample_expected(lambda t: jnp.zeros(1), (centres, np.full(2, 1 / n), w / w.sum()),
                           ("a", "b"), jax.random.key(2), 4, 1000)
    assert post.ok, post.problems
