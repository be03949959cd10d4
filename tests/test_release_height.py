"""Field runs released from above the ground: ``release_height_m``
from the rows to the CRSP forward model, the fit's release groups and the
predictive check."""

from __future__ import annotations

import json
import types

import jax
import numpy as np
import pytest

import calib  # noqa: F401  (x64)
from calib.files.observations import Observations
from calib.model.entries import Entries
from calib.model.forward import CrspForward
from calib.model.priors import CRSP_ROLLING_BOX
from solvers.profile import load_profile

TSCHAMUT = load_profile("data/tschamut2014/profile.csv")
# a restitution and rolling resistance near the shipped fit's old single-release
# point; x = 38.7 m lies on the profile's 25 deg shoulder, x = 41.5 m on the
# 44 deg slope below it
THETA = np.array([[0.596, 0.958, 0.104, 30.7]])
HEIGHTS_M = (np.nan, 0.0, 1e-6, 1.5)


def _runouts(release_x_m: float, speed_m_s: float) -> np.ndarray:
    n = len(HEIGHTS_M)
    entries = Entries.at_sizes(np.full(n, 0.3677), release_x_m, release_speed_m_s=speed_m_s,
                               release_height_m=HEIGHTS_M)
    fw = CrspForward(TSCHAMUT, entries, 200, jax.random.key(3), box=CRSP_ROLLING_BOX)
    return fw.runouts(THETA)[0]  # (heights, blocks)


def test_each_entry_is_released_from_its_height():
    """NaN is the solver's default (on the ground): the same blocks as 0 m. A
    block released 1.5 m above the shoulder, where phi_r (30.7 deg) exceeds the
    slope and every block released slowly on the ground stalls within 1 m, falls
    onto it and runs on. As the height goes to 0 the runout goes to that of a
    release on the ground (1e-6 m, on the 44 deg slope: medians within 1 m)."""
    shoulder, steep = _runouts(38.7, 0.39), _runouts(41.5, 0.8)
    for r in (shoulder, steep):
        np.testing.assert_array_equal(r[0], r[1])
    stalled = (shoulder < 1.0).mean(axis=1)
    print("stalled fraction on the shoulder, by height:", dict(zip(HEIGHTS_M, stalled)))
    print("medians on the steep slope:", np.median(steep, axis=1))
    assert stalled[1] == 1.0 and stalled[3] < 0.1, stalled
    assert abs(np.median(steep[2]) - np.median(steep[1])) < 1.0


def test_release_groups_split_releases_of_different_heights():
    """Rows share a group when both their abscissae and their heights lie within
    the tolerance of the group's first row (rows without a height only with each
    other), released at the means: two spots that project onto the same abscissa
    (0 m and 2.4 m above the ground, as at Tschamut) are two releases."""
    obs = types.SimpleNamespace(
        block_size_m=np.ones(6), n_obs=6,
        release_x_m=np.array([10.0, 10.5, 10.2, 40.0, 10.3, 10.1]),
        release_height_m=np.array([1.2, np.nan, 2.0, np.nan, 2.4, 0.0]))
    g = Entries.from_rows(obs, 0.0, tol_m=1.0)
    np.testing.assert_array_equal(g.index, [0, 3, 0, 4, 2, 1])
    np.testing.assert_allclose(g.release_x_m, [10.1, 10.1, 10.3, 10.5, 40.0])
    np.testing.assert_allclose(g.release_height_m, [1.6, 0.0, 2.4, np.nan, np.nan])


def test_an_older_crsp_calibration_refuses_held_out_rows_with_heights(tmp_path):
    """A CRSP fit whose release groups record no heights released its rows on the
    ground: held-out rows that give heights are refused with a line that says to
    refit; a fit that records them releases held-out rows from their heights."""
    from test_hazard_fixtures import write_calibration

    from calib.files.calibration_file import load_calibration
    from calib.inference.predictive_check import predictive_runouts

    postignano = load_profile("data/postignano_profile.csv")
    path = write_calibration(tmp_path, crsp=(0.41, 0.87, 2.0), dem=None)
    with open(path) as fh:
        doc = json.load(fh)
    group = {"block_size_m": 1.0, "release_x_m": 0.0, "release_speed_m_s": None,
             "n_rows": 1}
    old = dict(doc, release_groups={"tolerance_m": 1.0, "models": ["crsp"],
                                    "groups": [group]})
    new = dict(doc, release_groups={"tolerance_m": 1.0, "models": ["crsp"],
                                    "groups": [dict(group, release_height_m=None)]})
    for name, d in (("old.json", old), ("new.json", new)):
        with open(tmp_path / name, "w") as fh:
            json.dump(d, fh)
    held = Observations.points(np.array([1.0]), np.array([20.0]), 2.0)
    held = Observations(held.block_size_m, held.runout_m, held.runout_sd_m, held.runout_min_m,
                        held.runout_max_m, held.is_interval, held.source,
                        release_x_m=np.array([150.0]), release_height_m=np.array([1.0]))
    cal_old = load_calibration(str(tmp_path / "old.json"), "crsp")
    cal_new = load_calibration(str(tmp_path / "new.json"), "crsp")
    assert not cal_old.release_heights and cal_new.release_heights
    with pytest.raises(ValueError, match="refit"):
        predictive_runouts(cal_old, held, postignano, 1, 4, 0)
    runs, index, _, _ = predictive_runouts(cal_new, held, postignano, 1, 4, 0)
    assert runs.shape == (1, 4) and np.all(np.isfinite(runs))


def test_a_dem_calibration_says_whether_it_released_rows_from_their_heights(tmp_path):
    """A DEM fit listed in ``release_groups.speed_and_height_models`` released its
    groups from their rows' heights and speeds, and validate does the same for
    held-out rows; a DEM fit of an older file (not listed) released them by the
    DEM's own rule, and held-out rows with heights are refused with a line that
    says to refit."""
    from test_hazard_fixtures import write_calibration

    from calib.files.calibration_file import load_calibration
    from calib.inference.predictive_check import predictive_runouts

    postignano = load_profile("data/postignano_profile.csv")
    path = write_calibration(tmp_path, crsp=(0.41, 0.87, 2.0), dem=(0.40, 0.5))
    with open(path) as fh:
        doc = json.load(fh)
    groups = {"tolerance_m": 1.0, "models": ["dem"]}
    old = dict(doc, release_groups=groups)
    new = dict(doc, release_groups=dict(groups, speed_and_height_models=["dem"]))
    for name, d in (("old.json", old), ("new.json", new)):
        with open(tmp_path / name, "w") as fh:
            json.dump(d, fh)
    cal_old = load_calibration(str(tmp_path / "old.json"), "dem")
    cal_new = load_calibration(str(tmp_path / "new.json"), "dem")
    assert not cal_old.release_heights and cal_new.release_heights
    held = Observations.points(np.array([1.0]), np.array([20.0]), 2.0)
    held = Observations(held.block_size_m, held.runout_m, held.runout_sd_m, held.runout_min_m,
                        held.runout_max_m, held.is_interval, held.source,
                        release_x_m=np.array([150.0]), release_height_m=np.array([3.0]),
                        release_speed_m_s=np.array([4.0]))
    with pytest.raises(ValueError, match="refit"):
        predictive_runouts(cal_old, held, postignano, 1, 1, 0)
    runs, _, _, _ = predictive_runouts(cal_new, held, postignano, 1, 1, 0)
    assert runs.shape == (1, 1) and np.all(np.isfinite(runs))
