"""Unfinished blocks in calibration: a block still moving when the
solver's budget ran out (``solvers.status.BUDGET``) or in an invalid state
(``INVALID``) has no runout. Forward models exclude it (NaN) and the
likelihood, the fit check and the warnings count it; it never enters as a
runout."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import calib  # noqa: F401  (x64)
from calib.files.observations import Observations
from calib.inference.calibrate import Budget, calibrate
from calib.inference.likelihood import log_likelihood_jit as log_likelihood
from calib.model.forward import CrspForward
from calib.model.unfinished import UNFINISHED_WARN_FRACTION, UnfinishedBlocksWarning
from solvers import crsp, load_profile
from solvers.status import BUDGET, finished

THETA = np.array([0.41, 0.87, 2.0])  # the paper's Kn, Kt, S
SIZES = np.array([0.5, 2.0])
N = 32
# a budget of 20 events: on the Postignano profile a block of either size needs
# 15-25 of them, so many, but not all, are still moving
SETTINGS = crsp.Settings(max_events=20)


@pytest.fixture(scope="module")
def budget_case():
    profile = load_profile("data/postignano_profile.csv")
    key = jax.random.key(7)
    # one task per compiled call: the program of the direct runs below (one size each)
    fw = CrspForward(profile, SIZES, N, key, settings=SETTINGS, task_chunk=1)
    runs = fw.runouts(THETA[None])[0]  # (S, N)
    params = crsp.params_from_profile(profile, Kn=THETA[0], Kt=THETA[1], roughness_m=THETA[2])
    direct = [crsp.run_blocks(params, crsp.make_block(d / 2), key, N, profile, settings=SETTINGS)
              for d in SIZES]
    return profile, fw, runs, direct


def test_forward_gives_nan_exactly_for_the_blocks_that_did_not_finish(budget_case):
    """Block j of the forward model is block j of a direct solver run with the
    same key; its runout is NaN where that block's status is not finished."""
    _, _, runs, direct = budget_case
    for s, res in enumerate(direct):
        ok = finished(np.asarray(res.status))
        np.testing.assert_array_equal(np.isnan(runs[s]), ~ok)
        # the pool and the per-task parameters may round differently in the last bit
        np.testing.assert_allclose(runs[s][ok], np.asarray(res.runout_m)[ok], rtol=1e-12)
    n_budget = sum(int(np.sum(np.asarray(r.status) == BUDGET)) for r in direct)
    assert n_budget == int(np.isnan(runs).sum()) > 0
    assert 0 < np.isnan(runs[1]).sum() < N  # the case has both kinds of 2 m blocks


def test_likelihood_uses_the_finished_blocks_only(budget_case):
    """Point and interval rows: the log-likelihood of the forward's runouts equals
    the one computed from the finished blocks of the direct run alone."""
    _, _, runs, direct = budget_case
    fin = [np.asarray(r.runout_m)[finished(np.asarray(r.status))] for r in direct]
    size = np.array([1, 1, 0])  # rows: 2 m point, 2 m interval, 0.5 m point
    y, sd = np.array([112.0, 0.0, 30.0]), np.array([5.0, 0.0, 10.0])
    lo, hi = np.array([0.0, 105.0, 0.0]), np.array([0.0, 125.0, 0.0])
    is_int = np.array([False, True, False])
    got = np.asarray(log_likelihood(runs[size], y, sd, lo, hi, is_int))
    for s in (0, 1):
        rows = size == s
        want = np.asarray(log_likelihood(np.broadcast_to(fin[s], (rows.sum(), fin[s].size)),
                                         y[rows], sd[rows], lo[rows], hi[rows], is_int[rows]))
        np.testing.assert_allclose(got[rows], want, rtol=1e-12, atol=1e-12)
    assert np.isfinite(got[:2]).all()  # 2 m has finished blocks


def test_calibration_counts_unfinished_blocks_and_warns(budget_case):
    """A gradient fit whose blocks partly hit the budget warns once and records
    the counts of every stage; the check's fit quality comes from finished blocks."""
    profile, fw, _, _ = budget_case
    obs = Observations.points(SIZES, np.array([40.0, 112.0]), 10.0)
    budget = Budget(grad_starts=1, grad_steps=1, grad_k=1, n_blocks_grad=N, n_check=N)
    with pytest.warns(UnfinishedBlocksWarning, match="unfinished") as rec:
        fit = calibrate(fw, obs, jax.random.key(1), ("gradient",), budget)
    assert len([w for w in rec if w.category is UnfinishedBlocksWarning]) == 1
    record = fit.unfinished
    assert record["threshold"] == UNFINISHED_WARN_FRACTION
    check = record["stages"]["check"]
    assert check["n_blocks"] == fit.check_runouts.size
    assert check["n_unfinished"] == int(np.isnan(fit.check_runouts).sum()) > 0
    assert check["max_fraction"] == pytest.approx(np.isnan(fit.check_runouts).mean(-1).max())
    grad = record["stages"]["gradient"]
    assert grad["n_unfinished"] > 0 and grad["n_blocks"] % N == 0
    for q in fit.quality:  # a size with no finished block gives None, not a crash
        s = int(np.searchsorted(fit.check_sizes_m, q["block_size_m"]))
        r = fit.check_runouts[s][np.isfinite(fit.check_runouts[s])]
        assert q["sim_n_finished"] == r.size
        assert q["sim_few_blocks"] == (0 < r.size < 20)  # solvers.percentiles.few_blocks
        assert q["sim_median_m"] == (pytest.approx(np.median(r)) if r.size else None)
    assert fit.quality[1]["sim_n_finished"] > 0  # 2 m
    assert record["warning"].endswith("raise CRSP's event budget (Settings.max_events)")


