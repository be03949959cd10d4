"""CRSP invariants on surveyed-like profiles.

Each test names the defect it guards against and fails on a solver that has it
(collinear vertices that let blocks fall through the ground, a full impact at
every kink, a full impact every radius when rolling on rough ground, an
S -> 0 limit that jumps).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from solvers import crsp, ground_z, load_profile, make_profile
from solvers.crsp._contact import asperity_loss
from solvers.crsp._model import State, event_budget, segment_table, step
from solvers.crsp._vertex import vertex_transition
from solvers.profile import refine
from solvers.status import BUDGET, INVALID, LEFT_PROFILE, STOPPED

G = 9.81
POSTIGNANO = "data/postignano_profile.csv"


def _runs(prof, radius_m, n, seed, stations=None, **params):
    p = crsp.params_from_profile(prof, **params)
    return crsp.run_blocks(p, crsp.make_block(radius_m), jax.random.key(seed), n, prof,
                           stations_x_m=stations)


def _median_se(x, seed=0, n_boot=200):
    """Bootstrap standard error of the median (fixed seed)."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(x), (n_boot, len(x)))
    return float(np.std(np.median(np.asarray(x)[idx], axis=1)))


# slow: each refinement compiles two solver programs of its own (22 s at 0.5 m); the
# default run keeps the property on Postignano refined every 2 m with a barrier
# (test_crsp_barrier.py::test_no_block_below_the_ground_and_collinear_vertices_change_nothing)
@pytest.mark.slow
@pytest.mark.parametrize("step_m", [0.5, 2.0, 5.0])
@pytest.mark.parametrize("setting", [
    dict(radius_m=0.1, Kn=0.44, Kt=0.96, roughness_m=0.37),   # a Postignano calibration
    dict(radius_m=0.5, roughness_m=0.0),                        # smooth: rolls to 153 m
])
def test_collinear_vertices_leave_results_unchanged(step_m, setting):
    """Inserting collinear vertices changes nothing: impacts draw their roughness
    per impact, rolling is exact across segment ends, collinear vertices are
    continuations. Before: 677 of 2000 blocks fell below the ground at 2 m."""
    base = load_profile(POSTIGNANO)
    fine = refine(base, step_m)
    setting = dict(setting)
    r = setting.pop("radius_m")
    n = 4000
    stations = jnp.array([230.0])
    a = _runs(base, r, n, 1, stations, **setting)
    b = _runs(fine, r, n, 1, stations, **setting)
    assert np.all(b.status == STOPPED), np.bincount(b.status)
    same = np.abs(a.runout_m - b.runout_m) < 1e-6
    # identical block by block, up to round-off at rare borderline decisions
    assert same.mean() >= 0.995, same.mean()
    # (rounded: a point mass that differs by round-off is the same distribution)
    assert stats.ks_2samp(a.runout_m.round(6), b.runout_m.round(6)).pvalue > 0.01
    np.testing.assert_array_equal(a.stations.passed, b.stations.passed)


def test_no_block_below_ground_or_out_of_budget_over_the_prior_box():
    """Over random parameters of the calibration box (Kn 0.15-0.6, Kt 0.6-0.98,
    S 0-4 m, rolling friction 5-40 deg) and diameters 0.1-2 m, on a profile with
    1 m vertices and 5 cm survey noise: no block ends INVALID (below the ground
    after some event, or non-finite) and none runs out of its event budget."""
    prof = refine(load_profile(POSTIGNANO), 1.0, z_noise_m=0.05, seed=3)
    rng = np.random.default_rng(0)
    total = np.zeros(6, int)
    for i in range(8):
        kn, kt, s = rng.uniform(0.15, 0.6), rng.uniform(0.6, 0.98), rng.uniform(0.0, 4.0)
        phi = rng.uniform(5.0, 40.0)
        r = float([0.05, 0.1, 0.25, 0.5, 1.0, 0.05, 0.1, 0.5][i])
        res = _runs(prof, r, 300, i, Kn=kn, Kt=kt, roughness_m=s, rolling_friction_deg=phi)
        total += np.bincount(res.status, minlength=6)
        gz = np.asarray(ground_z(prof, jnp.asarray(res.stop_x_m)))
        assert np.all(res.stop_z_m >= gz - 1e-3)
        budget = int(event_budget(prof, jnp.asarray(r), crsp.Settings()))
        assert res.n_events.max() < budget / 4, (res.n_events.max(), budget)
    assert total[INVALID] == 0 and total[BUDGET] == 0, total


