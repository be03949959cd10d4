"""A fixed grid's posterior and held-out scores from the rows emulated between
its points (``calib.discovery.grid_emulation``), on a toy simulator whose
runouts are a straight line in the parameter plus common random numbers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from calib.discovery.grid_emulation import fit_row_emulator, grid_scores
from calib.discovery.scores import ELPD_MIN, cv_elpd, folds
from calib.files.observations import Observations
from calib.inference.importance import weighted_quantile
from calib.inference.likelihood import log_likelihood

TRUTH = 0.37
SPREAD_M = 10.0


def _rows(n_rows, seed):
    rng = np.random.default_rng(seed)
    return 100.0 + 50.0 * TRUTH + rng.normal(0.0, np.hypot(SPREAD_M, 2.0), n_rows)


def _simulated_loglik(theta, y, n_blocks, seed):
    """(N, R) the likelihood of ``calib.fit`` (2 m tolerance) from ``n_blocks``
    runouts 100 + 50 theta + 10 eps, the same eps at every theta."""
    eps = np.random.default_rng(1000 + seed).standard_normal(n_blocks)
    return np.stack([_rows_loglik(100.0 + 50.0 * t + SPREAD_M * eps, y)
                     for t in np.ravel(theta)])


def _rows_loglik(runouts_m, y):
    """(R,) every point row's log-likelihood (2 m tolerance) given one set of
    simulated runouts (n,), the same set for every row."""
    n = y.size
    return np.asarray(log_likelihood(jnp.broadcast_to(jnp.asarray(runouts_m), (n, runouts_m.size)),
                                     jnp.asarray(y), jnp.full(n, 2.0), jnp.zeros(n),
                                     jnp.zeros(n), jnp.zeros(n, bool)))


# slow: seed 0 80 s on 2 cores (2026-12-06, compilation included), seeds 1 and 2 18-19 s
@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_emulated_grid_scores_as_a_grid_sixty_times_finer(seed):
    """16 grid points, 64 blocks each, 60 rows: the held-out scores from the
    emulated rows agree with the simulated rows of a 1,025-point grid of the
    same simulator (same blocks) to less than the gain ``calib.discover``
    needs to name an effect (``ELPD_MIN``, 4 nats: the emulation alone cannot
    name one), and the posterior mean lies inside the fine grid's 90 %
    interval."""
    y = _rows(60, seed)
    fold = folds(np.zeros(y.size, int), 10, seed)
    grid = np.linspace(0.0, 1.0, 16)[:, None]
    g = grid_scores(grid, _simulated_loglik(grid, y, 64, seed), fold,
                    np.random.default_rng(seed))
    fine = np.linspace(0.0, 1.0, 1025)
    ll_fine = _simulated_loglik(fine, y, 64, seed)
    e_fine, _ = cv_elpd(ll_fine, np.zeros(fine.size), fold)
    assert abs(g.elpd.sum() - e_fine.sum()) < ELPD_MIN, (g.elpd.sum(), e_fine.sum())
    assert np.all(g.khat_folds < 0.7), g.khat_folds
    w_fine = np.exp(ll_fine.sum(axis=1) - ll_fine.sum(axis=1).max())
    lo, hi = (weighted_quantile(fine, w_fine, q) for q in (0.05, 0.95))
    assert lo < g.weights @ g.z[:, 0] < hi, (g.weights @ g.z[:, 0], lo, hi)


def _chaotic_loglik(theta, y, n_blocks, seed):
    """(N, R) as ``_simulated_loglik`` with fresh blocks at every theta: a
    block's runout changes unpredictably from one grid point to the next, as
    a DEM block's does (docs/studies.md)."""
    rng = np.random.default_rng(2000 + seed)
    return np.stack([_rows_loglik(100.0 + 50.0 * t + SPREAD_M * rng.standard_normal(n_blocks), y)
                     for t in np.ravel(theta)])


@pytest.mark.slow  # 97 s on 2 cores (2026-12-06): a coverage study
def test_the_intervals_cover_the_truth_when_every_grid_point_has_its_own_blocks():
    """16 grid points with 8 fresh blocks each, 60 rows, 12 data sets: the 90 %
    interval holds the truth in at least 9 of 12 (a binomial with the nominal
    0.9 falls below 9 with probability 0.026). The emulated mean alone, with
    the summed log-likelihood's uncertainty left out, held it in 5 of 12."""
    covered = []
    for seed in range(12):
        y = _rows(60, seed)
        grid = np.linspace(0.0, 1.0, 16)[:, None]
        g = grid_scores(grid, _chaotic_loglik(grid, y, 8, seed),
                        folds(np.zeros(y.size, int), 10, seed), np.random.default_rng(seed))
        lo, hi = (weighted_quantile(g.z[:, 0], g.weights, q) for q in (0.05, 0.95))
        covered.append(lo <= TRUTH <= hi)
    assert sum(covered) >= 9, covered


