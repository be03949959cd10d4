"""The one observation model (``calib.inference.likelihood``): ``calib.fit``'s path
(``calib.inference.calibrate``) and ``calib.discover``'s (``calib.discovery.discrepancy``) score the
same rows identically, and both are the model ``docs/calibration.md`` documents."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.special import logsumexp, ndtr
from scipy.stats import norm

from calib.discovery.candidate_fit import _loglik_design
from calib.discovery.discrepancy import size_classes
from calib.files.observations import Observations
from calib.inference.likelihood import (
    R_MAX_M,
    RUNOUT_EPS,
    RowLikelihood,
    log_likelihood,
    observed_rows,
)

NAN = np.nan


def _rows() -> Observations:
    """Point and interval rows over three sizes (two rows share a size)."""
    return Observations(
        block_size_m=np.array([0.2, 0.2, 0.5, 1.0, 1.0, 2.0]),
        runout_m=np.array([100.0, NAN, 150.0, NAN, 205.0, 240.0]),
        runout_sd_m=np.array([5.0, NAN, 3.0, NAN, 10.0, 0.5]),
        runout_min_m=np.array([NAN, 80.0, NAN, 170.0, NAN, NAN]),
        runout_max_m=np.array([NAN, 130.0, NAN, 260.0, NAN, NAN]),
        is_interval=np.array([False, True, False, True, False, False]),
        source=("test",) * 6)


def _runouts(n_points: int = 3, n: int = 24) -> np.ndarray:
    """(T, S, n) simulated runouts with unfinished blocks (NaN); at the last point
    no block of the 0.5 m size finished."""
    rng = np.random.default_rng(7)
    centre = np.array([110.0, 160.0, 210.0, 235.0])
    r = centre[None, :, None] + 25.0 * rng.standard_normal((n_points, 4, n))
    r[rng.uniform(size=r.shape) < 0.15] = NAN
    r[-1, 1] = NAN
    return r


def _documented(obs: Observations, runouts: np.ndarray) -> np.ndarray:
    """docs/calibration.md, "Observation model", in NumPy: points (1/n) sum_j N(y; r_j, sd^2),
    intervals (1/n) sum_j [Phi((b - r_j)/h) - Phi((a - r_j)/h)], h Silverman's
    width (>= 0.5 m), over the finished blocks; each mixed with weight 1 - eps
    with the defensive uniform eps / R_MAX (eps (b - a) / R_MAX for intervals)."""
    out = np.empty((runouts.shape[0], obs.n_obs))
    for t, by_size in enumerate(runouts):
        for i in range(obs.n_obs):
            r = by_size[obs.size_index[i]]
            r = r[np.isfinite(r)]
            width = (obs.runout_max_m[i] - obs.runout_min_m[i]) if obs.is_interval[i] else 1.0
            floor = RUNOUT_EPS * width / R_MAX_M
            if r.size == 0:
                out[t, i] = np.log(floor)
                continue
            if not obs.is_interval[i]:
                p = np.mean(norm.pdf(obs.runout_m[i], r, obs.runout_sd_m[i]))
            else:
                q75, q25 = np.percentile(r, [75.0, 25.0])
                spread = min(np.std(r), (q75 - q25) / 1.34)
                h = max(0.9 * spread * r.size ** -0.2, 0.5) if r.size >= 2 else 0.5
                p = np.mean(ndtr((obs.runout_max_m[i] - r) / h)
                            - ndtr((obs.runout_min_m[i] - r) / h))
            out[t, i] = np.log((1.0 - RUNOUT_EPS) * p + floor)
    return out


def test_fit_and_discover_score_the_same_rows_identically():
    obs, runs = _rows(), _runouts()
    fit_path = np.asarray(RowLikelihood(obs).pointwise(runs))
    _, row_class = size_classes(obs.block_size_m)
    discover_path = np.asarray(_loglik_design(runs, row_class, *observed_rows(obs)))
    assert fit_path.shape == (3, obs.n_obs)
    # no finished block of its size: only the defensive component is left
    assert fit_path[-1, 2] == pytest.approx(np.log(RUNOUT_EPS / R_MAX_M), rel=1e-12)
    np.testing.assert_allclose(discover_path, fit_path, rtol=1e-13, atol=0)
    for kind in (obs.is_interval, ~obs.is_interval):  # both kinds of row are there
        assert np.isfinite(fit_path[:, kind]).any()


def test_both_paths_are_the_documented_model():
    obs, runs = _rows(), _runouts()
    np.testing.assert_allclose(np.asarray(RowLikelihood(obs).pointwise(runs)),
                               _documented(obs, runs), rtol=1e-9)


def test_a_point_row_without_a_tolerance_is_refused():
    obs = Observations.points([0.5, 1.0], [100.0, 120.0], [2.0, NAN])
    with pytest.raises(ValueError, match="line 3, column 'runout_sd_m'"):
        observed_rows(obs)
    with pytest.raises(ValueError, match="positive tolerance"):
        observed_rows(Observations.points([0.5], [100.0], [0.0]))


def test_a_row_no_block_reaches_costs_a_bounded_amount():
    """The defensive component (Hesterberg 1995): a point row 40 m from every
    simulated block (a 2 m tolerance) scored -202 nats without it (as the
    Tschamut short runs did, pushing the rolling resistance to 36 deg); with
    it, it scores log(eps / R_MAX) = -13.8. A row the blocks explain changes by
    log(1 - eps) at most, and an interval row by its own floor."""
    blocks = np.linspace(90.0, 110.0, 64)[None].repeat(3, 0)
    y = np.array([50.0, 100.0, 0.0])
    sd = np.array([2.0, 2.0, 1.0])
    lo, hi = np.array([0.0, 0.0, 20.0]), np.array([1.0, 1.0, 40.0])
    is_interval = np.array([False, False, True])
    ll = np.asarray(log_likelihood(blocks, y, sd, lo, hi, is_interval))
    kde_far = logsumexp(norm.logpdf(50.0, blocks[0], 2.0)) - np.log(64)
    kde_near = logsumexp(norm.logpdf(100.0, blocks[1], 2.0)) - np.log(64)
    assert kde_far < -200.0
    assert ll[0] == pytest.approx(np.log(RUNOUT_EPS / R_MAX_M), abs=1e-9)
    assert ll[0] == pytest.approx(-13.8155, abs=1e-4)
    assert 0.0 < kde_near - ll[1] <= -np.log1p(-RUNOUT_EPS) + 1e-12
    assert ll[2] == pytest.approx(np.log(RUNOUT_EPS * 20.0 / R_MAX_M), abs=1e-9)


@pytest.mark.slow  # a study script's check, about 20 s of compilation: run with -m slow
def test_loglik_noise_script_measures_the_spread_over_block_sets(tmp_path, capsys):
    """``scripts/loglik_noise.py`` (docs/studies.md): independent block sets give
    different summed log-likelihoods (sd > 0), the same key gives the same value,
    more blocks per entry shrink the bootstrap sd of one set, a widened
    tolerance is the score of rows with that tolerance, the release allocation
    takes each release's rows from its chosen block count, and the
    nearest-neighbour kernel is the tolerance kernel until the k-th nearest
    runout lies beyond the tolerance."""

    from cli_run import load_script, run_cli

    mod = load_script("loglik_noise")
    theta = np.array([[0.41, 0.87, 0.25, 30.0], [0.30, 0.80, 0.10, 20.0]])
    few = mod.loglik_spread("data/postignano.csv", theta, 32, 3)
    again = mod.loglik_spread("data/postignano.csv", theta, 32, 3)
    more = mod.loglik_spread("data/postignano.csv", theta, 512, 3)
    np.testing.assert_array_equal(few["summed"], again["summed"])
    assert few["summed"].shape == (3, 2) and np.all(np.isfinite(few["summed"]))
    assert np.all(few["sd"] > 0)
    np.testing.assert_allclose(few["pointwise"].sum(-1), few["summed"], rtol=1e-12)
    # the tail allocation: with the same block count it is the plain score at no extra cost
    same = mod.tail_mixture(few, few)
    np.testing.assert_allclose(same["summed"], few["summed"], rtol=1e-12)
    np.testing.assert_allclose(same["cost"], 1.0)
    mixed = mod.tail_mixture(few, more)
    assert np.all((mixed["cost"] == 1.0) == (mixed["n_tail_entries"] == 0))
    assert np.all(mixed["cost"] <= 512 / 32)
    assert few["entry_quantiles_m"].shape[:2] == (3, 2)
    # the release allocation: at cost 1 it is the plain score; with room for every
    # release at the larger count (cost 512 / 32) it upgrades only where the pilot's
    # variance falls, and its score takes each release's rows from its chosen count
    plain = mod.release_allocation([few, more], 1.0)
    np.testing.assert_allclose(plain["summed"], few["summed"], rtol=1e-12)
    assert plain["cost"] == 1.0 and np.all(plain["n_blocks"] == 32)
    full = mod.release_allocation([few, more], 512 / 32)
    assert full["cost"] <= 512 / 32 and set(full["n_blocks"]) <= {32, 512}
    e_of = few["row_entry"]
    from_more = full["n_blocks"][e_of] == 512
    np.testing.assert_allclose(full["summed"], np.where(from_more, more["pointwise"],
                                                        few["pointwise"]).sum(-1), rtol=1e-12)
    # the nearest-neighbour kernel: where the k-th nearest runout lies within the
    # tolerance it is calib.fit's kernel; beyond, the kernel widens to that distance
    from calib.inference.likelihood import log_likelihood

    samples = np.array([[99.0, 101.0, 100.5, np.nan, 140.0]])  # (1 row, 5 blocks)
    y, sd, none = np.array([100.0]), np.array([2.0]), np.zeros(1)
    point = (y, sd, none, none, np.zeros(1, bool))
    near = mod.nearest_neighbour_loglik(samples, *point, 3)
    np.testing.assert_allclose(near, np.asarray(log_likelihood(samples, *point)), rtol=1e-12)
    wide = mod.nearest_neighbour_loglik(samples, *point, 4)  # 4th nearest: 40 m away
    ref_wide = log_likelihood(samples, y, np.array([40.0]), none, none, np.zeros(1, bool))
    np.testing.assert_allclose(wide, np.asarray(ref_wide), rtol=1e-12)
    assert np.all(more["bootstrap_sd"] < few["bootstrap_sd"])
    assert run_cli(mod.main, ["data/postignano.csv", "--theta", "0.5,0.9"], capsys)[0] == 2
    # --extra-sd-m E scores the rows as a file whose tolerances are sqrt(sd^2 + E^2)
    wide = tmp_path / "wide.csv"
    rows = Path("data/postignano.csv").read_text().splitlines()
    sd_wide = float(np.hypot(15.0, 20.0))
    wide.write_text("\n".join([rows[0]] + [r.replace(",15.0,", f",{sd_wide!r},")
                                             for r in rows[1:]]) + "\n")
    profile = "data/postignano_profile.csv"
    widened = mod.loglik_spread("data/postignano.csv", theta, 32, 2, profile=profile,
                                extra_sd_m=20.0)
    direct = mod.loglik_spread(str(wide), theta, 32, 2, profile=profile)
    np.testing.assert_allclose(widened["summed"], direct["summed"], rtol=1e-12)
    assert not np.allclose(widened["summed"], few["summed"][:2])
    # --rolling-threshold-m-s: the solver's default is the plain score; another
    # cutoff changes the runs, and the solver's default is back afterwards
    from solvers import crsp, load_profile

    same = mod.loglik_spread("data/postignano.csv", theta, 32, 3,
                             rolling_threshold_m_s=crsp.ROLLING_THRESHOLD_M_S)
    np.testing.assert_array_equal(same["summed"], few["summed"])
    low = mod.loglik_spread("data/postignano.csv", theta, 32, 3, rolling_threshold_m_s=0.02)
    assert not np.array_equal(low["summed"], few["summed"])
    prof = load_profile("data/postignano_profile.csv")
    assert float(crsp.params_from_profile(prof).rolling_threshold_m_s) == (
        crsp.ROLLING_THRESHOLD_M_S)
    rc, text, _ = run_cli(mod.main, ["data/postignano.csv", "--theta", "0.41,0.87,0.25,30",
                                     "--n-blocks", "32", "--replicates", "2",
                                     "--rolling-threshold-m-s", "0.5,0.02", "--entries"], capsys)
    assert rc == 0 and "rolling threshold 0.02 m/s" in text, text
    assert text.count("releases' 5/50/95 % runouts (m): ") == 2, text
