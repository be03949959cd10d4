"""The GP of the summed simulated log-likelihood (``calib.inference.loglik_emulator``)
and the chain screening that keeps NUTS's chains where the simulator fits
(``calib.inference.calibrate``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import qmc

from calib.inference.bayes import keep_chains
from calib.inference.importance import ess, psis_weights
from calib.inference.likelihood import RowLikelihood
from calib.inference.loglik_emulator import (
    CAP_NATS_PER_ROW,
    fit_loglik_emulator,
    loglik_holdout,
    smoothed_at_design,
)

LO, HI = np.zeros(2), np.ones(2)


def _peak(x):
    """A log-likelihood of 10 rows: a sharp peak at (0.3, 0.6), -2,000 at the far corner."""
    return -40.0 - 4000.0 * ((x[..., 0] - 0.3) ** 2 + 0.5 * (x[..., 1] - 0.6) ** 2)


@pytest.mark.slow  # 29 s on 2 cores (2026-12-06): a GP fit on a sharp peak
def test_the_emulator_finds_the_peak_and_caps_the_wall():
    """Fitted on 96 Sobol points with 4 nats^2 of noise: held-out points above the
    cap within a fifth of the 100 nats the values span there (the GP cannot
    follow the kink at the cap exactly; measured 10.0 nats RMS), the emulated
    maximum within 0.03 of the true one, and
    values below the cap (max - 10 nats x 10 rows) emulated as the cap, not
    as the wall's -2,000."""
    rng = np.random.default_rng(0)
    x = qmc.Sobol(2, scramble=True, seed=0).random_base2(7)[:96]
    ll = _peak(x) + 2.0 * rng.standard_normal(96)
    noise = np.full(96, 4.0)
    check = loglik_holdout(x, ll, noise, LO, HI, 10)
    assert check["rmse_above_cap_nats"] < 20.0, check
    assert check["n_test"] + check["n_train"] == 96
    emu = fit_loglik_emulator(x, ll, noise, LO, HI, 10)
    assert np.isclose(emu.cap, ll.max() - CAP_NATS_PER_ROW * 10)
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 101), np.linspace(0, 1, 101)), -1).reshape(-1, 2)
    mean = np.asarray(jax.vmap(lambda u: emu.predict(u)[0])(jnp.asarray(grid)))
    assert np.linalg.norm(grid[np.argmax(mean)] - [0.3, 0.6]) < 0.03
    far = float(emu.predict(jnp.array([1.0, 0.0]))[0])
    assert abs(far - emu.cap) < 30.0, (far, emu.cap)


# slow (17 s, GP fits on 512 points): the default run keeps the property at the
# discovery's level (test_discovery_proposals.py::test_discovery_weights_from_the_smoothed_
# log_likelihood_do_not_collapse, the same 512-point design through candidate_fit)
@pytest.mark.slow
def test_smoothing_the_design_s_log_likelihood_mends_noisy_importance_weights():
    """512 uniform points of the unit cube (3 parameters) under a Gaussian
    log-likelihood (sd 0.15 per parameter, 60 rows) seen with 2.5 nats of
    simulation noise, as a design's summed log-likelihoods are: the raw weights
    exp(l) collapse (Pareto k-hat above 0.7); the GP's smoothed values, told
    the noise variance, give weights with k-hat below min(0.7, 1 - 1/log10 512)
    = 0.63, an ESS near the exact weights' and the posterior mean within 0.03
    of the truth (measured: raw k-hat 1.18, ESS 6; smoothed 0.01 and 108;
    exact 0.16 and 80; without the noise variance, the nugget alone: 0.65 and
    21). A second sum (a fold's training rows: 4/5 of the same surface, 4/5 of
    the noise variance) is smoothed with its own ceiling on the same kernel."""
    rng = np.random.default_rng(3)
    x = rng.uniform(size=(512, 3))
    exact = -0.5 * np.sum(((x - 0.45) / 0.15) ** 2, axis=1) - 150.0
    noisy = exact + 2.5 * rng.standard_normal(512)
    sums = np.stack([noisy, 0.8 * noisy])
    smooth = smoothed_at_design(x, sums, [60, 48], np.array([[6.25], [4.0]]))
    assert smooth.shape == (2, 512)
    w_raw, k_raw = psis_weights(noisy)
    w_exact, _ = psis_weights(exact)
    w, k = psis_weights(smooth[0])
    assert k_raw > 0.7 and ess(w_raw) < 15
    assert k < 1 - 1 / np.log10(512)
    assert ess(w) > 0.6 * ess(w_exact)
    np.testing.assert_allclose(w @ x, 0.45, atol=0.03)
    w_fold, k_fold = psis_weights(smooth[1])
    assert k_fold < 1 - 1 / np.log10(512)
    np.testing.assert_allclose(w_fold @ x, 0.45, atol=0.03)


