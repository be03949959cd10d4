"""Unit tests of the calibration building blocks: observations, likelihood, emulator."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

import calib  # noqa: F401  (x64)
from calib.files.observations import ObservationError, load_observations
from calib.inference.emulator import fit_emulator, holdout_error, variance_inflation
from calib.inference.likelihood import R_MAX_M, RUNOUT_EPS, _log_diff_ndtr, log_likelihood


def _write(tmp_path, text, name="obs.csv"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def test_postignano_observations_load():
    obs = load_observations("data/postignano.csv")
    assert obs.n_obs == 2
    np.testing.assert_allclose(obs.block_size_m, [0.2, 2.0])
    np.testing.assert_allclose(obs.runout_m, [110.0, 220.0])
    assert not obs.is_interval.any()


def test_interval_rows(tmp_path):
    p = _write(tmp_path, "block_size_m,runout_min_m,runout_max_m\n0.5,100,150\n1.0,120,200\n")
    obs = load_observations(p)
    assert obs.is_interval.all()
    np.testing.assert_allclose(obs.centre_m, [125.0, 160.0])


@pytest.mark.parametrize("text,needle", [
    ("", "empty file"),
    ("size,runout_m,runout_sd_m\n1,100,5\n", "missing column 'block_size_m'"),
    ("block_size_m,runout_m,runout_sd_m\n", "no observation rows"),
    ("block_size_m,runout_m,runout_sd_m\n-1,100,5\n", "line 2, column 'block_size_m'"),
    ("block_size_m,runout_m,runout_sd_m\nnan,100,5\n", "line 2, column 'block_size_m'"),
    ("block_size_m,runout_m,runout_sd_m\n1,abc,5\n", "line 2, column 'runout_m'"),
    ("block_size_m,runout_m,runout_sd_m\n1,100,5\n1,100,0\n", "line 3, column 'runout_sd_m'"),
    ("block_size_m,runout_min_m,runout_max_m\n1,200,150\n", "interval min 200 > max 150"),
    ("block_size_m,runout_min_m,runout_max_m\n1,200,\n", "needs both"),
    ("block_size_m,foo\n1,2\n", "expected columns"),
])
def test_bad_observation_files_name_the_line_and_column(tmp_path, text, needle):
    p = _write(tmp_path, text)
    with pytest.raises(ObservationError, match=None) as e:
        load_observations(p)
    assert needle in str(e.value) and p in str(e.value)


def test_point_likelihood_is_the_kernel_density():
    """Two samples: the mixture of their kernels (weight 1 - eps), plus the
    defensive uniform eps / R_MAX."""
    r = jnp.array([[100.0, 130.0]])
    y, sd = jnp.array([110.0]), jnp.array([15.0])
    z = jnp.zeros(1)
    ll = log_likelihood(r, y, sd, z, z, jnp.array([False]))
    kde = 0.5 * norm.pdf(110, 100, 15) + 0.5 * norm.pdf(110, 130, 15)
    expect = math.log((1.0 - RUNOUT_EPS) * kde + RUNOUT_EPS / R_MAX_M)
    assert float(ll[0]) == pytest.approx(expect, rel=1e-10)


def test_interval_likelihood_is_a_probability_and_finite_in_the_tails():
    rng = np.random.default_rng(0)
    r = jnp.asarray(rng.normal(150.0, 10.0, (1, 4000)))
    z = jnp.zeros(1)
    ll = log_likelihood(r, z, z, jnp.array([140.0]), jnp.array([160.0]), jnp.array([True]))
    # smoothed by a kernel of width h: P = P(|N(0, 10^2 + h^2)| < 10), h small
    assert math.exp(float(ll[0])) == pytest.approx(0.683, abs=0.02)
    # far in either tail only the defensive component eps (b - a) / R_MAX is left
    far = log_likelihood(r, z, z, jnp.array([400.0]), jnp.array([500.0]), jnp.array([True]))
    assert float(far[0]) == pytest.approx(math.log(RUNOUT_EPS * 100.0 / R_MAX_M), rel=1e-9)
    lower = log_likelihood(r, z, z, jnp.array([0.0]), jnp.array([10.0]), jnp.array([True]))
    assert float(lower[0]) == pytest.approx(math.log(RUNOUT_EPS * 10.0 / R_MAX_M), rel=1e-9)
    # and the kernel's own tail probability stays finite (no 0 - 0 underflow)
    for hi, lo in ((-30.0, -40.0), (40.0, 30.0)):
        v = float(_log_diff_ndtr(jnp.asarray(hi), jnp.asarray(lo)))
        assert np.isfinite(v) and v < -400


def test_emulator_learns_a_smooth_quantile_function_and_its_uncertainty_is_honest():
    """Runouts ~ N(100 + 40 x0^2 + 10 x1, 5^2): quantiles are smooth in x; the GP
    must predict held-out quantiles to within a metre and with z_rms near 1."""
    rng = np.random.default_rng(1)
    x = rng.random((60, 2))
    mean = 100 + 40 * x[:, 0] ** 2 + 10 * x[:, 1]
    runs = mean[:, None, None] + 5.0 * rng.standard_normal((60, 1, 400))
    err = holdout_error(x, runs, np.zeros(2), np.ones(2), n_levels=5)
    print(err)
    assert err["rmse_m"] < 1.0
    assert 0.3 < err["z_rms"] < 3.0
    emu = fit_emulator(x, runs, np.zeros(2), np.ones(2), n_levels=5)
    m, v = emu.predict(jnp.array([[0.5, 0.5]]))
    expect = 100 + 10 + 5 + 5.0 * norm.ppf(emu.levels)
    np.testing.assert_allclose(np.asarray(m)[0], expect, atol=1.5)
    assert np.all(np.diff(np.asarray(m)[0]) >= 0)


def test_same_key_same_forward_runouts():
    from calib.model.forward import CrspForward
    from solvers.profile import load_profile

    prof = load_profile("data/postignano_profile.csv")
    fw = CrspForward(prof, np.array([0.5, 1.5]), 32, jax.random.key(3))
    th = np.array([[0.4, 0.85, 1.0], [0.3, 0.9, 2.0]])
    a, b = fw.runouts(th), fw.runouts(th[::-1])
    np.testing.assert_array_equal(a, b[::-1])  # same block keys whatever the batch


def test_variance_inflation_keeps_errors_far_below_the_tolerance_harmless():
    """Held-out quantiles that sit on an atom (many blocks stopping at one point)
    have Monte Carlo and latent variances of ~1e-6 m^2; errors of 0.2 m there
    give z ~ 80 (the old rule inflated every output by z_rms^2 ~ 6400 x its own
    variance). Here the inflated variance of those outputs only grows to their
    squared error, 0.04 m^2, harmless next to a 3 m tolerance; and mixed with
    well-emulated outputs (v = 1 m^2, errors ~1 m) the factor stays modest."""
    err = np.full(50, 0.2)
    var = np.full(50, 1e-6)
    noise = np.full(50, 1e-6)
    c = variance_inflation(err, var, noise, kernel_var_m2=9.0)
    assert c * 1e-6 < 0.05
    rng = np.random.default_rng(3)
    mixed_err = np.concatenate([err, rng.standard_normal(50)])
    mixed_var = np.concatenate([var, np.ones(50)])
    mixed_noise = np.concatenate([noise, np.zeros(50)])
    assert variance_inflation(mixed_err, mixed_var, mixed_noise, kernel_var_m2=9.0) < 20.0


def test_variance_inflation_adds_the_emulator_error_to_the_tolerance():
    """One output, s^2 = 4, v = 1, no noise, e^2 = 25: the likelihood's variance
    must become s^2 + e^2 (c = 25), not e^2 (c = 21, the rule of unit mean
    square against s^2 + c v). And the balance holds for many outputs."""
    c = variance_inflation(np.array([5.0]), np.array([1.0]), np.array([0.0]), kernel_var_m2=4.0)
    np.testing.assert_allclose(c, 25.0, rtol=1e-6)
    rng = np.random.default_rng(0)
    var = rng.uniform(0.5, 2.0, 200)
    noise = rng.uniform(0.0, 0.5, 200)
    err = 6.0 * rng.standard_normal(200)
    c = variance_inflation(err, var, noise, kernel_var_m2=1.0)
    assert c > 1.0
    bal = np.mean((err**2 - noise - c * var) / (1.0 + noise + 1e-9 + c * var))
    assert abs(bal) < 1e-6
    assert variance_inflation(2 * err, var, noise, kernel_var_m2=1.0) > c
