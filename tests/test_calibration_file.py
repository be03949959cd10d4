"""Every calibration ``calib.fit`` can write is one ``calib.hazard`` accepts, and
the hazard run simulates the parameters (DEM: the alpha per size) that the fit
simulated. Property test over each prior box: its corners and uniform draws
from it, written through the fit's own writers (``calib.files.fit_record.model_section``,
``calib.files.calibration_file.posterior_csv_text``), read back by
``load_calibration``, and taken through the hazard run's acceptance check and
the set-up of its work units (no simulation: seconds)."""

from __future__ import annotations

import itertools
import json
import os
from types import SimpleNamespace

import jax
import numpy as np
import pytest

from calib.files.calibration_file import (
    SCHEMA,
    CalibrationError,
    draw_parameters,
    load_calibration,
    posterior_csv_text,
)
from calib.files.fit_record import model_section
from calib.hazard._run import _crsp_units, _dem_units, check_dem_draws
from calib.model.dem_run import DEM_RUN, DemRun
from calib.model.entries import Entries
from calib.model.forward import CrspForward, DemForward
from calib.model.priors import CRSP_BOX, CRSP_ROLLING_BOX, DEM_BOXES
from solvers import crsp
from solvers.profile import load_profile

PROFILE_CSV = os.path.abspath("data/postignano_profile.csv")
# the hazard command's default sizes, and sizes the fit never sees (0.05 m: a
# power law with b = 1.5 is far above 1 there)
SIZES_M = np.array([0.05, 0.2, 0.5, 1.0, 2.0, 5.0])


def _box_points(box, n_random: int, seed: int) -> np.ndarray:
    """The 2^d corners of the box, then n_random uniform draws from it."""
    corners = np.array(list(itertools.product(*zip(box.lo, box.hi, strict=True))))
    z = np.random.default_rng(seed).uniform(size=(n_random, box.dim))
    return np.concatenate([corners, box.from_unit(z)])


def _write_fit(folder, model: str, box, estimate, samples, form=None) -> str:
    """calibration.json and the posterior CSV as ``calib.fit`` writes them, for a
    fit whose estimate and posterior draws are given."""
    post = SimpleNamespace(samples=samples, summary=lambda: {}, ok=True, problems=[], criteria={},
                           divergences=0, accept_prob=0.9, n_chains=1)
    fit = SimpleNamespace(names=box.names, estimate=np.asarray(estimate, float),
                          estimate_source="posterior_mode", posterior=post, gradient=None,
                          quality=[], unfinished=None, adequacy=None, timings_s={},
                          budget=SimpleNamespace(), check_runouts=np.zeros((1, 1)),
                          emulator_check=None, focus=None, chain_screen=None,
                          estimate_choice=None)
    run = DemRun(stiffness_scale=0.02, max_time_s=140.0)  # not the defaults: must travel
    sec = model_section(model, fit, SimpleNamespace(box=box, run=run), form)
    doc = {"schema": SCHEMA, "profile_csv": PROFILE_CSV, "release_x_m": 0.0, model: sec}
    with open(os.path.join(folder, f"{model}_posterior.csv"), "w") as fh:
        fh.write(posterior_csv_text(box.names, samples))
    path = os.path.join(folder, "calibration.json")
    with open(path, "w") as fh:
        json.dump(doc, fh, allow_nan=False)
    return path


def _drawn(cal):
    """The draws of a hazard run: every posterior row, and the point estimate."""
    return draw_parameters(cal, cal.posterior.shape[0], 0), draw_parameters(cal, 1, 0)