@pytest.mark.slow  # 11 s
def test_points_added_at_the_posterior_do_not_raise_the_level_far_from_them():
    """A refinement wave adds the best points of a design (where the chains
    sat). Counted in the GP's mean they raise the level it reverts to away
    from its data, and an unexplored corner looks almost as good as the peak
    (the Postignano main job's chains went to such corners). With
    ``level_of`` the level is the space-filling design's, as before the
    wave."""
    rng = np.random.default_rng(1)
    fill = qmc.Sobol(2, scramble=True, seed=1).random_base2(5)[:24] * 0.6  # the far corner empty
    near = np.array([0.3, 0.6]) + 0.03 * rng.standard_normal((64, 2))
    x = np.concatenate([fill, near])
    ll = _peak(x) + 1.0 * rng.standard_normal(len(x))
    noise = np.full(len(x), 1.0)
    level_of = np.arange(len(x)) < len(fill)
    corner = jnp.array([1.0, 1.0])
    raised = float(fit_loglik_emulator(x, ll, noise, LO, HI, 10).predict(corner)[0])
    kept = float(fit_loglik_emulator(x, ll, noise, LO, HI, 10, level_of).predict(corner)[0])
    emu = fit_loglik_emulator(x, ll, noise, LO, HI, 10, level_of)
    capped = np.maximum(ll, emu.cap)
    # the level of the fill, in the warped coordinates: the deficits' geometric mean;
    # far from the data the GP's variance makes the expected deficit larger still
    fill_level = emu.ceiling - np.exp(np.mean(np.log(emu.ceiling - capped[level_of])))
    assert kept <= fill_level + 1.0, (kept, fill_level)
    assert raised > kept + 20.0, (raised, kept)
    check = loglik_holdout(x, ll, noise, LO, HI, 10, level_of=level_of)
    assert check["n_test"] + check["n_train"] == len(x)


def test_a_flat_ridge_next_to_a_wall_gets_no_invented_peak():
    """The log-likelihood is flat (-40 nats) on a ridge and falls by up to
    3,000 nats beyond it (the synthetic data sets of ``test_calib_recovery``
    look like this: Kn, Kt and S trade off along a ridge). On 80 noisy Sobol
    points (sd 1 nat), the emulated maximum over a 101 x 101 grid stays below
    the best design value plus the headroom (twice the Monte Carlo sd, 2
    nats). A GP of the log-likelihood itself (before the log-deficit warp)
    carried the wall's slope past the ridge and promised -25.2 nats at its
    edge, 13 nats above the best design point and 15 above the truth; on data
    set 3 of ``test_calib_recovery`` it promised 226 nats above the best
    point, at a corner NUTS then sampled. The price of the ceiling: between
    design points it cannot promise much more than the best of them, so a
    peak the design missed is found by the refinement waves, not emulated."""
    rng = np.random.default_rng(0)
    x = qmc.Sobol(2, scramble=True, seed=0).random_base2(7)
    x = x[np.linalg.norm(x, axis=1) > 0.3][:80]
    ll = -40.0 - 3000.0 * np.maximum(0, x[:, 0] + 0.5 * x[:, 1] - 0.5) ** 2
    ll = ll + rng.standard_normal(len(x))
    emu = fit_loglik_emulator(x, ll, np.full(len(x), 1.0), LO, HI, 10)
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 101), np.linspace(0, 1, 101)), -1).reshape(-1, 2)
    mean = np.asarray(jax.vmap(lambda u: emu.predict(u)[0])(jnp.asarray(grid)))
    assert mean.max() <= ll.max() + 2.0 + 1e-9, (mean.max(), ll.max())


