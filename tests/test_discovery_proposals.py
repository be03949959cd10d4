"""The adaptive importance-sampling design of a discovery candidate's fit
(``calib.discovery.candidate_fit``): its proposals (Gaussian and Student t,
truncated to the cube), the warped stage 0, the stages fitted to the
log-likelihood GP's posterior, and the smoothed weights of the folds."""

from __future__ import annotations

import numpy as np
import pytest

from calib.discovery.proposals import proposal as _proposal
from calib.discovery.scores import folds


def test_proposal_density_is_normalised_on_the_cube():
    rng = np.random.default_rng(1)
    mean, cov = np.array([0.8, 0.1]), np.array([[0.04, 0.01], [0.01, 0.02]])
    draws, logpdf = _proposal(mean, cov, rng, 500, dim=3)
    assert draws.shape == (500, 3) and np.all((draws >= 0) & (draws <= 1))
    u = rng.uniform(size=(200_000, 3))
    assert np.mean(np.exp(logpdf(u))) == pytest.approx(1.0, rel=0.03)


@pytest.mark.parametrize("mean, df", [((3.2, -2.4), None), ((3.2, -2.4), 4),
                                      ((1.5, 0.5), None)])
def test_a_proposal_padded_from_the_uniform_returns_the_density_of_its_draws(mean, df):
    """A proposal whose mass lies almost wholly outside the cube: fewer than n of
    its draws land inside (none for the first two, some for the third), the
    rest are uniform, and the density returned is the pair's: normalised on the
    cube, and the density of the draws (the mean of 1/q over them estimates the
    cube's volume, 1)."""
    rng = np.random.default_rng(2)
    draws, logpdf = _proposal(np.array(mean), np.diag([0.15, 0.15]) ** 2, rng, 2000, dim=3,
                              df=df)
    assert draws.shape == (2000, 3) and np.all((draws >= 0) & (draws <= 1))
    u = rng.uniform(size=(200_000, 3))
    assert np.mean(np.exp(logpdf(u))) == pytest.approx(1.0, rel=0.03)
    assert np.mean(np.exp(-logpdf(draws))) == pytest.approx(1.0, rel=0.05)


def test_student_t_proposal_draws_and_density_are_the_t_s():
    """The adaptive stages' proposal with ``df`` degrees of freedom: its density is
    scipy's multivariate t (well inside the cube, so truncated by almost nothing),
    normalised on the cube, and its draws' squared Mahalanobis distance over the
    dimension follows F(dim, df), which the Gaussian's (a chi^2 over dim) does not."""
    from scipy import stats

    from calib.discovery.proposals import PROPOSAL_DF

    rng = np.random.default_rng(4)
    mean, cov = np.array([0.5, 0.45]), np.array([[4e-4, 1e-4], [1e-4, 2e-4]])
    draws, logpdf = _proposal(mean, cov, rng, 4000, dim=3, df=PROPOSAL_DF)
    assert draws.shape == (4000, 3) and np.all((draws >= 0) & (draws <= 1))
    ref = stats.multivariate_t(loc=mean, shape=cov, df=PROPOSAL_DF)
    np.testing.assert_allclose(logpdf(draws[:50]), ref.logpdf(draws[:50, :2]), atol=1e-3)
    d = draws[:, :2] - mean
    m2 = np.einsum("ij,jk,ik->i", d, np.linalg.inv(cov), d) / 2
    assert stats.kstest(m2, stats.f(2, PROPOSAL_DF).cdf).pvalue > 0.01
    assert stats.kstest(m2, stats.chi2(2, scale=0.5).cdf).pvalue < 1e-6
    u = rng.uniform(size=(200_000, 3))  # truncated near a corner: still normalised
    _, logpdf = _proposal(np.array([0.9, 0.1]), np.array([[0.04, 0.01], [0.01, 0.02]]), rng,
                          500, dim=3, df=PROPOSAL_DF)
    assert np.mean(np.exp(logpdf(u))) == pytest.approx(1.0, rel=0.03)