@pytest.mark.parametrize("form", ["power", "constant"])
def test_every_dem_calibration_the_fit_can_write_is_accepted_by_hazard(tmp_path, form):
    """DEM: for each corner of the prior box as the estimate and the box (corners
    + 64 uniform draws) as the posterior, the hazard run accepts every draw at
    every size, and the alpha of each block it would simulate equals the alpha
    the fit's forward model runs for that draw and size."""
    box = DEM_BOXES[form]
    samples = _box_points(box, 64, seed=1)
    profile = load_profile(PROFILE_CSV)
    fit_forward = DemForward(profile, SIZES_M, 1, jax.random.key(0), form=form)
    stations = np.array([50.0, 150.0])
    for k, estimate in enumerate(_box_points(box, 0, seed=0)):
        folder = tmp_path / f"{form}{k}"
        folder.mkdir()
        cal = load_calibration(_write_fit(str(folder), "dem", box, estimate, samples, form),
                               "dem")
        assert cal.alpha_form == form
        for draws in _drawn(cal):
            check_dem_draws(cal, draws, SIZES_M)  # raises if refused
            units = _dem_units(cal, draws, profile, Entries.at_sizes(SIZES_M, 0.0), stations,
                               2, 0, 2, [0], DEM_RUN)
            ran = np.full((len(draws.values), len(SIZES_M)), np.nan)
            for (d, t_sl), make_args, _ in units:
                ran[d, t_sl] = np.asarray(make_args()[1].alpha)[0]
            np.testing.assert_allclose(ran, fit_forward.alphas(draws.values), rtol=1e-12)
        # the values the fit held (before the CSV's 8 digits) give the same alphas
        np.testing.assert_allclose(fit_forward.alphas(samples),
                                   fit_forward.alphas(cal.posterior), rtol=1e-7)


@pytest.mark.parametrize("box", [CRSP_BOX, CRSP_ROLLING_BOX], ids=["3", "rolling"])
def test_every_crsp_calibration_the_fit_can_write_is_accepted_by_hazard(tmp_path, box):
    """CRSP: the same property for both prior boxes; the hazard run's parameters
    (every zone) are the ones the fit's forward model runs for the draw."""
    samples = _box_points(box, 32, seed=2)
    profile = load_profile(PROFILE_CSV)
    fit_forward = CrspForward(profile, SIZES_M, 1, jax.random.key(0), box=box)
    stations = np.array([50.0, 150.0])
    for k, estimate in enumerate(_box_points(box, 0, seed=0)[[0, -1]]):
        folder = tmp_path / f"crsp{k}"
        folder.mkdir()
        cal = load_calibration(_write_fit(str(folder), "crsp", box, estimate, samples), "crsp")
        assert cal.names == box.names
        for draws in _drawn(cal):
            units = _crsp_units(draws, profile, Entries.at_sizes(SIZES_M, 0.0), stations, 2, 0, 2,
                                [0], 64,
                                crsp.Settings())
            want = fit_forward.params(draws.values)
            for (d, _), make_args, _ in units:
                params = make_args()[0]
                for name in box.names:
                    got = np.asarray(getattr(params, name))[0]
                    np.testing.assert_allclose(got, np.asarray(getattr(want, name))[d],
                                               rtol=1e-12, err_msg=name)


def test_the_fit_checks_its_dem_draws_before_writing():
    """``calib.fit`` runs the hazard's acceptance check on what it would write:
    the box passes; a draw the hazard would refuse stops the fit, named."""
    from calib.model.alpha_law import check_fit

    box = DEM_BOXES["power"]
    good = _box_points(box, 16, seed=3)
    check_fit("power", good[0], good, np.array([0.2, 2.0]))
    bad = good.copy()
    bad[5, 0] = 0.0
    with pytest.raises(ValueError, match=r"posterior draw 6 would be refused .*a = 0"):
        check_fit("power", good[0], bad, np.array([0.2, 2.0]))


def test_calibration_file_round_trips_and_is_the_one_reader(tmp_path):
    """CalibrationFile: to_json then from_json gives the same document; the reader
    refuses another schema version and a bad model section (as hazard would),
    and hands out each model's Calibration."""
    from test_hazard_fixtures import write_calibration

    from calib.files.calibration_file import SCHEMA, CalibrationError, CalibrationFile

    path = write_calibration(tmp_path, crsp_posterior=None)
    doc = CalibrationFile.from_json(path)
    assert doc.schema == SCHEMA and set(doc.models) == {"crsp", "dem"}
    again = tmp_path / "again.json"
    again.write_text(doc.to_json())
    assert CalibrationFile.from_json(str(again)).doc == doc.doc
    assert doc.calibration("crsp").names[:3] == ("Kn", "Kt", "roughness_m")
    bad = dict(doc.doc, schema="rockfall-calibration/0")
    with pytest.raises(CalibrationError, match="schema"):
        CalibrationFile.from_dict(bad)
    broken = dict(doc.doc)
    broken["crsp"] = dict(broken["crsp"], Kn={"map": 1.5})
    (tmp_path / "broken.json").write_text(CalibrationFile.from_dict(broken).to_json())
    with pytest.raises(CalibrationError, match="crsp.Kn"):
        CalibrationFile.from_json(str(tmp_path / "broken.json"))