def test_a_state_below_the_ground_is_flagged_invalid():
    """The ground check after every event turns a block under the ground into
    status INVALID (an error), never a passage or a stop."""
    prof = load_profile(POSTIGNANO)
    params = crsp.params_from_profile(prof)
    block = crsp.make_block(0.5)
    s = crsp._model.init(params, block, jax.random.key(0), prof)
    # 1 m under the talus, flying down the slope: the next event cannot fix it
    x = 50.0
    s = s._replace(x_m=jnp.float64(x), z_m=ground_z(prof, jnp.float64(x)) - 1.0,
                   vx_m_s=jnp.float64(5.0), vz_m_s=jnp.float64(-1.0),
                   seg=jnp.int32(1), mode=jnp.int32(crsp.FLIGHT))
    from solvers._rng import key_words
    new, _ = step(s, params, block, key_words(jax.random.key(1)), prof,
                  segment_table(prof, params, block), crsp.Settings())
    assert int(new.mode) == INVALID
    assert isinstance(new, State)


def test_roughness_limit_s_to_zero_equals_s_zero():
    """S -> 0 is continuous: no asperity impacts survive the limit. Before:
    S = 0 gave 173.5 m and S = 1e-6 m gave 110.8 m (r = 0.5 m). 500 blocks with
    the same keys (common random numbers): on 2 cores, two chunks of 250, the
    compiled program of the other 256-slot runs on this profile."""
    prof = load_profile(POSTIGNANO)
    r0 = _runs(prof, 0.5, 500, 0, roughness_m=0.0).runout_m
    for s in (1e-6, 1e-4):
        rs = _runs(prof, 0.5, 500, 0, roughness_m=s).runout_m
        assert abs(np.median(rs) - np.median(r0)) < 0.05, (s, np.median(rs), np.median(r0))


@pytest.mark.slow  # two sizes x 1000 blocks, 11 s
def test_small_roughness_adds_no_size_effect():
    """Dissipation that does not come through S / R: with S = 1e-4 m a 0.1 m and
    a 2 m block run out alike (no loss that scales as 1/R whatever S)."""
    prof = load_profile(POSTIGNANO)
    small = _runs(prof, 0.05, 500, 0, roughness_m=1e-4).runout_m
    large = _runs(prof, 1.0, 500, 0, roughness_m=1e-4).runout_m
    assert abs(np.median(small) - np.median(large)) < 0.5, (np.median(small), np.median(large))


def test_asperity_loss_limits():
    """lambda(0) = 0, lambda increasing in theta_max, and the closed form equals
    the mean over uniform tilts."""
    k = 0.4
    t = jnp.linspace(0.0, math.pi / 2, 50)
    lam = np.asarray(asperity_loss(t, k))
    assert lam[0] == 0.0
    assert np.all(np.diff(lam) > 0)
    u = (np.arange(20000) + 0.5) / 20000
    for tm in (0.1, 0.8, 1.5):
        keep = np.mean(((np.cos(u * tm) + k) / (1 + k)) ** 2)
        np.testing.assert_allclose(float(asperity_loss(jnp.float64(tm), k)), 1 - keep, rtol=1e-6)


ROUGHNESS_GRID_M = (0.0, 0.01, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)


def _medians_over_roughness(radius_m, phi_deg, n=1000):
    prof = load_profile(POSTIGNANO)
    meds, ses = [], []
    for s in ROUGHNESS_GRID_M:
        r = _runs(prof, radius_m, n, 0, roughness_m=s, rolling_friction_deg=phi_deg).runout_m
        meds.append(float(np.median(r)))
        ses.append(_median_se(r))
    return np.array(meds), np.array(ses)


def _assert_non_increasing(meds, ses):
    for i in range(len(meds) - 1):
        tol = 2.0 * math.hypot(ses[i], ses[i + 1]) + 1e-6
        assert meds[i + 1] <= meds[i] + tol, (ROUGHNESS_GRID_M[i + 1], meds.round(1).tolist())


