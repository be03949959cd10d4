"""With ``--row-shapes`` the fit simulates each observed row in its CRSP shape class
(the ``shape`` column, ``calib.files.observations``): the Tschamut plate is a disc of
the plate's mass, ``calibration.json`` records each release group's shape, the
predictive check simulates held-out rows the same way, and a hazard run given a
shape says whether the calibration's fit simulated it. Without it every row is a
sphere, and the fit says what the shape column held."""

from __future__ import annotations

import json

import jax
import numpy as np
import pandas as pd
import pytest
import xarray as xr
from cli_run import run_cli
from test_hazard_fixtures import posterior_rows, write_calibration

import calib  # noqa: F401  (x64)
from calib.files.calibration_file import fitted_block_shapes, load_calibration
from calib.files.inputs import load_inputs
from calib.hazard.__main__ import main as hazard
from calib.model.entries import Entries
from calib.model.forward import CrspForward
from solvers import crsp
from solvers.profile import load_profile

TSCHAMUT = "data/tschamut2014"


def test_each_field_run_is_simulated_in_its_shape(tmp_path):
    """Tschamut's 20 runs of the plate (block 4, ``disc``) are disc entries of the
    plate's mass, radius s d / 2 with s = 1.387 (the disc of the volume of the
    sphere of diameter d); its spheres keep radius d / 2. Each release group's
    record names its shape."""
    inputs = load_inputs(f"{TSCHAMUT}/observations.csv", None, str(tmp_path / "out"))
    spheres = inputs.entries(1.0)
    assert set(spheres.shapes) == {"sphere"}
    said = [x for x in inputs.grouping_lines(spheres, 1.0) if "shape column" in x]
    assert said and "20 disc" in said[0] and "--row-shapes" in said[0], said
    entries = inputs.entries(1.0, row_shapes=True)
    assert entries.n == spheres.n and np.array_equal(entries.index, spheres.index)
    rows = pd.read_csv(f"{TSCHAMUT}/observations.csv")
    assert list(entries.shapes[entries.index]) == list(rows["shape"])
    assert (rows["shape"] == "disc").sum() == 20
    s_disc = crsp.shape_constants("disc")[0]
    assert s_disc == pytest.approx(1.387, abs=1e-3)
    for e in range(entries.n):
        s = s_disc if entries.shapes[e] == "disc" else 1.0
        assert entries.crsp_radius_m[e] == pytest.approx(s * entries.sizes_m[e] / 2, rel=1e-14)
        block = crsp.make_block(float(entries.crsp_radius_m[e]), entries.shapes[e],
                                density_kg_m3=entries.density_kg_m3)
        assert float(block.mass_kg) == pytest.approx(entries.mass_kg[e], rel=1e-12)
        assert float(block.inertia_ratio) == (0.5 if entries.shapes[e] == "disc" else 0.4)
    said = [x for x in inputs.grouping_lines(entries, 1.0) if "shape class" in x]
    assert said and "42 rows sphere" in said[0] and "20 rows disc" in said[0], said
    record = entries.record("profile.csv")
    assert [g["shape"] for g in record] == list(entries.shapes)


def test_rows_of_one_size_and_release_but_two_shapes_are_two_entries():
    """Grouping keeps shapes apart: three rows of one size released at one point, one
    a sphere and one a disc (an empty shape is a sphere), are two entries."""
    obs = pd.DataFrame({"block_size_m": [0.5, 0.5, 0.5], "release_x_m": [10.0, 10.0, 10.0],
                        "shape": ["disc", "", "sphere"]})

    class Rows:
        n_obs = 3
        block_size_m = obs["block_size_m"].to_numpy()
        release_x_m = obs["release_x_m"].to_numpy()
        shape = obs["shape"].to_numpy(object)

    assert Entries.from_rows(Rows(), 0.0).n == 1  # without row_shapes: three spheres
    e = Entries.from_rows(Rows(), 0.0, row_shapes=True)
    assert e.n == 2
    assert list(e.shapes[e.index]) == ["disc", "sphere", "sphere"]
    with pytest.raises(ValueError, match="shapes: unknown block shape 'cube'"):
        Entries([0.5], 0.0, None, None, None, None, shapes=["cube"])