def test_noise_variance_falls_with_the_number_of_blocks():
    """Bootstrap over a design point's blocks: four times the blocks, about a
    quarter of the variance of the summed log-likelihood."""
    from calib.files.observations import Observations

    rng = np.random.default_rng(1)
    # two point rows of one size, 5 m tolerance: a Gaussian kernel at 5 m
    rows = RowLikelihood(Observations.points([0.5, 0.5], [100.0, 120.0], [5.0, 5.0]))
    small = rows.noise_var(110 + 10 * rng.standard_normal((3, 1, 200)), n_boot=64)
    large = rows.noise_var(110 + 10 * rng.standard_normal((3, 1, 800)), n_boot=64)
    ratio = float(np.mean(small) / np.mean(large))
    assert 2.5 < ratio < 6.0, ratio


def test_chains_the_simulator_fits_far_worse_are_dropped():
    """Four chains, one sitting where the simulated log-likelihood is 500 nats
    below the others': it is dropped, the diagnostics are recomputed on the
    other three, and nothing is dropped when all agree."""
    from calib.inference.bayes import Posterior
    from calib.inference.chains import screen_chains

    rng = np.random.default_rng(2)
    c, n = 4, 200
    centre = np.array([[0.3, 0.6], [0.3, 0.6], [0.3, 0.6], [0.9, 0.1]])
    draws = centre[:, None, :] + 0.01 * rng.standard_normal((c, n, 2))
    stats = {"diverging": np.zeros((c, n), bool), "acceptance_rate": np.full((c, n), 0.9)}
    post = Posterior(("a", "b"), draws.reshape(-1, 2), np.zeros(c * n), np.zeros((c * n, 1)),
                     np.ones(2), np.ones(2), np.ones(2), 0, 0.9, False, ["R-hat"], c, stats,
                     "summed")

    def runouts(theta):  # one entry, one "block" whose runout is the point's quality
        return np.where(theta[:, 0] > 0.6, -500.0, -50.0)[:, None, None]

    def simulate(theta):  # runouts, no passage speeds
        return runouts(theta), None

    class Rows:  # 10 rows whose summed log-likelihood is the point's one "runout"
        n_rows = 10

        def summed(self, runs, speeds=None):
            return runs[:, 0, 0]

    kept, rec, (theta, runs, speeds) = screen_chains(post, simulate, Rows())
    assert speeds is None
    assert rec["kept"] == [True, True, True, False] and rec["n_dropped"] == 1
    # the screened draws (8 per chain, the dropped chain's too) come back for the
    # next refinement wave, with their simulations
    assert theta.shape == (4 * 8, 2) and runs.shape == (4 * 8, 1, 1)
    assert np.array_equal(runs, runouts(theta))
    assert kept.n_chains == 3 and kept.samples.shape == (3 * n, 2)
    assert kept.rhat.max() < 1.05 and kept.ok is not None and kept.loglik_kind == "summed"
    same, rec, _ = screen_chains(keep_chains(post, [True, True, True, False]), simulate,
                                  Rows())
    assert rec["n_dropped"] == 0 and same.n_chains == 3


def test_one_chain_gets_a_finite_r_hat_from_its_halves():
    from calib.inference.bayes import chain_diagnostics

    rng = np.random.default_rng(3)
    rhat, bulk, tail = chain_diagnostics(rng.standard_normal((1, 400, 2)))
    assert np.all(np.isfinite(rhat)) and np.all(rhat < 1.05)
    drift = np.linspace(0, 5, 400)[None, :, None] + rng.standard_normal((1, 400, 1))
    assert chain_diagnostics(drift)[0][0] > 1.1