def test_median_runout_does_not_increase_with_roughness_weak_rolling_resistance():
    """With a rolling resistance of 8 deg (RocFall's arctan((1 - Rt) / Rt) at
    Rt 0.87) the median runout falls with S at every step of the grid (within 2
    bootstrap standard errors). Before: it jumped from S = 0 to any S > 0."""
    meds, ses = _medians_over_roughness(0.5, 8.0)
    _assert_non_increasing(meds, ses)


@pytest.mark.xfail(strict=True, reason=(
    "measured 2026-11-23, r = 0.5 m, Kn 0.41, Kt 0.87, rolling friction 30 deg, 1000 blocks: "
    "medians 153.2, 149.4, 153.7, 177.2, 162.9, 124.8, 111.6, 110.2 m for S = 0, 0.01, "
    "0.05, 0.1, 0.2, 0.5, 1, 2 m. On the 40 deg talus a rock rolling against tan(30 deg) "
    "gains 1.4 m/s^2 along the slope, one in flight ~6.3 m/s^2: small roughness (S/R ~ "
    "0.1-0.2) turns rolling into hops and carries rocks further. A property of a strong "
    "rolling resistance next to CRSP's impact law, not of the roughness treatment "
    "(monotone at 8 deg); the rolling resistance is a site parameter to calibrate"))
def test_median_runout_does_not_increase_with_roughness_paper_rolling_resistance():
    meds, ses = _medians_over_roughness(0.5, 30.0)
    _assert_non_increasing(meds, ses)



@pytest.mark.slow  # a measured gap, 10-15 s; the default run keeps the tests of the threshold's use
@pytest.mark.xfail(strict=True, reason=(
    "measured 2026-12-06 (512 blocks, key 0): the runouts' 5/50/95 % quantiles are "
    "16.2/103.5/126.2 m at the default 0.5 m/s (32 % of the blocks within 40 m), "
    "16.4/109.8/129.0 m at 0.25 (6 %), 95.3/111.5/129.3 m at 0.125 (1 %), "
    "95.7/111.6/129.4 m at 0.02, 0.01 and 0.005 m/s (none): the cutoff settles from "
    "about 0.05 m/s down. A default of 0.02 m/s fails ten other tests, nine of them "
    "written for the stalls, and the median runout's fall with roughness at a rolling "
    "resistance of 8 deg: every micro-hop becomes a CRSP impact costing Kt "
    "(docs/studies.md, 'The rolling threshold')"))
def test_runouts_do_not_depend_on_the_rolling_threshold_below_the_default():
    """The rolling threshold (a rebound slower than it keeps the rock on the
    ground, rolling) is a numerical cutoff: halving or quartering the default
    must leave the runouts' 5/50/95 % quantiles where they are (within 2 m, 512
    blocks, the same keys). Setting: the Tschamut east spot's profile cut from
    the proxy raster, a slow release just below its top bench (x 40.4 m, 0.45 m
    up, 0.35 m/s, the site's release errors), a 0.37 m block, parameters fitted
    on the main line (rolling resistance 36 deg, above the 24-30 deg stretch at
    57-73 m, where a rolling rock stalls)."""
    prof = load_profile("data/tschamut2014/east_spot_profile.csv")
    quantiles = []
    for factor in (1.0, 0.5, 0.25):
        r = _runs(prof, 0.3677 / 2, 512, 0, Kn=0.316, Kt=0.979, roughness_m=0.0965,
                  rolling_friction_deg=36.27, release_x_m=40.4, release_height_m=0.45,
                  release_vx_m_s=0.35, release_height_sd_m=0.6, release_speed_sd_m_s=0.3,
                  rolling_threshold_m_s=factor * crsp.ROLLING_THRESHOLD_M_S)
        assert np.all(np.isin(r.status, [STOPPED, LEFT_PROFILE])), np.unique(r.status)
        quantiles.append(np.quantile(r.runout_m, [0.05, 0.5, 0.95]))
    q = np.array(quantiles)
    assert np.max(np.abs(q[1:] - q[0])) <= 2.0, q.round(1).tolist()