def test_proposals_in_warped_coordinates_weight_back_to_the_uniform_prior():
    """Stage 0 draws half its points uniform in theta and half uniform in the
    warped cube (log S, log(1 - Kt), tan(phi_r)); with a flat likelihood the
    self-normalised weights 1 / q must give back the uniform prior in theta:
    its mean and quartiles per parameter. Without the change of variables the
    weighted median of S would be about 0.2 m instead of 2 m."""
    from scipy.stats import qmc

    from calib.discovery.proposals import mixture_log_q as _mixture_log_q
    from calib.model.priors import CRSP_ROLLING_BOX as box
    from calib.model.warp import unit_coordinates

    to_z, to_theta, log_jac = unit_coordinates(box)
    sob = qmc.Sobol(box.dim, scramble=True, seed=3).random(2**14)
    n = sob.shape[0] // 2
    z = np.concatenate([to_z(box.from_unit(sob[:n])), sob[n:]])
    np.testing.assert_allclose(to_theta(to_z(box.from_unit(sob[:8]))), box.from_unit(sob[:8]),
                               rtol=1e-12)
    log_q = _mixture_log_q(z, [n, n], [lambda z: -log_jac(z), lambda z: np.zeros(len(z))])
    log_q = log_q + log_jac(z)  # relative to the prior in theta
    w = np.exp(-log_q - np.max(-log_q))
    w /= w.sum()
    theta = to_theta(z)
    u = box.to_unit(theta)  # uniform on [0, 1] per parameter under the prior
    for j in range(box.dim):
        order = np.argsort(u[:, j])
        cdf = np.cumsum(w[order])
        for q in (0.25, 0.5, 0.75):
            assert abs(u[order, j][np.searchsorted(cdf, q)] - q) < 0.02, (box.names[j], q)
    assert abs(np.mean(u[:, 2]) - 0.5) > 0.1  # the draws themselves are not uniform in S


def test_an_adaptive_stage_fitted_to_the_gp_posterior_covers_a_narrow_posterior():
    """A posterior narrower than the 0.05 floor of a fit to the design's weighted
    points (sd 0.01, 0.02, 0.008 in unit coordinates, as a CRSP baseline's on 180
    rows), seen through 256 noisy design points (one uniform stage, one broad
    Gaussian stage near it; 1.5 nats of noise on each sum). The stage's Gaussian
    fitted to the log-likelihood GP's posterior (``_surrogate_gaussian``) is
    centred on it and about twice its spread (the inflation), and 256 points drawn
    from it weight the exact posterior with k-hat below min(0.7, 1 - 1/log10 256);
    the Gaussian fitted to the design's own weights (the fallback) is held at
    the 0.05 floor and its points' weights collapse. Measured: sd ratio 2.5-3.0
    (the fallback's 2.6-6.6), centre within 0.24 sd, k-hat 0.16 against 2.23."""
    from calib.discovery.candidate_fit import _surrogate_gaussian
    from calib.discovery.proposals import gaussian_fit
    from calib.inference.importance import psis_weights

    rng = np.random.default_rng(7)
    centre, sd = np.array([0.4, 0.55, 0.3]), np.array([0.01, 0.02, 0.008])

    def exact(x):
        return -0.5 * np.sum(((x - centre) / sd) ** 2, axis=1)

    z = np.concatenate([rng.uniform(size=(64, 3)),
                        np.clip(centre + 0.02 + 0.05 * rng.standard_normal((192, 3)), 0, 1)])
    total = exact(z) + 1.5 * rng.standard_normal(z.shape[0])
    log_q = np.zeros(z.shape[0])
    mean, cov = _surrogate_gaussian(z, total, log_q, 1.5**2, 180, rng,
                                    lambda x: np.zeros(x.shape[0]))
    ratio = np.sqrt(np.diag(cov)) / sd
    assert np.all(np.abs(mean - centre) < sd) and np.all((ratio > 1.5) & (ratio < 4.0)), \
        (mean, ratio)
    old_mean, old_cov = gaussian_fit(z, psis_weights(total - log_q)[0])
    assert np.all(np.sqrt(np.diag(old_cov)) >= 0.05)
    khat = []
    for m, c in ((mean, cov), (old_mean, old_cov)):
        x, logpdf = _proposal(m, c, rng, 256, 3)
        khat.append(psis_weights(exact(x) - logpdf(x))[1])
    assert khat[0] < 1 - 1 / np.log10(256) < khat[1], khat


