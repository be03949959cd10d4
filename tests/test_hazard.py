"""Hazard Monte Carlo: exceedance step for a deterministic setting,
monotone bounded curves, reach vs per-block output, 1/sqrt(N) bands, chunking
invariance, histogram quantiles, intensity classes and matrix."""

from __future__ import annotations

import math
import os

import jax
import numpy as np
import pytest
from test_hazard_fixtures import write_calibration

from calib.hazard import (
    BINS,
    draw_parameters,
    exceedance_table,
    hazard_level,
    hazard_table,
    hist_quantile,
    intensity_class,
    load_calibration,
    probability_class,
    run_hazard,
    summary_text,
)
from calib.hazard._units import draw_key
from calib.model.release import ReleaseState
from solvers import crsp, load_profile

G = 9.81


def _run(cal_path, n_posterior, n_blocks, sizes, stations, seed=0, **kw):
    cal = load_calibration(cal_path, "crsp")
    profile = load_profile(cal.profile_csv)
    draws = draw_parameters(cal, n_posterior, seed)
    counts = run_hazard(cal, draws, profile, sizes, np.asarray(stations, float), n_blocks,
                        seed, **kw)
    return cal, profile, counts


# ------------------------------------------------------------- deterministic step

def test_exceedance_is_a_step_at_the_analytic_runout(tmp_path):
    """Roughness 0 and no release spread: CRSP is deterministic. A sphere
    released on the ground at 1 m/s rolls down a 25 deg incline (rolling
    resistance 20 deg: it accelerates),
        (1 + k) du/dt = g sin(b) - tan(phi) g cos(b)   (k = 2/5).
    At the concave break its normal speed into the flat, u1 sin(25 deg), is far
    above the rolling threshold (0.5 m/s), so it makes a CRSP impact on the flat
    (facet tilt 0, slip Vt - w r, w r = u1 while rolling):
        Vn2 = Kn Vn1 / (1 + (Vn1 / 9.144)^2),
        Vt2 = sqrt((k (w r)^2 + Vt1^2) FF SF / (1 + k)),
        FF = Kt + (1 - Kt) / (((Vt1 - w r) / 6.096)^2 + 1.2),
        SF = Kt / ((Vn1 / (76.2 Kn))^2 + 1),
    hops 2 Vn2 Vt2 / g on the flat while Vn2 >= 0.5 m/s, lands again with the
    same speeds (spin kept in flight), and rolls out the rest:
    x_stop = x_last + Vt^2 (1 + k) / (2 g tan(phi)). Every block stops there
    (the mass and radius cancel), so P(runout > x) is 1 before and 0 after, in
    every draw."""
    beta, phi, k = math.radians(25.0), math.radians(20.0), 0.4
    kn, kt, threshold = 0.4, 0.8, crsp.ROLLING_THRESHOLD_M_S
    (tmp_path / "ramp_profile.csv").write_text(
        f"x_m,z_m,zone\n0,{20 * math.tan(beta):.12f},ramp\n20,0,flat\n60,0,\n")
    (tmp_path / "ramp_materials.csv").write_text(
        "zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg\n"
        "ramp,0.4,0.8,0,20,30\nflat,0.4,0.8,0,20,30\n")
    path = write_calibration(tmp_path, crsp=(kn, kt, 0.0),
                             profile=str(tmp_path / "ramp_profile.csv"))

    def impact(vn, vt, wr):
        ff = kt + (1 - kt) / (((vt - wr) / 6.096) ** 2 + 1.2)
        sf = kt / ((vn / (76.2 * kn)) ** 2 + 1)
        return kn * vn / (1 + (vn / 9.144) ** 2), math.sqrt((k * wr**2 + vt**2) * ff * sf
                                                              / (1 + k))

    u0 = math.cos(beta)  # release velocity (1, 0) m/s projected on the incline
    a1 = G * (math.sin(beta) - math.tan(phi) * math.cos(beta)) / (1 + k)
    u1 = math.sqrt(u0**2 + 2 * a1 * 20.0 / math.cos(beta))
    x_stop = 20.0
    vn, vt = impact(u1 * math.sin(beta), u1 * math.cos(beta), u1)
    while vn >= threshold:
        x_stop += vt * 2 * vn / G
        vn, vt = impact(vn, vt, vt)
    x_stop += vt**2 * (1 + k) / (2 * G * math.tan(phi))
    stations = np.round(np.arange(21.0, 28.01, 0.25), 2)
    _, _, c = _run(path, 3, 16, [0.5, 1.0], stations)
    exc = exceedance_table(c)
    expected = (exc.x_m < x_stop).astype(float)
    for col in ("p_exceed_mean", "p_exceed_q05", "p_exceed_q50", "p_exceed_q95"):
        np.testing.assert_array_equal(exc[col].to_numpy(), expected.to_numpy(), err_msg=col)
    assert 0 < (exc.x_m < x_stop).sum() < len(exc)  # the step lies inside the stations