def test_the_forward_model_rolls_a_disc_on_its_own_radius():
    """Two entries of one 0.5 m block from one release, a sphere and a disc of the
    same mass: common random numbers, so the runouts differ only by the shape
    (radius and inertia), and they do differ; a sphere given as "" is the
    sphere."""
    profile = load_profile("data/postignano_profile.csv")
    theta = np.array([[0.35, 0.85, 1.0]])
    key = jax.random.key(3)
    e = Entries(np.array([0.5, 0.5, 0.5]), 0.0, None, None, None, None,
                shapes=["sphere", "disc", ""])
    runouts = CrspForward(profile, e, 16, key).simulate(theta)[0][0]
    print("mean runouts sphere, disc, sphere:", np.nanmean(runouts, axis=-1))
    assert np.all(np.isfinite(runouts))
    np.testing.assert_array_equal(runouts[0], runouts[2])
    assert not np.array_equal(runouts[0], runouts[1])


def test_a_hazard_run_says_whether_the_fit_simulated_its_shape(tmp_path, capsys):
    """A calibration whose release groups are spheres and discs: a hazard run of
    discs says every shape was fitted, one of cylinders that the fit never
    simulated them. A file without release groups simulated spheres."""
    groups = {"groups": [{"block_size_m": 0.5, "shape": "disc"},
                         {"block_size_m": 0.6, "shape": "sphere"}]}
    cal = write_calibration(tmp_path, crsp_posterior=posterior_rows(20), dem=None,
                            extra={"release_groups": groups})
    assert fitted_block_shapes(load_calibration(cal, "crsp")) == ("disc", "sphere")
    plain = write_calibration(tmp_path, dem=None, name="plain.json")
    assert fitted_block_shapes(load_calibration(plain, "crsp")) == ("sphere",)
    small = ["--n-posterior", "2", "--n-blocks", "8", "--block-sizes-m", "0.5", "--seed", "0"]
    for shape, said in (("disc", "the fit simulated disc, sphere: every shape here was fitted"),
                        ("cylinder", "the fit simulated disc, sphere only: cylinder "
                                     "extrapolates the calibration")):
        out = tmp_path / shape
        rc, _, err = run_cli(hazard, [cal, *small, "--block-shape", shape, "--out", str(out)],
                             capsys)
        assert rc == 0, err
        assert said in (out / "summary.txt").read_text()
        with xr.open_dataset(out / "hazard.nc", engine="h5netcdf") as ds:
            assert ds.attrs["fitted_block_shapes"] == "disc, sphere"
    with open(cal) as fh:
        doc = json.load(fh)
    assert doc["release_groups"]["groups"][0]["shape"] == "disc"


def test_validation_simulates_held_out_rows_as_the_fit_did(tmp_path):
    """A calibration that records ``row_shapes`` makes the predictive check simulate
    Tschamut's held-out plate runs as discs; one without it, as spheres."""
    from calib.files.observations import load_observations
    from calib.inference.predictive_check import heldout_entries

    profile = load_profile(f"{TSCHAMUT}/profile.csv")
    rows = load_observations(f"{TSCHAMUT}/observations.csv")
    for flag, want in ((True, {"disc", "sphere"}), (False, {"sphere"})):
        cal = write_calibration(tmp_path, dem=None, name=f"cal-{flag}.json",
                                extra={"row_shapes": flag, "rock_density_kg_m3": 2650.0})
        loaded = load_calibration(cal, "crsp")
        assert loaded.row_shapes is flag
        assert set(heldout_entries(loaded, rows, profile).shapes) == want


def test_row_shapes_without_crsp_is_refused(tmp_path, capsys):
    """--row-shapes with --model dem: one line, exit 2, nothing written."""
    from calib.fit import main as fit

    out = tmp_path / "out"
    rc, _, err = run_cli(fit, [f"{TSCHAMUT}/observations.csv", "--model", "dem",
                               "--row-shapes", "--out", str(out)], capsys)
    assert rc == 2
    assert "--row-shapes: shape classes are CRSP's" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    assert not out.exists()