def test_discovery_weights_from_the_smoothed_log_likelihood_do_not_collapse():
    """A design of 512 uniform points (3 parameters, log q = 0) whose 20 rows'
    log-likelihoods carry simulation noise (2.5 nats on their sum): the
    weights of the simulated sums collapse in some fold (k-hat above 0.7);
    weighted by the GP-smoothed sums (``candidate_fit``, told the noise
    variance) every fold's k-hat lies below min(0.7, 1 - 1/log10 512) and the
    held-out scores are finite. Measured: largest fold k-hat 1.24 simulated,
    -0.04 smoothed."""
    from calib.discovery.candidate_fit import _weights_and_scores

    rng = np.random.default_rng(5)
    z = rng.uniform(size=(512, 3))
    exact = -0.5 * np.sum(((z - 0.45) / 0.15) ** 2, axis=1) / 20 - 3.0
    ll = exact[:, None] + (2.5 / np.sqrt(20)) * rng.standard_normal((512, 20))
    fold = folds(np.zeros(20), 5, seed=0)
    _, _, _, k_raw = _weights_and_scores(z, ll, np.zeros(512), fold, 6.25, smooth=False)
    w, khat, elpd, k_smooth = _weights_and_scores(z, ll, np.zeros(512), fold, 6.25)
    assert np.max(k_raw) > 0.7
    assert np.max(k_smooth) < 1 - 1 / np.log10(512) and khat < 1 - 1 / np.log10(512)
    assert np.all(np.isfinite(elpd)) and w.sum() == pytest.approx(1.0)


# the toy design of the two tests below: fold 0's five rows pin the posterior
# at A (sd 0.03 per coordinate), the other 20 rows pull towards B (sd 0.06)
_A = np.array([0.35, 0.4])
_B = _A + 0.12


def _toy_fold_design(rng):
    """(design, fold): 256 points (64 uniform, 192 from a t at A) for 25 rows in
    five folds, each row's simulated log-likelihood with noise sd 0.05."""
    from calib.discovery.candidate_fit import _Design

    fold = np.repeat(np.arange(5), 5)

    def simulate(z):
        ll = np.empty((z.shape[0], 25))
        ll[:, :5] = (-0.5 * np.sum(((z - _A) / 0.03) ** 2, axis=1) / 5)[:, None]
        ll[:, 5:] = (-0.5 * np.sum(((z - _B) / 0.06) ** 2, axis=1) / 20)[:, None]
        return ll + 0.05 * rng.standard_normal(ll.shape)

    def uniform(z):
        return np.zeros(z.shape[0])

    t_draws, t_logpdf = _proposal(_A, 0.03**2 * np.eye(2), rng, 192, 2, df=4)
    z = np.concatenate([rng.uniform(size=(64, 2)), t_draws])
    return _Design(z, simulate(z), [64, 192], [uniform, t_logpdf], uniform, lambda z: z,
                   25 * 0.05**2, simulate, 2), fold