# ---------------------------------------------------- shared small Postignano run

@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cal")
    path = write_calibration(folder)
    stations = np.arange(0.0, 301.0, 10.0)
    cal, profile, c = _run(path, 1, 400, [0.5, 2.0], stations, seed=3)
    return cal, profile, c


def test_exceedance_non_increasing_and_in_unit_interval(small_run):
    _, _, c = small_run
    exc = exceedance_table(c)
    for _, g in exc.groupby("block_size_m"):
        for col in ("p_exceed_mean", "p_exceed_q05", "p_exceed_q50", "p_exceed_q95"):
            v = g.sort_values("x_m")[col].to_numpy()
            assert np.all((v >= 0) & (v <= 1)), col
            assert np.all(np.diff(v) <= 0), col
    # not trivially flat: every block starts beyond 0 and none leaves a 300 m profile here
    assert exc.p_exceed_mean.max() == 1.0 and exc.p_exceed_mean.min() == 0.0


def test_reach_and_exceedance_equal_per_block_fractions(small_run):
    """Recompute from the per-block output of the plain batch runner
    (``crsp.run_blocks``, same keys: block j of draw 0 uses fold_in(K_0, j))."""
    cal, profile, c = small_run
    table = hazard_table(c, profile)
    stations = c.stations_x_m
    kn, kt, rough = cal.point
    params = crsp.params_from_profile(profile, Kn=kn, Kt=kt, roughness_m=rough)
    for t, size in enumerate(c.sizes_m):
        res = crsp.run_blocks(params, crsp.make_block(size / 2), draw_key(3, 0), c.n_blocks,
                              profile, stations_x_m=stations)
        rows = table[table.block_size_m == size].sort_values("x_m")
        beyond = (res.stop_x_m[:, None] > stations[None, :]).mean(axis=0)
        passed = res.stations.passed.mean(axis=0)
        np.testing.assert_array_equal(rows.p_exceed_mean.to_numpy(), beyond)
        down = stations > 0.0
        np.testing.assert_array_equal(rows.reach_prob_mean.to_numpy()[down], passed[down])
        assert np.all(np.isnan(rows.reach_prob_mean.to_numpy()[~down]))
        # reach >= exceedance: a block beyond x has passed x; the excess is the
        # blocks that passed x and came back upslope (a few % at most here)
        gap = passed[down] - beyond[down]
        assert np.all(gap >= 0) and gap.max() <= 0.05
        e = res.stations.energy_kJ
        with np.errstate(invalid="ignore"):
            p30 = np.nansum(e > 30, axis=0) / np.maximum(res.stations.passed.sum(axis=0), 1)
        has = res.stations.passed.sum(axis=0) > 0
        np.testing.assert_allclose(rows.p_E_gt_30kJ_given_reach.to_numpy()[has & down],
                                   p30[has & down], rtol=0, atol=1e-12)
        # design energy from the histogram vs the exact sample quantile (the
        # smallest value with F >= q, NumPy's "inverted_cdf"): within one bin
        for s in np.flatnonzero(has & down):
            exact = np.quantile(e[res.stations.passed[:, s], s], 0.95, method="inverted_cdf")
            got = rows.energy_p95_kJ.to_numpy()[s]
            assert abs(math.log10(got / exact)) <= 1 / BINS["energy_kJ"].per_decade + 1e-12, (
                s, got, exact)


# ------------------------------------------------- blocks that leave or do not finish

