"""Release conditions as uncertain inputs: a tracked release height and speed
carry errors (the site's ``release_height_sd_m``, ``release_speed_sd_m_s``),
and every CRSP block draws its own from truncated normals about them
(``solvers.crsp.init``); a release that a raster puts below its ground is a
release from the error's tail above the ground, not a block at rest. Also the
plumbing (site file, entries, forward model, calibration file, validation) and
the flag on rows that stall at their release."""

from __future__ import annotations

import functools
import json
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import truncnorm
from test_hazard_fixtures import write_calibration

import calib  # noqa: F401  (x64)
import solvers.crsp as crsp
from calib.files.calibration_file import load_calibration
from calib.files.observations import Observations
from calib.files.site import SiteError, load_site
from calib.inference.adequacy import adequacy_record
from calib.inference.predictive_check import heldout_entries, stall_message, stalled_rows
from calib.model.entries import Entries
from calib.model.forward import CrspForward, release_rolling_deg, release_slopes_deg
from calib.model.priors import CRSP_BOX, CRSP_ROLLING_BOX
from calib.validate import main as validate_main
from calib.validate import print_summary
from solvers.crsp._model import CONTACT, FLIGHT, init
from solvers.profile import ground_z, load_profile
from solvers.truncated_normal import nonnegative_normal

TSCHAMUT = load_profile("data/tschamut2014/profile.csv")
SITE = load_site("data/tschamut2014/profile.csv")
BLOCK = crsp.make_block(0.3677 / 2, density_kg_m3=2650.0)
# the shoulder of the Tschamut line (25 deg) below a rolling resistance of 30.7 deg
# (tests/test_release_height.py): a block released slowly on the ground stalls there
SHOULDER_X_M, PHI_R_DEG = 38.7, 30.7
THETA = np.array([[0.596, 0.958, 0.104, PHI_R_DEG]])


def _truncnorm(mean, sd):
    return truncnorm(-mean / sd, np.inf, loc=mean, scale=sd)


# ---------------------------------------------------------------- the draw


@pytest.mark.parametrize("mean, sd", [(-0.5, 0.6), (0.0, 0.6), (1.2, 0.6), (-3.0, 0.3),
                                      (0.39, 0.3)])
def test_the_draw_is_the_truncated_normals_inverse_cdf(mean, sd):
    u = np.linspace(0.0, 0.999, 37)
    x = np.asarray(nonnegative_normal(jnp.asarray(u), mean, sd))
    np.testing.assert_allclose(x, _truncnorm(mean, sd).ppf(u), rtol=1e-9, atol=1e-12)
    assert np.all(x >= 0.0)


def test_sd_zero_is_the_point_clipped_to_the_ground_and_the_limit_of_small_sds():
    u = jnp.linspace(0.0, 0.999, 11)
    for mean in (-1.0, -1e-3, 0.0, 0.7):
        exact = np.asarray(nonnegative_normal(u, mean, 0.0))
        assert np.all(exact == max(mean, 0.0))
        for sd in (1e-6, 1e-9):
            # every draw lies within 37.5 sd of the point (Phi^-1 of the smallest
            # normal float64, the draw at u = 0), so it tends to it as sd -> 0
            near = np.asarray(nonnegative_normal(u, mean, sd))
            assert np.all(np.abs(near - max(mean, 0.0)) <= 37.6 * sd), (mean, sd, near)
            assert np.all(np.abs(near[1:] - max(mean, 0.0)) <= 5 * sd), (mean, sd, near)


def test_a_release_far_below_the_ground_draws_a_finite_height_just_above_it():
    x = np.asarray(nonnegative_normal(jnp.linspace(0.0, 0.999, 11), -100.0, 1.0))
    assert np.all(np.isfinite(x)) and np.all(x >= 0.0) and np.all(x < 0.1)


# ---------------------------------------------------------------- the solver's release


def _params(**kw):
    base = dict(rolling_friction_deg=PHI_R_DEG, release_x_m=SHOULDER_X_M, release_vx_m_s=0.39)
    return crsp.params_from_profile(TSCHAMUT, **{**base, **kw})


def _inits(params, n=400, seed=0):
    keys = jax.random.split(jax.random.key(seed), n)
    return jax.vmap(lambda k: init(params, BLOCK, k, TSCHAMUT))(keys)