def test_the_fit_dem_numerics_travel_to_the_hazard_run(tmp_path):
    """The DEM section records the fit's numerics (calib.model.dem_run); the reader hands
    them to the hazard run, which builds the same DemRun from them."""
    box = DEM_BOXES["power"]
    pts = _box_points(box, 4, seed=1)
    cal = load_calibration(_write_fit(tmp_path, "dem", box, pts[0], pts, "power"), "dem")
    assert DemRun(**cal.dem_run) == DemRun(stiffness_scale=0.02, max_time_s=140.0)


@pytest.mark.parametrize("key, value, message", [
    ("stiffness_scale", 0.0, "dem.run.stiffness_scale': expected a value in \\(0, 1\\], got 0"),
    ("stiffness_scale", 1.5, "dem.run.stiffness_scale': expected a value in \\(0, 1\\]"),
    ("max_time_s", -5.0, "dem.run.max_time_s': expected a positive time, got -5"),
    ("dt_size_m", 0.0, "dem.run.dt_size_m': expected a positive size"),
    ("max_time_s", "long", "dem.run.max_time_s': expected a number"),
])
def test_a_calibration_with_bad_dem_numerics_is_refused(tmp_path, key, value, message):
    """The reader checks the DEM run's numerics with the solver's one check
    (``solvers.dem.check_run_numerics``), naming the file and the key."""
    box = DEM_BOXES["power"]
    pts = _box_points(box, 4, seed=1)
    path = _write_fit(tmp_path, "dem", box, pts[0], pts, "power")
    with open(path) as fh:
        doc = json.load(fh)
    doc["dem"]["run"][key] = value
    with open(path, "w") as fh:
        json.dump(doc, fh)
    with pytest.raises(CalibrationError, match=message):
        load_calibration(path, "dem")


def test_summary_reads_each_model_section_typed(tmp_path):
    """CalibrationFile.summary: each parameter's map/mean/q05/q95 as written, the
    prior box, the diagnostics and (DEM) alpha(L) with the published values,
    keyed by the side in metres; a model the file lacks is refused."""
    from calib.files.calibration_file import CalibrationError, CalibrationFile

    box = CRSP_ROLLING_BOX
    samples = _box_points(box, 40, 0)
    est = samples.mean(axis=0)
    with open(_write_fit(str(tmp_path), "crsp", box, est, samples)) as fh:
        doc = json.load(fh)
    doc.update(data_csv="rows.csv", seed=0)
    s = CalibrationFile.from_dict(doc, str(tmp_path / "calibration.json")).summary("crsp")
    assert tuple(s.parameters) == tuple(box.names)
    kn = s.parameters["Kn"]
    assert kn.map == est[0] and kn.q05 == pytest.approx(np.quantile(samples[:, 0], 0.05))
    assert kn.mean == pytest.approx(samples[:, 0].mean())
    assert s.prior["Kn"] == (float(box.lo[0]), float(box.hi[0]))
    assert s.diagnostics_ok is True and s.problems == () and s.alpha_form == ""
    assert s.alpha_at_L == {} and s.alpha_reference == {}

    dbox = DEM_BOXES["power"]
    dsamples = _box_points(dbox, 10, 1)
    with open(_write_fit(str(tmp_path), "dem", dbox, dsamples[0], dsamples, "power")) as fh:
        ddoc = json.load(fh)
    ddoc.update(data_csv="rows.csv", seed=0)
    ddoc["dem"]["alpha_at_L"] = {"0.2": {"map": 0.8, "mean": 0.7, "q05": 0.6, "q95": 0.9,
                                         "reference": 0.9}}
    d = CalibrationFile.from_dict(ddoc).summary("dem")
    assert d.alpha_form == "power" and tuple(d.parameters) == ("a", "b")
    assert d.parameters["a"].map == dsamples[0][0]
    assert d.alpha_at_L[0.2].q95 == 0.9 and d.alpha_reference == {0.2: 0.9}
    with pytest.raises(CalibrationError, match="no 'crsp' section"):
        CalibrationFile.from_dict(ddoc).summary("crsp")