def test_left_profile_and_unfinished_fractions_equal_a_direct_count(tmp_path):
    """The Postignano profile cut at x = 116 m (on the full one the 2 m blocks stop
    around 110-123 m, so here many leave its end still moving): per row,
    ``p_left_profile`` is the fraction of the blocks of a direct solver run with
    the same keys whose status is LEFT_PROFILE, ``p_unfinished`` the fraction
    not finished, and the exceedance counts finished blocks only. Same sizes,
    block count and station count as ``small_run``: no new compilation."""
    from solvers.status import LEFT_PROFILE, finished

    (tmp_path / "cut_profile.csv").write_text(
        "x_m,z_m,zone\n0.000,135.526,cliff\n8.038,105.526,talus\n110.000,19.970,lower\n"
        "116.000,19.339,\n")
    (tmp_path / "cut_materials.csv").write_text(
        "zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg\ncliff,0.41,0.87,2.0,30,30\n"
        "talus,0.41,0.87,2.0,30,30\nlower,0.41,0.87,2.0,30,30\n")
    path = write_calibration(tmp_path, profile=str(tmp_path / "cut_profile.csv"))
    stations = np.linspace(0.0, 115.0, 31)
    cal, profile, c = _run(path, 1, 400, [0.5, 2.0], stations, seed=4)
    table = hazard_table(c, profile)
    params = crsp.params_from_profile(profile, Kn=0.41, Kt=0.87, roughness_m=2.0)
    for size in c.sizes_m:
        res = crsp.run_blocks(params, crsp.make_block(size / 2), draw_key(4, 0), c.n_blocks,
                              profile, stations_x_m=stations)
        status = np.asarray(res.status)
        ok = finished(status)
        rows = table[table.block_size_m == size].sort_values("x_m")
        left, unfinished = np.mean(status == LEFT_PROFILE), np.mean(~ok)
        np.testing.assert_array_equal(rows.p_left_profile.to_numpy(), left)
        np.testing.assert_array_equal(rows.p_unfinished.to_numpy(), unfinished)
        beyond = ((res.stop_x_m[:, None] > stations[None, :]) & ok[:, None]).mean(axis=0)
        np.testing.assert_array_equal(rows.p_exceed_mean.to_numpy(), beyond)
        if size == 2.0:
            assert 0.1 < left < 0.9, left  # the case has blocks that leave and that stop


def test_chunk_counts_read_the_status():
    """``reduce_chunk`` on hand-made blocks: BUDGET and INVALID are unfinished and
    never exceed a station; LEFT_PROFILE is finished and counted apart; an
    invalid block's passages are not counted, a budget-stopped block's are;
    padding (valid False) counts for nothing."""
    from calib.hazard._stats import reduce_chunk
    from solvers.status import BUDGET, INVALID, LEFT_PROFILE, STOPPED

    status = np.array([[STOPPED, LEFT_PROFILE, BUDGET, INVALID, STOPPED, BUDGET]])
    stop_x = np.array([[50.0, 100.0, 80.0, 90.0, 5.0, 99.0]])
    stations = np.array([10.0, 60.0])
    passed = np.array([[[True, False], [True, True], [True, True], [True, True],
                        [False, False], [True, True]]])
    e = np.where(passed, 50.0, np.nan)
    valid = np.array([True, True, True, True, True, False])
    out = jax.device_get(jax.jit(reduce_chunk)(stop_x, status,
                                               passed, e, e, e, valid, stations))
    assert int(out.n_blocks) == 5
    np.testing.assert_array_equal(out.n_unfinished, [2])
    np.testing.assert_array_equal(out.n_left_profile, [1])
    np.testing.assert_array_equal(out.exceed, [[2, 1]])  # stopped at 50, left at 100
    np.testing.assert_array_equal(out.reach, [[3, 2]])  # not the invalid, not the padding
    np.testing.assert_array_equal(out.e30, [[3, 2]])


# ---------------------------------------------------------------- 1/sqrt(N) bands