# slow: a 150-vertex profile's compilation, 19 s; the default run keeps collinear vertices at 0.5
# m
@pytest.mark.slow
def test_survey_noise_does_not_change_a_smooth_run():
    """A rolling block crossing hundreds of small kinks (1 cm noise every 2 m)
    keeps its runout. Before: 173.5 m on 3 segments, 117.0 m with the noise."""
    base = load_profile(POSTIGNANO)
    noisy = refine(base, 2.0, z_noise_m=0.01, seed=1)
    a = np.median(_runs(base, 0.5, 4, 0, roughness_m=0.0).runout_m)  # S = 0: deterministic
    b = np.median(_runs(noisy, 0.5, 4, 0, roughness_m=0.0).runout_m)
    assert abs(a - b) < 0.01 * a, (a, b)


def _curve(n_seg, phi_deg=20.0):
    x = np.linspace(0.0, 300.0, n_seg + 1)
    z = 100.0 * np.exp(-x / 50.0) - 4.0 * np.exp(-((x - 120.0) / 15.0) ** 2)
    mats = {"z": {"Kn": 0.41, "Kt": 0.87, "roughness_m": 0.0,
                  "rolling_friction_deg": phi_deg, "phi_deg": 30.0}}
    return make_profile(x, z, ["z"] * n_seg, mats)


# slow: four profiles' compilations, 37 s; the default run keeps collinear vertices at 0.5 m
@pytest.mark.slow
def test_refining_a_smooth_curve_converges():
    """A smooth concave curve with a convex hump, sampled ever more finely: the
    median runout settles (S = 0.3 m: within 0.3 m from 100 segments on)."""
    meds = []
    for n_seg in (100, 200, 400, 800):
        prof = _curve(n_seg)
        meds.append(float(np.median(_runs(prof, 0.5, 200, 0, roughness_m=0.3).runout_m)))
    assert max(meds) - min(meds) < 0.3, meds


@pytest.mark.slow
def test_refining_a_smooth_curve_converges_without_roughness():
    """S = 0 (one deterministic block): concave kinks whose normal speed reaches
    the rolling threshold are impacts, so coarse samplings of a smooth curve
    stop early (measured 140, 157, 182 m at 100, 200, 400 segments); once every
    kink is below the threshold the runout settles (292.1, 293.0, 293.2 m at
    800, 1600, 3200 segments)."""
    meds = []
    for n_seg in (800, 1600, 3200):
        prof = _curve(n_seg)
        meds.append(float(_runs(prof, 0.5, 1, 0, roughness_m=0.0).runout_m[0]))
    assert abs(meds[2] - meds[1]) < abs(meds[1] - meds[0]) + 0.1, meds
    assert abs(meds[2] - meds[1]) < 1.0, meds


def test_vertex_transition_cases():
    """Collinear: continue; slow rock over a small convex edge: rounds it; fast
    rock: launches; concave: impact only at or above the threshold; pit: rest."""
    k, r, thr = 0.4, 0.5, 0.5
    beta0 = jnp.float64(0.0)

    def vt(v, beta2, beta=beta0, d=1.0, length=jnp.inf):
        return vertex_transition(jnp.float64(v), jnp.float64(d), beta, jnp.float64(beta2), r, k,
                                 thr, G, length)

    a = vt(3.0, 1e-12)
    assert not bool(a.launch) and not bool(a.impact) and float(a.u_next_m_s) == 3.0
    # 30 deg convex edge from flat ground: from rest the rock leaves at 10/17
    # (psi 54 deg > 30 deg), so it rounds the edge; at 10 m/s it leaves at once
    slow = vt(0.5, -math.radians(30.0))
    assert not bool(slow.launch) and float(slow.u_next_m_s) == 0.5
    fast = vt(10.0, -math.radians(30.0))
    assert bool(fast.launch) and float(fast.launch_rad) == 0.0
    # 0.3 deg convex kink at 10 m/s: separates, but the hop is no hop
    kink = vt(10.0, -math.radians(0.3), length=2.0)
    assert not bool(kink.launch) and not bool(kink.impact)
    np.testing.assert_allclose(float(kink.u_next_m_s), 10.0 * math.cos(math.radians(0.3)))
    # concave: 10 deg at 1 m/s -> 0.17 m/s normal: touch-down; at 5 m/s -> impact
    assert not bool(vt(1.0, math.radians(10.0)).impact)
    assert bool(vt(5.0, math.radians(10.0)).impact)
    # pit: descending into a rising segment with almost no speed
    pit = vt(0.01, math.radians(20.0), beta=jnp.float64(-math.radians(20.0)))
    assert bool(pit.rest)


