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
