"""One rock density per site: the site file states it, the fit simulates its
blocks with it and records it, and the hazard run and the predictive check
simulate at the calibration's density or refuse a site that says otherwise."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

import calib  # noqa: F401  (x64)
from calib.files.calibration_file import CalibrationError, draw_parameters, load_calibration
from calib.files.inputs import load_inputs
from calib.files.site import load_site
from calib.hazard._run import _crsp_units
from calib.model.entries import Entries
from solvers import crsp
from solvers.material import ROCK_DENSITY_KG_M3
from solvers.profile import load_profile

TSCHAMUT = "data/tschamut2014"


def test_the_simulated_tschamut_block_weighs_what_the_rock_weighed(tmp_path):
    """calib.field sized the Tschamut blocks from their weighed masses at the
    site's 2650 kg/m^3; the entries the fit simulates, and the CRSP blocks made
    from them, have those masses (at the solvers' 2350 kg/m^3 they would be
    about 11 % lighter)."""
    inputs = load_inputs(f"{TSCHAMUT}/observations.csv", None, str(tmp_path / "out"))
    assert inputs.site.rock_density_kg_m3 == 2650.0
    entries = inputs.entries(1.0)
    measured = pd.read_csv(f"{TSCHAMUT}/observations.csv")["mass_kg"].to_numpy(float)
    simulated = entries.mass_kg[entries.index]
    # block_size_m is written with 4 decimals: a relative error of at most 3 x 0.5e-4 / 0.3
    np.testing.assert_allclose(simulated, measured, rtol=6e-4)
    for e in range(entries.n):  # discs (the plate) and spheres alike
        block = crsp.make_block(float(entries.crsp_radius_m[e]), entries.shapes[e],
                                density_kg_m3=entries.density_kg_m3)
        assert float(block.mass_kg) == pytest.approx(entries.mass_kg[e], rel=1e-12)
    at_default = ROCK_DENSITY_KG_M3 * np.pi * entries.sizes_m[entries.index]**3 / 6
    assert np.all(at_default / measured < 0.9)


def test_sites_without_a_density_use_the_solvers_default(tmp_path):
    assert load_site(str(tmp_path / "nowhere_profile.csv")).rock_density_kg_m3 == \
        ROCK_DENSITY_KG_M3
    assert load_site("data/postignano_profile.csv").rock_density_kg_m3 == 2350.0


def _calibration(folder, density=None) -> str:
    point = {"map": 0.41, "mean": None, "q05": None, "q95": None}
    doc = {"schema": "rockfall-calibration/1", "profile_csv": f"{TSCHAMUT}/profile.csv",
           "data_csv": f"{TSCHAMUT}/observations.csv", "seed": 0,
           "crsp": {"Kn": point, "Kt": dict(point, map=0.87),
                    "roughness_m": dict(point, map=0.2), "posterior_csv": None}}
    if density is not None:
        doc["rock_density_kg_m3"] = density
    path = folder / "calibration.json"
    path.write_text(json.dumps(doc))
    return str(path)


def test_the_hazard_run_simulates_at_the_calibrations_density(tmp_path):
    cal = load_calibration(_calibration(tmp_path, 2650.0))
    assert cal.rock_density_kg_m3 == 2650.0
    profile = load_profile(cal.profile_csv)
    sizes = np.array([0.3, 1.0])
    entries = Entries.at_sizes(sizes, 40.0, density_kg_m3=cal.rock_density_kg_m3)
    units = _crsp_units(draw_parameters(cal, 1, 0), profile, entries, np.array([80.0]), 2, 0,
                        2, [0], 64, crsp.Settings())
    (_, make_args, _), = list(units)
    blocks = make_args()[1]
    np.testing.assert_allclose(np.asarray(blocks.mass_kg), 2650.0 * np.pi * sizes**3 / 6,
                               rtol=1e-12)


def test_a_calibration_used_at_another_density_is_refused(tmp_path):
    """An older file (no density recorded) was fitted at the solvers' default; a
    site that states another density refuses it with one line."""
    old = load_calibration(_calibration(tmp_path))
    assert old.rock_density_kg_m3 == ROCK_DENSITY_KG_M3
    with pytest.raises(CalibrationError, match="fitted at a rock density of 2350 kg/m.3, but "
                                               "the site file .* gives 2650"):
        old.check_density(load_site(old.profile_csv).rock_density_kg_m3,
                          "the site file profile_site.json")
    load_calibration(_calibration(tmp_path, 2650.0)).check_density(2650.0, "the site")