def test_vertex_transition_never_creates_energy():
    rng = np.random.default_rng(0)
    n = 20000
    v = rng.uniform(0.0, 40.0, n)
    beta = rng.uniform(-1.4, 1.4, n)
    beta2 = rng.uniform(-1.4, 1.4, n)
    d = rng.choice([-1.0, 1.0], n)
    r = rng.uniform(0.05, 2.0, n)
    out = jax.vmap(vertex_transition, in_axes=(0, 0, 0, 0, 0, None, None, None, None))(
        v, d, beta, beta2, r, 0.4, 0.5, G, 2.0)
    assert np.all(np.asarray(out.u_next_m_s) <= v * (1 + 1e-12))


def test_stops_only_where_rest_is_possible():
    """Every STOPPED block lies on a segment where tan|beta| <= mu, or at a pit
    vertex (the two segments around it slope towards it)."""
    prof = refine(load_profile(POSTIGNANO), 1.0, z_noise_m=0.05, seed=3)
    res = _runs(prof, 0.25, 400, 0, roughness_m=1.0, rolling_friction_deg=20.0)
    x = np.asarray(prof.x_m)
    z = np.asarray(prof.z_m)
    beta = np.arctan2(np.diff(z), np.diff(x))
    mu = math.tan(math.radians(20.0))
    for xs in res.stop_x_m[res.status == STOPPED]:
        j = np.searchsorted(x, xs)
        if j < len(x) and abs(x[j] - xs) < 1e-9 and 0 < j < len(x) - 1:
            assert beta[j - 1] <= 1e-12 and beta[j] >= -1e-12 or \
                abs(math.tan(beta[j - 1])) <= mu + 1e-9 or abs(math.tan(beta[j])) <= mu + 1e-9
        else:
            seg = min(max(j - 1, 0), len(beta) - 1)
            assert abs(math.tan(beta[seg])) <= mu + 1e-9, (xs, math.degrees(beta[seg]))
    assert np.all((res.status == STOPPED) | (res.status == LEFT_PROFILE))


@pytest.mark.parametrize("path, refine_m, radius_m", [
    ("data/tschamut2014/profile.csv", None, 0.3),  # the raster cut, 179 segments
    (POSTIGNANO, 1.0, 0.5),                         # 1 m vertices with 5 cm survey noise
])
def test_every_shape_class_stays_above_ground_and_creates_no_energy(path, refine_m, radius_m):
    """The hazard run releases CRSP's three shape classes (``--block-shape``): a
    sphere, a cylinder and a disc of one radius each finish (no INVALID, none out of
    its budget), end above the ground, and pass every station with at most the
    energy their fall has released, m (v0^2 / 2 + g (z_release - z_ground(x)))."""
    prof = load_profile(path)
    if refine_m:
        prof = refine(prof, refine_m, z_noise_m=0.05, seed=3)
    st = jnp.asarray(np.arange(float(prof.x_m[0]) + 5.0, float(prof.x_m[-1]), 5.0))
    p = crsp.params_from_profile(prof, Kn=0.4, Kt=0.9, roughness_m=0.2,
                                 rolling_friction_deg=25.0)
    z0 = float(ground_z(prof, jnp.asarray(float(p.release_x_m)))) + float(p.release_height_m)
    drop = z0 - np.asarray(ground_z(prof, st))
    for shape in crsp.SHAPES:
        block = crsp.make_block(radius_m, shape)
        res = crsp.run_blocks(p, block, jax.random.key(1), 300, prof, stations_x_m=st)
        assert not np.any((res.status == INVALID) | (res.status == BUDGET)), shape
        gz = np.asarray(ground_z(prof, jnp.asarray(res.stop_x_m)))
        assert np.all(res.stop_z_m >= gz - 1e-3), shape
        m = float(block.mass_kg)
        bound_kJ = m * (0.5 * float(p.release_vx_m_s) ** 2 + G * drop) / 1000.0
        e = np.where(res.stations.passed, res.stations.energy_kJ, 0.0)
        assert np.all(e <= bound_kJ * (1 + 1e-9) + 1e-12), (shape, float(np.max(e - bound_kJ)))