@pytest.mark.slow  # three run sizes, 14 s
def test_bands_shrink_as_one_over_sqrt_n(tmp_path):
    """No posterior sample: every draw is the point estimate with its own random
    numbers, so the spread over draws is Monte Carlo noise only, sd =
    sqrt(p (1 - p) / N). With M = 64 draws the sample sd has a relative standard
    error of about 1 / sqrt(2 (M - 1)) = 9 %; we allow 4 of them (36 %) on each
    sd and 4 x sqrt(2) x 9 % on the ratio of the two sds (expected 1/2)."""
    path = write_calibration(tmp_path)
    stations = np.arange(100.0, 131.0, 2.0)
    m = 64
    sds, widths = {}, {}
    for n in (50, 200):
        # chunks of 50 blocks: N = 200 runs as 4 chunks, one compilation for both
        _, _, c = _run(path, m, n, [2.0], stations, seed=11, chunk_blocks=50)
        p = c.exceed[:, 0, :] / n                         # (M, S)
        pbar = p.mean(axis=0)
        s = int(np.argmin(np.abs(pbar - 0.5)))
        assert 0.2 < pbar[s] < 0.8
        sd = p[:, s].std(ddof=1)
        expected = math.sqrt(pbar[s] * (1 - pbar[s]) / n)
        assert abs(sd / expected - 1) < 4 / math.sqrt(2 * (m - 1)), (n, sd, expected)
        sds[n] = sd
        exc = exceedance_table(c)
        row = exc[np.isclose(exc.x_m, stations[s])].iloc[0]
        widths[n] = row.p_exceed_q95 - row.p_exceed_q05
    ratio = sds[200] / sds[50]
    assert abs(ratio - 0.5) < 0.5 * 4 * math.sqrt(2) / math.sqrt(2 * (m - 1))
    assert widths[200] < widths[50]


# ------------------------------------------------------------- reproducibility

def test_counts_do_not_depend_on_chunking_or_pool(small_run):
    """The same counts in one chunk of 400 blocks (256 lanes), in 3 chunks of 134
    (the last one 132 blocks) and in 2 of 200 (64 lanes each); chunks of 134 and
    200 share 256 slots (``solvers.crsp.task_slots``) and so one compiled program."""
    from calib.hazard._units import _slotted_chunk

    cal, profile, a = small_run
    b = run_hazard(cal, a.draws, profile, a.sizes_m, a.stations_x_m, a.n_blocks, 3,
                   chunk_blocks=150, pool=64)
    n_programs = _slotted_chunk._cache_size()
    c = run_hazard(cal, a.draws, profile, a.sizes_m, a.stations_x_m, a.n_blocks, 3,
                   chunk_blocks=200, pool=64)
    assert _slotted_chunk._cache_size() == n_programs
    for other in (b, c):
        for k in ("exceed", "reach", "e30", "e300", "n_unfinished"):
            np.testing.assert_array_equal(getattr(a, k), getattr(other, k), err_msg=k)
        for q in a.hist:
            np.testing.assert_array_equal(a.hist[q], other.hist[q], err_msg=q)


def test_draws_are_seeded_rows_of_the_posterior(tmp_path):
    rows = np.column_stack([np.linspace(0.3, 0.5, 30), np.full(30, 0.85), np.full(30, 2.0)])
    path = write_calibration(tmp_path, crsp_posterior=rows)
    cal = load_calibration(path)
    a, b = draw_parameters(cal, 10, 0), draw_parameters(cal, 10, 0)
    np.testing.assert_array_equal(a.values, b.values)
    assert len(set(a.rows)) == 10 and a.source == "posterior"
    np.testing.assert_allclose(a.values, rows[a.rows - 1], atol=1e-6)
    one = draw_parameters(cal, 1, 0)
    np.testing.assert_array_equal(one.values, [[0.41, 0.87, 2.0]])


# ------------------------------------------------------------- quantiles, classes

def test_hist_quantile_matches_percentile_within_one_bin():
    rng = np.random.default_rng(0)
    bins = BINS["energy_kJ"]
    v = rng.lognormal(mean=3.0, sigma=1.5, size=20000)
    counts = np.bincount(np.asarray(bins.index(jax.numpy.asarray(v))), minlength=bins.n)
    for q in (0.05, 0.5, 0.95, 0.99):
        got = hist_quantile(counts, q, bins)
        exact = np.quantile(v, q, method="inverted_cdf")
        assert abs(math.log10(got / exact)) <= 1 / bins.per_decade + 1e-12, (q, got, exact)
    with_zeros = counts.copy()
    with_zeros[0] += 3 * counts.sum()  # 75 % zeros (e.g. rolling blocks' bounce height)
    assert hist_quantile(with_zeros, 0.5, bins) == 0.0
    assert np.isnan(hist_quantile(np.zeros(bins.n, int), 0.5, bins))