def test_the_emulator_refuses_too_few_points_and_non_finite_values():
    with pytest.raises(ValueError, match="at least 3 points"):
        fit_row_emulator(np.zeros((2, 1)), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="finite"):
        fit_row_emulator(np.linspace(0, 1, 4)[:, None],
                         np.array([[0.0], [-np.inf], [1.0], [0.0]]))


class _Line:
    """runout = scale * 100 m + 10 m noise, common random numbers per class."""

    def __init__(self, sizes_m, n_blocks, key):
        self.sizes_m = np.asarray(sizes_m, float)
        self.noise = np.asarray(jax.random.normal(key, (self.sizes_m.size, n_blocks)))

    def runouts(self, theta):
        theta = np.atleast_2d(theta)
        return theta[:, :1, None] * 100.0 + 10.0 * self.noise[None]


@pytest.mark.slow  # 22 s on 2 cores (2026-12-06): a fit on a fixed grid
def test_a_fixed_grid_fit_holds_a_posterior_narrower_than_its_step():
    """60 rows on a 16-point grid of one parameter (step 0.1): every fold's
    training weights have k-hat below the bar, and the 90 % interval is
    narrower than a grid step and holds the median of the same simulator's
    posterior on a 1,025-point grid; the grid's own simulated sums put all
    the weight on one point. 64 blocks per point, so that the fine grid's
    sums are smooth enough to be the reference (with the DEM's 8 they are
    spiky: a 2 m kernel on runouts 10 m apart)."""
    from calib.discovery.candidate_fit import Candidate, fit_candidate
    from calib.inference.budget import DiscoveryBudget as Budget
    from calib.inference.importance import ess, psis_weights
    from calib.model.priors import Box

    n_blocks = 64
    sizes = np.full(60, 1.0)
    y = 100.0 * 1.2 + np.random.default_rng(4).normal(0, 10, sizes.size)
    nan = np.full(sizes.size, np.nan)
    obs = Observations(sizes, y, np.full(sizes.size, 2.0), nan, nan,
                       np.zeros(sizes.size, bool), ("synthetic",) * sizes.size)
    grid = np.linspace(0.5, 2.0, 16)[:, None]
    cand = Candidate("none", Box(("scale",), (0.5,), (2.0,)), _Line, design=lambda: grid)
    budget = Budget(n_sobol=0, n_warm=0, n_refine=(), n_blocks=n_blocks, n_draws=8,
                    n_blocks_check=0, k_folds=5, noise_reps=0, fold_rounds=0)
    row_class = np.zeros(sizes.size, int)
    fold = folds(row_class, 5, seed=0)
    key = jax.random.key(0)
    fit = fit_candidate(cand, obs, np.array([1.0]), row_class, key, budget, fold)
    assert fit.n_simulated == 16
    rec = fit.grid_emulator  # what discovery.json records
    assert rec["trend_degree"] in (0, 1, 2) and np.isfinite(rec["loo_rmse_nats"])
    assert np.isfinite(rec["sum_noise_sd_nats"]) and rec["n_realisations"] > 1
    assert np.all(fit.khat_folds <= fit.khat_bar), (fit.khat_folds, fit.khat_bar)
    lo, hi = fit.q05[0], fit.q95[0]
    fw = _Line([1.0], n_blocks, jax.random.fold_in(key, 1))  # the fit's blocks

    def summed(theta):
        return np.array([_rows_loglik(r[0], y).sum() for r in fw.runouts(theta)])
    fine = np.linspace(0.5, 2.0, 1025)
    s_fine = summed(fine[:, None])
    median = weighted_quantile(fine, np.exp(s_fine - s_fine.max()), 0.5)
    assert lo < median < hi and hi - lo < 0.1, (lo, median, hi)
    assert ess(psis_weights(summed(grid))[0]) < 2.0  # the grid's own weights: one point


def test_a_run_on_fixed_grids_says_what_its_scores_leave_out():
    """The warning names each fixed-grid fit with its emulator's left-out
    error and its summed log-likelihood's noise, and says the scores rest on
    one block set; a run without one (every CRSP run) says nothing."""
    from calib.discovery.discovery_warnings import grid_warnings

    (w,) = grid_warnings({"none": {"loo_rmse_nats": 2.499, "sum_noise_sd_nats": 56.5},
                          "size_dissipation": {"loo_rmse_nats": 2.117,
                                               "sum_noise_sd_nats": 74.2}})
    assert "none 2.50, size_dissipation 2.12" in w
    assert "none 56, size_dissipation 74" in w and "one set of blocks" in w
    assert grid_warnings({"none": None, "fragmentation": None}) == []