@pytest.mark.slow  # 49 s on 2 cores (2026-12-06): a staged proposal study
def test_fold_stages_cover_the_training_posterior_the_design_missed():
    """The toy design (``_toy_fold_design``), 256 points for 25 rows in five
    folds: fold 0's five rows pin the posterior at A (sd 0.03 per coordinate),
    the other 20 pull towards B = A + 0.12 (sd 0.06). Fold 0's training
    posterior, near B, falls where only the uniform points lie, so its weights'
    k-hat lies above the bar min(0.7, 1 - 1/log10 S); the fold stages
    (``_scores_covering_folds``: up to two rounds of 64 points for each fold
    above it) bring it below, leave the other folds below, and keep the design
    one mixture. Measured: fold 0's k-hat 1.07 -> 1.50 after one stage (its 64
    points spread over a t of twice the posterior's sd: about a dozen land
    where it lives) -> -0.60 after the second."""
    from calib.discovery.candidate_fit import _scores_covering_folds
    from calib.inference.importance import khat_threshold

    rng = np.random.default_rng(2)
    design, fold = _toy_fold_design(rng)
    *_, before, _ = _scores_covering_folds(design, fold, 64, 0, True, rng)
    assert before[0] > khat_threshold(256) and np.all(before[1:] < khat_threshold(256))
    assert design.z.shape == (256, 2)  # no rounds: nothing added
    w, _, elpd, after, _ = _scores_covering_folds(design, fold, 64, 2, True, rng)
    n = design.z.shape[0]
    assert n in (320, 384) and design.ll.shape == (n, 25) and sum(design.counts) == n
    assert np.all(after < khat_threshold(n)), (before, after)
    assert np.all(np.isfinite(elpd)) and w.sum() == pytest.approx(1.0)


# seeds 5 and 7 repeat seed 2's check on other random designs (5-6 s each alone,
# 12-16 s in the default run's two workers): -m slow
@pytest.mark.parametrize("seed", [2, pytest.param(5, marks=pytest.mark.slow),
                                  pytest.param(7, marks=pytest.mark.slow)])
def test_a_fold_the_design_cannot_weight_is_scored_on_fresh_draws(seed):
    """The toy design (``_toy_fold_design``; fold 0's training posterior, N(B, 0.06^2)
    per coordinate, where only the uniform points lie), without fold stages:
    fold 0's weights' k-hat lies above the bar and its rows' importance-weighted
    scores miss the exact held-out density, log E_{theta ~ N(B, 0.06^2)}
    exp(-|theta - A|^2 / (2 x 5 x 0.03^2)) = -2.366 nats per row (Gaussian
    integral; the cube's truncation is below 1e-9). With fresh draws
    (``_fresh_draw_scores``, 64 draws) its score is that density within 0.25
    nats per row, its k-hat (the draws' weights') below the bar, and the other
    folds are untouched. Measured: errors per row +1.03, +0.49, +0.19 nats
    weighted (seeds 2, 5, 7) and -0.05, -0.20, +0.11 on fresh draws."""
    from calib.discovery.candidate_fit import _scores_covering_folds
    from calib.inference.importance import khat_threshold

    rng = np.random.default_rng(seed)
    design, fold = _toy_fold_design(rng)
    s2, sig2 = 5 * 0.03**2, 0.06**2
    exact = 2 * (0.5 * np.log(s2 / (s2 + sig2)) - 0.12**2 / (2 * (s2 + sig2)))
    _, _, weighted, k_weighted, none = _scores_covering_folds(design, fold, 64, 0, True, rng)
    w, _, fresh, k_fresh, scored = _scores_covering_folds(design, fold, 64, 0, True, rng,
                                                          n_draws=64)
    bar = khat_threshold(256)
    assert k_weighted[0] > bar and none == ()
    assert scored == (0,) and k_fresh[0] < bar
    assert np.abs(fresh[:5] - exact).mean() < 0.25, (weighted[:5], fresh[:5], exact)
    assert np.array_equal(fresh[5:], weighted[5:]) and np.array_equal(k_fresh[1:], k_weighted[1:])
    assert design.z.shape == (256, 2) and w.sum() == pytest.approx(1.0)  # no point joined