def test_intensity_classes_and_matrix():
    assert [intensity_class(e) for e in (0.0, 29.9, 30.0, 300.0, 300.1)] == [
        "weak", "weak", "medium", "medium", "strong"]
    assert intensity_class(float("nan")) == ""
    assert [probability_class(f) for f in (2.0, 1 / 30, 1 / 31, 1 / 100, 1 / 299, 1 / 301,
                                           0.0)] == ["high", "high", "medium", "medium",
                                                     "low", "very low", ""]
    # strong blocks every 50 yr: red; weak every 10 yr only: blue; rare: residual
    assert hazard_level(1 / 50, 1 / 50, 1 / 50) == "red"
    assert hazard_level(1 / 10, 0.0, 0.0) == "blue"
    assert hazard_level(1 / 50, 1 / 200, 0.0) == "blue"
    assert hazard_level(1 / 200, 0.0, 0.0) == "yellow"
    assert hazard_level(1 / 1000, 1 / 1000, 1 / 1000) == "residual"
    assert hazard_level(0.0, 0.0, 0.0) == "white"


def test_release_rate_gives_frequencies(small_run):
    _, profile, c = small_run
    t = hazard_table(c, profile, release_rate_per_year=0.5)
    down = t[t.x_m > 0]
    np.testing.assert_allclose(down.freq_reach_per_yr, 0.5 * down.reach_prob_mean)
    assert np.all(down.freq_E_gt_300kJ_per_yr <= down.freq_E_gt_30kJ_per_yr)
    assert np.all(down.freq_E_gt_30kJ_per_yr <= down.freq_reach_per_yr)
    assert set(down.hazard_level) <= {"white", "residual", "yellow", "blue", "red"}
    assert "hazard_level" not in hazard_table(c, profile).columns


def test_percentiles_from_few_blocks_are_flagged_and_named(small_run):
    """A row whose percentiles rest on 1 to 19 passers has few_blocks set, and
    summary_text names it in a warning line (solvers.percentiles.few_blocks, the one rule)."""
    _, profile, c = small_run
    t = hazard_table(c, profile)
    n = t.n_blocks_reached
    expected = (t.x_m > c.release_x_m) & (n > 0) & (n < 20)
    assert (t.few_blocks == expected).all()
    assert expected.any() and (~expected & (n > 0)).any()  # both kinds in this run
    road = float(t[t.few_blocks].x_m.iloc[0])
    lines = summary_text(c, t, road).splitlines()
    assert any("(fewer than 20: rough)" in ln for ln in lines[1:-1])
    warning = lines[-1]
    assert warning.startswith("warning: the energy, bounce-height and speed percentiles rest "
                              "on fewer than 20 blocks in ")
    assert f"x = {road:g} m" in warning and "few_blocks" in warning
    assert "warning" not in summary_text(c, t[~t.few_blocks], road)


# ------------------------------------------------------------------ memory bound

