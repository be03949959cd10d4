"""The rolling resistance as a fourth CRSP parameter: the forward model,
the calibration file and the hazard run all read it by name."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from test_hazard_fixtures import write_calibration

from calib.files.calibration_file import load_calibration
from calib.hazard import draw_parameters, run_hazard
from calib.model.forward import CrspForward
from calib.model.priors import CRSP_BOX, CRSP_ROLLING_BOX
from solvers.profile import load_profile

PROFILE = load_profile("data/postignano_profile.csv")  # every zone: 30 deg


def test_fourth_parameter_at_the_profile_value_changes_nothing_and_orders_runouts():
    key = jax.random.key(4)
    sizes = np.array([0.5, 2.0])
    three = CrspForward(PROFILE, sizes, 64, key, box=CRSP_BOX)
    four = CrspForward(PROFILE, sizes, 64, key, box=CRSP_ROLLING_BOX)
    assert four.n_rolling == 1 and three.n_rolling == 0
    np.testing.assert_array_equal(four.runouts([[0.41, 0.87, 1.0, 30.0]]),
                                  three.runouts([[0.41, 0.87, 1.0]]))
    r = four.runouts([[0.41, 0.87, 1.0, 10.0], [0.41, 0.87, 1.0, 40.0]])
    assert np.all(np.nanmedian(r[0], axis=-1) > np.nanmedian(r[1], axis=-1))
    assert four.input_box.dim == 4 and four.input_box.names[3] == "tan(phi_r)"


@pytest.mark.slow  # 14 s
def test_hazard_reads_a_fitted_rolling_angle(tmp_path):
    """A calibration with rolling_friction_deg: the reader returns four names and the
    hazard run uses the angle: on smooth ground (S = 0.25 m, where rolling matters)
    2 m blocks pass 200 m at 10 deg and not at 40 deg (measured: 19 and 0 of 256)."""
    reach = []
    for phi in (10.0, 40.0):
        folder = tmp_path / f"phi{phi:g}"
        folder.mkdir()
        path = write_calibration(folder, crsp=(0.41, 0.87, 0.25, phi))
        cal = load_calibration(path, "crsp")
        assert cal.names == ("Kn", "Kt", "roughness_m", "rolling_friction_deg")
        counts = run_hazard(cal, draw_parameters(cal, 1, 0), PROFILE, [2.0],
                            np.array([200.0]), 256, 0)
        reach.append(float(np.asarray(counts.reach).ravel()[0]))
    assert reach[0] > 0 and reach[1] == 0, reach


def test_hazard_releases_where_the_calibration_was_fitted(tmp_path):
    """calib.fit records the release it simulated (release_x_m); the hazard run
    starts its blocks there: released at 150 m, no block passes a station at
    100 m (upslope), and the release is what the tables are measured from."""
    import json

    path = write_calibration(tmp_path, crsp=(0.41, 0.87, 2.0))
    import pathlib

    doc = json.loads(pathlib.Path(path).read_text())
    doc["release_x_m"] = 150.0
    pathlib.Path(path).write_text(json.dumps(doc))
    cal = load_calibration(path, "crsp")
    assert cal.release_x_m == 150.0
    # one size, three stations, 64 blocks: the compiled program of the hazard runs of
    # test_zoned_rolling.py and test_design_angles.py
    counts = run_hazard(cal, draw_parameters(cal, 1, 0), PROFILE, [1.0],
                        np.array([100.0, 155.0, 230.0]), 64, 0)
    assert counts.release_x_m == 150.0
    assert int(np.asarray(counts.reach)[0, 0, 0]) == 0


def test_emulator_coordinates_invert():
    """``from_input`` undoes ``to_input`` over the whole box, with and without
    the rolling resistance (the design's points go back to theta for the
    adequacy check of a better design point)."""
    rng = np.random.default_rng(0)
    for box in (CRSP_BOX, CRSP_ROLLING_BOX):
        fw = CrspForward(PROFILE, np.array([0.4]), 4, jax.random.key(0), box=box)
        theta = box.from_unit(rng.random((64, box.dim)))
        np.testing.assert_allclose(fw.from_input(fw.to_input(theta)), theta, rtol=1e-12)


def test_no_block_rests_on_a_profile_steeper_than_its_rolling_resistance():
    """Postignano's profile falls at 6.0 deg or more everywhere (its lowest zone,
    110-300 m): with a rolling resistance angle just below that no block comes to
    rest on it, every block runs to the profile's end; just above, blocks of
    every size come to rest on it (64 blocks of 0.2 and 2 m)."""
    from calib.model.priors import flattest_slope_deg

    floor = flattest_slope_deg(PROFILE)
    assert floor == pytest.approx(6.0, abs=1e-3)
    four = CrspForward(PROFILE, np.array([0.2, 2.0]), 64, jax.random.key(5),
                       box=CRSP_ROLLING_BOX)
    below, above = (four.runouts([[0.45, 0.90, 0.3, floor + d]])[0] for d in (-0.1, 0.5))
    end = float(PROFILE.x_m[-1])
    np.testing.assert_array_equal(below, end)
    assert np.all(np.min(above, axis=-1) < end - 100.0)


def test_the_rolling_prior_starts_where_a_block_can_rest():
    """``rest_possible_box`` raises the one rolling angle's lower bound to the
    flattest slope of the profiles (the largest of their minima), and leaves
    alone boxes without that angle, zoned angles and profiles with a flatter
    stretch than the published 5 deg."""
    from calib.model.priors import NoRestError, rest_possible_box, zoned_rolling_box
    from solvers.profile import make_profile, refine

    tschamut = load_profile("data/tschamut2014/profile.csv")  # flat beyond ~65 m
    box = rest_possible_box(CRSP_ROLLING_BOX, [PROFILE])
    assert box.names == CRSP_ROLLING_BOX.names and box.upper == CRSP_ROLLING_BOX.upper
    assert box.lower[:3] == CRSP_ROLLING_BOX.lower[:3]
    assert box.lower[3] == pytest.approx(6.0, abs=1e-3)
    assert rest_possible_box(CRSP_ROLLING_BOX, [PROFILE, tschamut]) == box
    # collinear vertices every 7 m change no slope, so not the bound
    assert rest_possible_box(CRSP_ROLLING_BOX, [refine(PROFILE, 7.0)]) == box
    assert rest_possible_box(CRSP_ROLLING_BOX, [tschamut]) == CRSP_ROLLING_BOX
    assert rest_possible_box(CRSP_BOX, [PROFILE]) == CRSP_BOX
    zoned = zoned_rolling_box(PROFILE.zone_names)
    assert rest_possible_box(zoned, [PROFILE]) == zoned
    wall = make_profile([0.0, 10.0, 20.0], [30.0, 15.0, 0.0], ["rock", "rock"],
                        {"rock": {"Kn": 0.4, "Kt": 0.9, "roughness_m": 0.5,
                                  "rolling_friction_deg": 30.0, "phi_deg": 30.0}})
    with pytest.raises(NoRestError, match="56.3 deg"):
        rest_possible_box(CRSP_ROLLING_BOX, [wall])


def test_discovery_candidates_start_the_rolling_prior_where_calib_fit_does():
    """``calib.discover --rolling-resistance fit``: the baseline and the effects
    that leave the rolling resistance alone start phi_r at the profile's
    flattest slope, as the fit does; the forest belt, which lets blocks rest in
    it, keeps the published 5 deg."""
    from calib.discovery.candidates import candidate_set

    cands, combine = candidate_set("crsp", ["none", "size_dissipation", "vegetation_belt"],
                                   PROFILE, rolling="fit")
    lower = {c.effect: c.box.lower[c.box.names.index("rolling_friction_deg")] for c in cands}
    assert lower["none"] == pytest.approx(6.0, abs=1e-3)
    assert lower["size_dissipation"] == lower["none"]
    assert lower["vegetation_belt"] == 5.0
    both = combine(["size_dissipation", "vegetation_belt"])
    assert both.box.lower[both.box.names.index("rolling_friction_deg")] == 5.0