def test_the_gp_is_checked_against_the_simulator_where_the_posterior_sits():
    """``at_posterior``: draws whose simulated values are those the GP learnt
    pass (RMS z of order 1); the same draws simulated 200 nats lower (the GP
    promised a region the simulator rules out) fail. So does a GP fitted
    without the points near the peak: the ceiling keeps it below the peak it
    missed (a median of -61.9 nats promised, -42.5 simulated, best fill
    point -53.6; RMS z 13), and the check says so, which
    is what makes ``calib.inference.calibrate`` teach it those points."""
    from calib.inference.loglik_emulator import Z_AT_POSTERIOR_MAX, at_posterior

    rng = np.random.default_rng(5)
    fill = qmc.Sobol(2, scramble=True, seed=5).random_base2(6)
    draws = np.array([0.3, 0.6]) + 0.02 * rng.standard_normal((32, 2))
    x = np.concatenate([fill, draws])
    ll = _peak(x) + rng.standard_normal(len(x))
    emu = fit_loglik_emulator(x, ll, np.full(len(x), 1.0), LO, HI, 10)
    new = np.array([0.3, 0.6]) + 0.02 * rng.standard_normal((16, 2))
    sim = _peak(new) + rng.standard_normal(16)
    good = at_posterior(emu, new, sim, np.full(16, 1.0))
    assert good["ok"] and good["z_rms"] < Z_AT_POSTERIOR_MAX, good
    bad = at_posterior(emu, new, sim - 200.0, np.full(16, 1.0))
    assert not bad["ok"] and bad["z_median"] < -Z_AT_POSTERIOR_MAX, bad
    missed = fit_loglik_emulator(fill, ll[:len(fill)], np.full(len(fill), 1.0), LO, HI, 10)
    assert not at_posterior(missed, new, sim, np.full(16, 1.0))["ok"]


def test_chains_start_at_the_best_design_points_spread_apart():
    """``chains.chain_starts``: the best point first, then those farthest from the
    ones taken among the 4 x chains best; all inside the box; None when no
    design point is inside it."""
    from calib.inference.chains import chain_starts
    from calib.model.priors import Box

    box = Box(("a", "b"), (0.0, 0.0), (1.0, 1.0))
    rng = np.random.default_rng(6)
    cluster = 0.5 + 0.02 * rng.random((10, 2))
    theta = np.concatenate([[[0.5, 0.5]], cluster[1:], [[0.9, 0.1], [0.1, 0.9], [0.95, 0.95],
                                                        [1.5, 0.5]]])
    ll = np.concatenate([[-10.0], -10.1 - 0.1 * np.arange(9), [-12.0, -13.0, -90.0, 0.0]])
    starts = chain_starts(theta, ll, box, 3)  # the 12 best inside: not the -90 point
    assert np.allclose(starts[0], [0.5, 0.5])
    assert {tuple(p) for p in starts[1:]} == {(0.9, 0.1), (0.1, 0.9)}
    assert chain_starts(theta[-1:], ll[-1:], box, 2) is None  # outside the box


def test_emulators_of_one_shape_share_one_compiled_prediction():
    """Two emulators fitted to different designs of the same size go through
    ``predict_batch`` as arguments: one compiled program for both, and each
    gives its own ``predict``'s values (a closure over the emulator would fold
    its arrays into a program of its own)."""
    from calib.inference.emulator import predict_batch

    x = qmc.Sobol(2, scramble=True, seed=3).random_base2(4)
    pts = jnp.asarray(qmc.Sobol(2, scramble=True, seed=4).random_base2(3))
    emus = [fit_loglik_emulator(x, _peak(x) + shift, np.full(len(x), 1.0), LO, HI, 10)
            for shift in (0.0, 5.0)]
    before = predict_batch._cache_size()
    for emu in emus:
        mean, var = predict_batch(emu, pts)
        one = [emu.predict(p) for p in pts]
        np.testing.assert_allclose(mean, [float(m) for m, _ in one], rtol=1e-10)
        np.testing.assert_allclose(var, [float(v) for _, v in one], rtol=1e-10)
    assert predict_batch._cache_size() - before <= 1  # 0 where an earlier test compiled it