# The command's peak resident size, read by the command itself as it exits: the
# high-water mark of its own address space (``VmHWM`` of /proc/self/status, kB).
# Not the child's ``ru_maxrss`` (wait4, RUSAGE_CHILDREN): Linux folds the address
# space a process had before its exec into that figure, and a child started by
# fork or vfork had its parent's, so it reads at least the test process's own
# resident size (a 1.5 GB parent gave 1,512 MB for a child whose VmHWM was 11 MB).
_OWN_PEAK = """
import atexit, runpy, sys

def _write_peak(path=sys.argv[1]):
    with open("/proc/self/status") as f:
        kb = next(line.split()[1] for line in f if line.startswith("VmHWM:"))
    with open(path, "w") as f:
        f.write(kb)

atexit.register(_write_peak)
sys.argv = [sys.argv[2]] + sys.argv[3:]
runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
"""


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads Linux's /proc")
def test_one_million_blocks_per_size_run_in_bounded_memory(tmp_path):
    """1e6 CRSP blocks of one size through the command line. Kept in memory
    whole, the per-block results alone would take 1e6 x 61 stations x 25 bytes
    = 1.5 GB; chunked, the command's peak resident size stays near the JAX
    baseline (about 0.9 GB)."""
    import subprocess
    import sys

    path = write_calibration(tmp_path)
    peak_file = tmp_path / "peak_kb.txt"
    p = subprocess.run([sys.executable, "-c", _OWN_PEAK, str(peak_file), "calib.hazard", path,
                        "--n-posterior", "1", "--n-blocks", "1000000", "--block-sizes-m", "2.0",
                        "--no-progress", "--out", str(tmp_path / "out")],
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert p.returncode == 0, p.stdout
    peak_mb = int(peak_file.read_text()) / 1024.0
    print(p.stdout, f"peak RSS {peak_mb:.0f} MB")
    import pandas as pd

    t = pd.read_csv(tmp_path / "out" / "hazard_table.csv")
    assert (t.n_blocks_per_draw == 1_000_000).all()
    assert peak_mb < 1500, peak_mb


# ------------------------------------------------------------------------- DEM

def _dem_run(tmp_path, n_blocks):
    path = write_calibration(tmp_path, dem=(0.40, 0.5))
    cal = load_calibration(path, "dem")
    profile = load_profile(cal.profile_csv)
    draws = draw_parameters(cal, 1, 0)
    stations = np.array([0.0, 50.0, 115.0, 130.0, 160.0])
    return cal, profile, run_hazard(cal, draws, profile, [2.0], stations, n_blocks, 5)


def test_dem_hazard_counts_are_consistent(tmp_path):
    """DEM path: a 2 m square, alpha = 0.40 L^-0.5; every block passes the talus
    (x = 50 m) and the curves are monotone; reach >= exceedance."""
    _, profile, c = _dem_run(tmp_path, 3)
    exc = exceedance_table(c)
    p = exc.p_exceed_mean.to_numpy()
    assert np.all(np.diff(p) <= 0) and p[0] == 1.0 and p[1] == 1.0
    t = hazard_table(c, profile)
    assert t.reach_prob_mean.iloc[1] == 1.0 and np.isnan(t.reach_prob_mean.iloc[0])
    assert np.all(t.reach_prob_mean.iloc[1:] >= t.p_exceed_mean.iloc[1:])
    assert c.n_unfinished.sum() == 0
    assert np.isfinite(t.energy_p95_kJ.iloc[1]) and t.energy_p95_kJ.iloc[1] > 0


def test_dem_counts_do_not_depend_on_chunking(tmp_path):
    """24 blocks of 2 m in one unit and in units of 10, 10 and 4: the same counts
    and histograms (a DEM block's result does not depend on its place in a
    compiled call, ``solvers.dem._sums``)."""
    path = write_calibration(tmp_path, dem=(0.40, 0.5))
    cal = load_calibration(path, "dem")
    profile = load_profile(cal.profile_csv)
    draws = draw_parameters(cal, 1, 0)
    stations = np.array([50.0, 115.0, 130.0, 160.0, 225.0])
    a, b = (run_hazard(cal, draws, profile, [2.0], stations, 24, 5, chunk_blocks=n)
            for n in (24, 10))
    assert 0 < a.exceed[0, 0, 2] < 24, a.exceed  # blocks stop on both sides of 130 m
    for k in ("exceed", "reach", "e30", "e300", "n_unfinished"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    for q in a.hist:
        np.testing.assert_array_equal(a.hist[q], b.hist[q], err_msg=q)


def _dem_seeded(tmp_path, zone, state, n_blocks):
    """``_dem_run``'s calibration, stations and 2 m blocks with release conditions."""
    from calib.model.release import Seeder

    path = write_calibration(tmp_path, dem=(0.40, 0.5))
    cal = load_calibration(path, "dem")
    profile = load_profile(cal.profile_csv)
    draws = draw_parameters(cal, 1, 0)
    stations = np.array([0.0, 20.0, 50.0, 115.0, 130.0, 160.0])
    seeder = Seeder.fixed_sizes([2.0], zone, state)
    return seeder, profile, run_hazard(cal, draws, profile, None, stations, n_blocks, 5,
                                       release=seeder)


def test_a_dem_release_at_one_point_in_the_solvers_state_is_the_plain_run(tmp_path):
    """DEM blocks of a fixed size through the per-block release path
    (``_units.dem_chunk`` with seeds) at one point, height and speed the solver's
    own (NaN): every block is the block of the run without release conditions,
    to the bit (the same key, the same release rule)."""
    from calib.model.release import ReleaseZone

    _, _, plain = _dem_run(tmp_path, 3)
    _, _, seeded = _dem_seeded(tmp_path, ReleaseZone("point", (0.0,)), ReleaseState(), 3)
    keep = [0, 2, 3, 4, 5]  # _dem_seeded's stations less 20 m are _dem_run's
    for k in ("exceed", "reach", "e30", "e300"):
        np.testing.assert_array_equal(getattr(seeded, k)[..., keep], getattr(plain, k),
                                      err_msg=k)
    np.testing.assert_array_equal(seeded.n_unfinished, plain.n_unfinished)
    for q in plain.hist:
        np.testing.assert_array_equal(seeded.hist[q][:, keep], plain.hist[q], err_msg=q)


def test_dem_blocks_start_where_the_release_zone_draws_them(tmp_path):
    """DEM blocks released in a zone of two points, 0 m and 30 m, at a drawn height
    (1 m, sd 0.5 m) and speed (2 m/s, sd 0.5 m/s): each block is the DEM run of
    its own drawn release (``sample_release`` on its key: abscissa, height and
    speed given to ``solvers.dem.simulate`` with the same key and the run's
    numerics), counted beyond every station to the block; a block passes the
    station at 20 m exactly when it starts at 0 m (every block from there passes
    the talus at 50 m, none from 30 m climbs back); every block ends."""
    from calib.model.release import ReleaseZone, sample_release
    from solvers import dem

    zone = ReleaseZone("points", (0.0, 30.0), (0.5, 0.5))
    n = 8
    seeder, profile, c = _dem_seeded(tmp_path, zone, ReleaseState(1.0, 0.5, 2.0, 0.5), n)
    keys = jax.vmap(lambda i: jax.random.fold_in(draw_key(5, 0), i))(np.arange(n))
    _, _, x, h, v = jax.vmap(lambda k: sample_release(seeder.arrays(0), seeder.kinds, k))(keys)
    upslope = int((np.asarray(x) == 0.0).sum())
    assert 0 < upslope < n, x  # both points drawn (this key, these 8 blocks)
    # the run's numerics (calib.model.dem_run): the step bound of a 0.2 m square, 150 s
    params = dem.make_params(profile, stiffness_scale=0.01)
    block = dem.make_block(2.0, alpha=0.40 * 2.0**-0.5, release_x_m=30.0,
                           stations=c.stations_x_m)
    dt = float(dem.stable_dt(params, dem.make_block(0.2, alpha=0.0)))
    options = dem.Options(max_steps=math.ceil(150.0 / dt))
    blocks = jax.vmap(lambda x, h, v: block._replace(release_x_m=x, release_height_m=h,
                                                     release_speed_m_s=v))(x, h, v)
    res = jax.vmap(lambda b, k: dem.simulate(params, b, k, options))(blocks, keys)
    stop = np.asarray(res.stop_x_m[:, 0])
    np.testing.assert_array_equal(c.exceed[0, 0], (stop[:, None] > c.stations_x_m).sum(0))
    np.testing.assert_array_equal(c.reach[0, 0], np.asarray(res.stations.passed[:, 0]).sum(0))
    assert c.reach[0, 0, 1] == upslope and c.n_unfinished.sum() == 0


def test_dem_counts_equal_a_direct_batch_run(tmp_path):
    """The DEM unit (keys, step bound, per-block energy) against a plain
    ``simulate_batch`` run of the same blocks."""
    from solvers import dem
    from solvers.dem._integrate import simulate_batch

    cal, profile, c = _dem_run(tmp_path, 3)
    params = dem.make_params(profile, stiffness_scale=0.01)
    block = dem.make_block(2.0, alpha=0.40 * 2.0**-0.5, release_x_m=0.0,
                           stations=c.stations_x_m)
    # the fit's step bound (calib.model.dem_run): 150 s at the step of a 0.2 m square
    dt = float(dem.stable_dt(params, dem.make_block(0.2, alpha=0.0)))
    keys = jax.vmap(lambda i: jax.random.fold_in(draw_key(5, 0), i))(np.arange(3))
    res = simulate_batch(params, block, keys, dem.Options(max_steps=math.ceil(150.0 / dt)))
    np.testing.assert_array_equal(c.reach[0, 0], np.asarray(res.stations.passed[:, 0]).sum(0))
    beyond = (np.asarray(res.stop_x_m[:, 0])[:, None] > c.stations_x_m).sum(0)
    np.testing.assert_array_equal(c.exceed[0, 0], beyond)
    # energies per block: the 2D energy per metre times the side (a 2 m cube)
    e_block = np.asarray(res.stations.energy_kJ[:, 0]) * 2.0
    passed = np.asarray(res.stations.passed[:, 0])
    bins = BINS["energy_kJ"]
    for s in range(len(c.stations_x_m)):
        k = np.asarray(bins.index(jax.numpy.asarray(e_block[passed[:, s], s])))
        np.testing.assert_array_equal(c.hist["energy_kJ"][0, s],
                                      np.bincount(k, minlength=bins.n))