def test_the_warning_names_what_the_user_can_raise(budget_case):
    """CRSP: its event budget; the DEM: calib.fit's --dem-max-time-s, with the
    fit's own value."""
    import dataclasses

    from calib.inference.calibrate import unfinished_remedy
    from calib.model.dem_run import DEM_RUN
    from calib.model.forward import DemForward

    profile, fw, _, _ = budget_case
    assert "Settings.max_events" in unfinished_remedy(fw)
    dem = DemForward(profile, SIZES, 2, jax.random.key(0),
                     run=dataclasses.replace(DEM_RUN, max_time_s=210.0))
    assert unfinished_remedy(dem) == ("give the DEM's blocks more simulated time "
                                      "(calib.fit --dem-max-time-s; this fit: 210 s)")


@pytest.mark.slow  # 37 s on 2 cores (2026-12-06): a whole discrepancy fit
def test_discrepancy_fit_counts_unfinished_blocks_and_warns(budget_case):
    """The discovery workflow's fit of one candidate on 2 m rows: unfinished blocks
    are counted in the design and the predictive, one warning, and every design
    point keeps a finite likelihood and the gap a finite value (finished blocks)."""
    from calib.discovery.candidate_fit import Candidate, fit_candidate
    from calib.discovery.scores import folds
    from calib.inference.budget import DiscoveryBudget as FitBudget
    from calib.model.priors import CRSP_BOX

    profile = budget_case[0]

    def forward(sizes_m, n_blocks, key):
        return CrspForward(profile, sizes_m, n_blocks, key, settings=SETTINGS)

    design = np.array([[0.41, 0.87, 2.0], [0.35, 0.85, 1.5], [0.45, 0.9, 2.5], [0.3, 0.8, 3.0]])
    cand = Candidate("none", CRSP_BOX, forward, design=lambda: design)
    obs = Observations.points(np.full(6, 2.0), np.linspace(105.0, 125.0, 6), 5.0)
    row_class = np.zeros(6, int)
    budget = FitBudget(n_sobol=0, n_warm=0, n_refine=(), n_blocks=N, n_draws=2,
                       n_blocks_check=N, k_folds=2, noise_reps=0)
    with pytest.warns(UnfinishedBlocksWarning, match="candidate 'none'"):
        fit = fit_candidate(cand, obs, np.array([2.0]), row_class, jax.random.key(3), budget,
                            folds(row_class, 2, seed=0))
    stages = fit.unfinished["stages"]
    assert stages["design"]["n_blocks"] == len(design) * N
    assert 0 < stages["design"]["n_unfinished"] < len(design) * N
    assert stages["predictive"]["n_blocks"] == 2 * N
    assert stages["predictive"]["n_unfinished"] == int(np.isnan(fit.samples).sum())
    assert np.all(np.isfinite(fit.loglik)) and np.isfinite(fit.gap)


def test_synthetic_rows_are_finished_blocks(monkeypatch):
    """Synthetic observations are the first n finished blocks of each size: an
    unfinished block is replaced by the next finished one, simulated anew (a
    stand-in forward model: block j's runout is 100 + j m, and blocks 1 and 4 of
    the second size never finish)."""
    from calib.discovery.synthetic import synthesize

    def runouts(self, theta):
        r = np.tile(100.0 + np.arange(self.n_blocks), (len(self.sizes_m), 1))
        r[1, [j for j in (1, 4) if j < self.n_blocks]] = np.nan
        return r[None]

    monkeypatch.setattr(CrspForward, "runouts", runouts)
    profile = load_profile("data/postignano_profile.csv")
    obs = synthesize(CrspForward, profile, THETA, [0.5, 1.0], 4, 1e-9, jax.random.key(0))
    np.testing.assert_allclose(obs.runout_m, [100, 101, 102, 103, 100, 102, 103, 105],
                               atol=1e-6)