def test_with_zero_sds_the_release_is_the_point_release():
    """sd 0 (the default): the release abscissa from the key's uniform as before,
    the block exactly at the given height and velocity; a NEGATIVE height (below
    the profile's ground) is clipped: the block starts on the ground, rolling,
    the same state as a release at height 0."""
    assert float(crsp.params_from_profile(TSCHAMUT).release_height_sd_m) == 0.0
    assert float(crsp.params_from_profile(TSCHAMUT).release_speed_sd_m_s) == 0.0
    key = jax.random.key(5)
    p = _params(release_height_m=1.2, release_x_spread_m=2.0, release_vz_m_s=0.1)
    s = init(p, BLOCK, key, TSCHAMUT)
    x0 = SHOULDER_X_M + float(jax.random.uniform(key, dtype=jnp.float64)) * 2.0
    assert float(s.x_m) == x0 and int(s.mode) == FLIGHT
    assert float(s.z_m) == float(ground_z(TSCHAMUT, s.x_m)) + 1.2
    assert (float(s.vx_m_s), float(s.vz_m_s)) == (0.39, 0.1)
    below, ground = (init(_params(release_height_m=h), BLOCK, key, TSCHAMUT) for h in (-0.7, 0.0))
    for a, b in zip(below, ground, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert int(below.mode) == CONTACT and float(below.z_m) == float(ground_z(TSCHAMUT, below.x_m))


@pytest.mark.parametrize("height_m, sd_m", [(-1.0, 0.6), (-0.2, 0.6), (0.5, 1.0), (-0.5, 0.0)])
def test_no_block_starts_below_the_ground_and_heights_follow_the_truncated_normal(height_m,
                                                                                   sd_m):
    s = _inits(_params(release_height_m=height_m, release_height_sd_m=sd_m,
                       release_x_spread_m=5.0))
    h = np.asarray(s.z_m - jax.vmap(lambda x: ground_z(TSCHAMUT, x))(s.x_m))
    assert np.all(h >= 0.0)
    if sd_m == 0.0:
        assert np.all(h == 0.0)
        return
    t = _truncnorm(height_m, sd_m)
    se = t.std() / np.sqrt(h.size)
    assert abs(h.mean() - t.mean()) < 4 * se, (h.mean(), t.mean(), se)
    assert np.all(np.asarray(s.mode) == FLIGHT)  # above the ground: in flight


def test_speeds_follow_the_truncated_normal_along_the_given_direction():
    s = _inits(_params(release_height_m=1.0, release_speed_sd_m_s=0.3, release_vz_m_s=0.2))
    v = np.hypot(np.asarray(s.vx_m_s), np.asarray(s.vz_m_s))
    t = _truncnorm(np.hypot(0.39, 0.2), 0.3)
    assert abs(v.mean() - t.mean()) < 4 * t.std() / np.sqrt(v.size)
    np.testing.assert_allclose(np.asarray(s.vz_m_s) / v, 0.2 / np.hypot(0.39, 0.2), rtol=1e-12)
    # no velocity given: the drawn speed is horizontal, downslope (+x)
    s0 = _inits(_params(release_height_m=1.0, release_speed_sd_m_s=0.3, release_vx_m_s=0.0))
    assert np.all(np.asarray(s0.vx_m_s) >= 0) and np.all(np.asarray(s0.vz_m_s) == 0.0)
    assert abs(np.asarray(s0.vx_m_s).mean() - _truncnorm(0.0, 0.3).mean()) < 0.02


@functools.cache
def _shoulder_runouts() -> np.ndarray:
    """Runouts (5, 200) of one forward call (common random numbers: block j of
    every entry has the same key): releases at h = -0.5 m (below the profile's
    ground) and 0 m on the shoulder, exact; -0.5 m with the site's errors; and
    h = 0.3 m on the 44 deg slope below, exact and with the site's errors."""
    site_sd = (SITE.release_height_sd_m, SITE.release_speed_sd_m_s)
    shoulder = Entries.at_sizes(np.full(2, 0.3677), SHOULDER_X_M, release_speed_m_s=0.39,
                                release_height_m=[-0.5, 0.0], density_kg_m3=2650.0)
    steep = Entries.at_sizes([0.3677], 41.5, release_speed_m_s=0.8, release_height_m=0.3,
                             density_kg_m3=2650.0)
    e = (shoulder.concat(shoulder.take([0]).with_release_errors(*site_sd)).concat(steep)
         .concat(steep.with_release_errors(*site_sd)))
    return CrspForward(TSCHAMUT, e, 200, jax.random.key(3), box=CRSP_ROLLING_BOX).runouts(
        THETA)[0]


def test_a_release_below_the_ground_runs_on_with_the_sites_error():
    """The defect: a tracked release below the profile's ground (h = -0.5 m on
    the 25 deg shoulder) taken as exact starts every block on the ground, at the
    tracked 0.39 m/s, where phi_r (30.7 deg) exceeds the slope: all stall within
    1 m, the runs of a release at 0 m. With the site's errors (0.6 m, 0.3 m/s)
    each block starts at a height drawn above the ground and falls onto the
    slope: most run on."""
    r = _shoulder_runouts()
    np.testing.assert_array_equal(r[0], r[1])
    assert np.mean(r[0] < 1.0) == 1.0
    stalled = np.mean(r[2] < 1.0)
    print(f"stalled within 1 m: {stalled:.1%}, median runout {np.nanmedian(r[2]):.1f} m")
    assert stalled < 0.2 and np.nanmedian(r[2]) > 50.0


def test_the_sites_errors_change_the_blocks_of_a_release_above_the_ground():
    r = _shoulder_runouts()
    assert np.mean(r[3] != r[4]) > 0.5
    assert np.all(np.isfinite(r[3])) and np.mean(np.isfinite(r[4])) > 0.95


# ---------------------------------------------------------------- the DEM's release


def _dem_release(height_m, speed_m_s, height_sd_m, speed_sd_m_s, n_keys=400, errors=True):
    """Heights of the lowest possible corner above the ground (m) and speeds
    (m/s) of ``n_keys`` DEM releases of a 0.37 m block on the shoulder
    (``errors``: the draws compiled, ``solvers.dem.Options.release_errors``)."""
    from solvers.dem import make_block, make_params
    from solvers.dem._integrate import _release

    params = make_params(TSCHAMUT)
    block = make_block(0.3677, alpha=0.5, release_x_m=SHOULDER_X_M,
                       release_speed_m_s=speed_m_s, release_height_m=height_m,
                       release_height_sd_m=height_sd_m, release_speed_sd_m_s=speed_sd_m_s)
    keys = jax.random.split(jax.random.key(11), n_keys)
    pose = jax.vmap(lambda k: _release(params, block, k, errors))(keys)
    centre = np.asarray(pose.pos)[:, 0]
    ground = float(ground_z(TSCHAMUT, jnp.asarray(SHOULDER_X_M)))
    return centre[:, 1] - 0.3677 / np.sqrt(2.0) - ground, np.asarray(pose.vel)[:, 0, 0], pose


def test_a_dem_release_below_the_ground_draws_its_height_from_the_error():
    """The DEM's blocks draw a tracked release as CRSP's do: h = -0.5 m with the
    site's sd 0.6 m is a height drawn from the truncated normal's tail, above
    the ground (the DEM took the mean clipped to the ground before, every block
    at 0); the tracked 0.39 m/s with sd 0.3 m/s is a truncated normal draw."""
    h, v, _ = _dem_release(-0.5, 0.39, 0.6, 0.3)
    assert np.all(h >= -1e-12) and np.mean(h > 0.05) > 0.5
    for x, (mean, sd) in ((h, (-0.5, 0.6)), (v, (0.39, 0.3))):
        t = _truncnorm(mean, sd)
        assert abs(x.mean() - t.mean()) < 4 * t.std() / np.sqrt(x.size), (x.mean(), t.mean())


def test_a_dem_release_with_exact_inputs_is_the_point_release():
    """sd 0: the given height (on the ground where it is negative) and speed
    exactly, and every other draw of the release (turn, offset) as with the
    same key and no errors at all."""
    h, v, pose = _dem_release(-0.5, 0.39, 0.0, 0.0, n_keys=8)
    np.testing.assert_allclose(h, 0.0, atol=1e-12)
    assert np.all(v == 0.39)
    for height in (-0.5, 0.0):  # the same pose whether the draws are compiled or not
        _, _, plain = _dem_release(height, 0.39, 0.0, 0.0, n_keys=8, errors=False)
        np.testing.assert_array_equal(np.asarray(pose.pos), np.asarray(plain.pos))
    _, _, drawn = _dem_release(0.0, 0.39, 0.6, 0.3, n_keys=8)
    np.testing.assert_array_equal(np.asarray(drawn.theta), np.asarray(pose.theta))
    with pytest.raises(ValueError, match="release_height_sd_m"):
        from solvers.dem import make_block
        make_block(0.5, alpha=0.5, release_height_sd_m=-0.1)


def test_a_dem_program_without_the_draws_refuses_a_release_with_errors():
    """A block with a positive sd in a program compiled without the draws
    (``Options.release_errors`` False, the default) ends ``INVALID``: its
    errors are never silently dropped."""
    from solvers.dem import make_block, make_params, simulate
    from solvers.status import INVALID

    params = make_params(TSCHAMUT)
    for h, sd_h in ((-0.5, 0.0), (np.nan, 0.0), (0.3, 0.6)):  # the speed's error, the height's
        block = make_block(0.3677, alpha=0.5, release_x_m=SHOULDER_X_M, release_speed_m_s=0.39,
                           release_height_m=h, release_height_sd_m=sd_h,
                           release_speed_sd_m_s=0.3 if sd_h == 0.0 else 0.0)
        res = jax.jit(lambda k, b=block: simulate(params, b, k))(jax.random.key(0))
        assert int(res.status) == INVALID, (h, sd_h)


def test_the_dem_forward_draws_each_blocks_release_from_the_entries_errors():
    """``DemForward`` hands every block its entry's release errors: with the
    site's sds the runouts of a release below the shoulder's ground differ
    from block to block and from those of the exact release."""
    from calib.model.forward import DemForward

    exact = Entries.at_sizes([0.3677], SHOULDER_X_M, release_speed_m_s=0.39,
                             release_height_m=-0.5, density_kg_m3=2650.0)
    e = exact.concat(exact.with_release_errors(SITE.release_height_sd_m,
                                               SITE.release_speed_sd_m_s))
    r = DemForward(TSCHAMUT, e, 4, jax.random.key(2), form="constant").runouts_at_alpha(
        np.array([[0.5, 0.5]]))[0]
    assert np.all(np.isfinite(r)), r
    assert np.all(r[0] != r[1]) and len(set(r[1].tolist())) == 4, r


# ---------------------------------------------------------------- entries, site, files


def test_entries_carry_release_errors_only_where_a_release_is_tracked():
    e = Entries.at_sizes([0.3, 0.3, 0.3], 10.0, release_speed_m_s=[0.5, np.nan, 1.0],
                         release_height_m=[-0.4, 0.2, np.nan])
    assert np.all(e.release_height_sd_m == 0) and np.all(e.release_speed_sd_m_s == 0)
    w = e.with_release_errors(0.6, 0.3)
    np.testing.assert_array_equal(w.release_height_sd_m, [0.6, 0.6, 0.0])
    np.testing.assert_array_equal(w.release_speed_sd_m_s, [0.3, 0.0, 0.3])
    assert not w.same_as(e) and w.same_as(e.with_release_errors(0.6, 0.3))
    np.testing.assert_array_equal(w.take([2, 0]).release_height_sd_m, [0.0, 0.6])
    np.testing.assert_array_equal(w.concat(e).release_speed_sd_m_s, [0.3, 0, 0.3, 0, 0, 0])
    rec = w.record("p.csv")
    assert rec[0]["release_height_sd_m"] == 0.6 and rec[0]["release_height_m"] == -0.4
    with pytest.raises(ValueError, match="release_height_sd_m"):
        Entries.at_sizes([0.3], 10.0, release_height_m=0.5).with_release_errors(-0.1, 0.0)


def test_rows_below_the_ground_group_at_the_mean_of_their_measured_heights():
    """Heights as measured, negative included: rows within the tolerance share
    an entry at the mean of their raw heights (not of heights clipped at 0)."""
    obs = types.SimpleNamespace(
        block_size_m=np.ones(4), n_obs=4, release_x_m=np.array([10.0, 10.2, 10.4, 10.1]),
        release_height_m=np.array([-0.6, 0.2, -1.9, -0.3]), release_speed_m_s=None,
        profile=None)
    g = Entries.from_rows(obs, 0.0, tol_m=1.0)
    np.testing.assert_array_equal(g.index, [0, 0, 1, 0])
    np.testing.assert_allclose(g.release_height_m, [(-0.6 + 0.2 - 0.3) / 3, -1.9])


def test_site_file_gives_the_release_errors_with_their_sources(tmp_path):
    assert (SITE.release_height_sd_m, SITE.release_speed_sd_m_s) == (0.6, 0.3)
    assert "raster_height_error.py" in SITE.release_height_source
    assert "ASSUMPTION" in SITE.release_speed_source
    post = load_site("data/postignano_profile.csv")
    assert (post.release_height_sd_m, post.release_speed_sd_m_s) == (0.0, 0.0)
    for doc, needle in (
            ({"release_height_sd_m": -0.1, "release_height_source": "x"}, "release_height_sd_m"),
            ({"release_speed_sd_m_s": 0.3}, "'release_speed_source'"),
            ({"release_height_source": "x"}, "given without 'release_height_sd_m'"),
            ({"release_height_sd_m": "big", "release_height_source": "x"}, "finite number")):
        (tmp_path / "profile_site.json").write_text(json.dumps(doc))
        with pytest.raises(SiteError, match="profile_site.json") as e:
            load_site(str(tmp_path / "profile.csv"))
        assert needle in str(e.value)


def test_the_fit_inputs_carry_the_sites_errors(tmp_path):
    from calib.files.inputs import load_inputs

    inputs = load_inputs("data/tschamut2014/observations.csv", None, str(tmp_path / "out"))
    e = inputs.entries(1.0)
    assert np.all(e.release_height_sd_m == 0.6) and np.all(e.release_speed_sd_m_s == 0.3)
    assert np.all(inputs.entries(None).release_height_sd_m == 0.0)  # one default release


def test_validation_draws_releases_with_the_calibrations_errors(tmp_path):
    path = write_calibration(tmp_path, crsp=(0.41, 0.87, 2.0), dem=None)
    old = load_calibration(path, "crsp")
    assert (old.release_height_sd_m, old.release_speed_sd_m_s) == (0.0, 0.0)  # older files
    with open(path) as fh:
        doc = json.load(fh)
    doc.update(release_height_sd_m=0.6, release_speed_sd_m_s=0.3)
    with open(path, "w") as fh:
        json.dump(doc, fh)
    cal = load_calibration(path, "crsp")
    assert (cal.release_height_sd_m, cal.release_speed_sd_m_s) == (0.6, 0.3)
    b = Observations.points(np.ones(2), np.full(2, 50.0), 2.0)
    held = Observations(b.block_size_m, b.runout_m, b.runout_sd_m, b.runout_min_m,
                        b.runout_max_m, b.is_interval, b.source,
                        release_x_m=np.array([150.0, 160.0]),
                        release_height_m=np.array([-0.3, np.nan]),
                        release_speed_m_s=np.array([0.5, 0.5]))
    e = heldout_entries(cal, held, load_profile(cal.profile_csv))
    np.testing.assert_array_equal(e.release_height_sd_m, [0.6, 0.0])
    np.testing.assert_array_equal(e.release_speed_sd_m_s, [0.3, 0.3])


# ---------------------------------------------------------------- the stall flag


def _stall_case():
    """Three rows of one size: row 1 stalls (80 % of its runouts within 5 m)
    though it ran 35 m; row 2 stalls and was seen to (3 m); row 3 runs."""
    obs = Observations.points(np.ones(3), np.array([35.0, 3.0, 60.0]), 2.0)
    runs = np.empty((3, 100))
    runs[0, :80], runs[0, 80:] = 0.5, 60.0
    runs[1] = 1.0
    runs[2] = np.linspace(40.0, 80.0, 100)
    return obs, runs, np.arange(3)


def test_rows_that_stall_at_their_release_are_flagged_with_the_reason():
    obs, runs, idx = _stall_case()
    slope = np.array([25.0, 25.0, 40.0])
    phi = np.array([[20.0, 26.0, 30.0, 31.0]] * 3)  # 3 of 4 draws steeper than 25 deg
    rec = stalled_rows(obs, runs, idx, np.array([38.7, 38.7, 41.5]), slope, phi)
    assert [r["row"] for r in rec["rows"]] == [1]
    row = rec["rows"][0]
    assert row["fraction_within"] == 0.8 and row["rolling_above_slope"] == 0.75
    assert row["observed_m"] == 35.0 and row["release_slope_deg"] == 25.0
    msg = stall_message(rec)
    assert "row 1" in msg and "80%" in msg and "phi_r above it in 75% of the draws" in msg
    # exactly half within 5 m is flagged, less is not; unfinished blocks do not count
    half = runs.copy()
    half[0, :50], half[0, 50:] = 0.5, 60.0
    assert [r["row"] for r in stalled_rows(obs, half, idx)["rows"]] == [1]
    half[0, 49] = 60.0
    assert stalled_rows(obs, half, idx)["rows"] == []
    half[0, 50:] = np.nan
    assert [r["row"] for r in stalled_rows(obs, half, idx)["rows"]] == [1]
    # the fit's adequacy record flags it too, and says why
    a = adequacy_record(None, CRSP_BOX, obs, runs, "test", idx, np.full(3, 38.7), slope,
                        release_rolling_deg=phi)
    assert not a["ok"] and a["stalled_rows"]["rows"][0]["row"] == 1
    assert "stall at their release in the simulation" in a["message"]
    fine = adequacy_record(None, CRSP_BOX, obs, runs[[2, 1, 2]], "test", idx)
    assert fine["stalled_rows"]["rows"] == []


def test_validate_prints_and_records_stalled_rows(tmp_path, capsys):
    """Held-out rows released on the Postignano profile's 6 deg lower slope, where
    a block on the ground at the default 1 m/s stops at once (phi_r 30 deg): the
    one seen to run 50 m is flagged in validation.json and on stderr, with the
    fraction of draws whose phi_r exceeds the slope; the one released at the
    crest is not."""
    path = write_calibration(tmp_path, crsp=(0.41, 0.87, 2.0, 30.0), dem=None)
    held = tmp_path / "held.csv"
    held.write_text("block_size_m,runout_m,runout_sd_m,release_x_m\n1.0,50,2,200\n"
                    "1.0,150,5,0\n")
    out = tmp_path / "val"
    assert validate_main([path, str(held), "--n-posterior", "1", "--n-blocks", "16",
                          "--out", str(out)]) == 0
    s = json.loads((out / "validation.json").read_text())
    rows = s["stalled_rows"]["rows"]
    assert [r["row"] for r in rows] == [1] and rows[0]["rolling_above_slope"] == 1.0
    assert rows[0]["release_slope_deg"] == pytest.approx(np.degrees(np.arctan(19.97 / 190)))
    assert s["release_height_sd_m"] == 0.0
    err = capsys.readouterr().err
    assert "1 rows stall at their release" in err and "row 1:" in err
    print_summary(s, str(out))  # the summary alone prints it too
    assert "stall at their release" in capsys.readouterr().err


def test_rolling_angle_at_each_release_per_draw():
    e = Entries.at_sizes([0.3, 0.3], np.array([50.0, 120.0]))
    zoned = ("Kn", "Kt", "roughness_m", "rolling_friction_deg[steep]",
             "rolling_friction_deg[flat]")
    theta = np.array([[0.5, 0.9, 0.1, 33.0, 20.0], [0.5, 0.9, 0.1, 35.0, 22.0]])
    np.testing.assert_array_equal(release_rolling_deg(zoned, theta, TSCHAMUT, e),
                                  [[33.0, 35.0], [20.0, 22.0]])
    plain = release_rolling_deg(CRSP_BOX.names, theta[:, :3], TSCHAMUT, e)
    np.testing.assert_array_equal(plain, np.asarray(TSCHAMUT.rolling_friction_deg)[[0, 1]][
        :, None].repeat(2, 1))
    slopes = release_slopes_deg(TSCHAMUT, e.release_x_m)
    assert slopes[0] > 30 and slopes[1] < 10
