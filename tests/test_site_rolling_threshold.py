"""A site's CRSP rolling threshold: the site file states it with its source,
the fit simulates with it and records it in ``calibration.json``, and the
predictive check, the discrepancy workflow, the hazard run and the design
simulate the calibration's value (older files: the solver's default)."""

from __future__ import annotations

import json
import os
import pathlib

import jax
import numpy as np
import pytest
from test_hazard_fixtures import write_calibration

import calib  # noqa: F401  (x64)
import solvers.crsp as crsp
from calib.files.calibration_file import CalibrationError, draw_parameters, load_calibration
from calib.files.inputs import load_inputs
from calib.files.observations import Observations
from calib.files.site import SiteError, load_site
from calib.inference.predictive_check import predictive_runouts
from calib.model.entries import Entries
from calib.model.forward import CrspForward
from calib.model.priors import CRSP_ROLLING_BOX
from solvers.profile import load_profile

TSCHAMUT = "data/tschamut2014/profile.csv"
# a 0.37 m block released on the ground at 0.39 m/s on the Tschamut line's
# 25 deg shoulder, rolling resistance 30.7 deg (tests/test_release_uncertainty.py)
SHOULDER_X_M, THETA = 38.7, np.array([[0.596, 0.958, 0.104, 30.7]])


def _shoulder(threshold_m_s: float) -> np.ndarray:
    e = Entries.at_sizes([0.3677], SHOULDER_X_M, release_speed_m_s=0.39, release_height_m=0.0,
                         density_kg_m3=2650.0)
    return CrspForward(load_profile(TSCHAMUT), e, 200, jax.random.key(3), box=CRSP_ROLLING_BOX,
                       rolling_threshold_m_s=threshold_m_s).runouts(THETA)[0, 0]


def test_the_threshold_decides_whether_a_slow_release_on_the_ground_starts():
    """At the solver's 0.5 m/s the release's normal speed (about 0.17 m/s) keeps
    the block on the ground, where phi_r exceeds the slope: every block stalls
    within a metre. At the site's 0.05 m/s it leaves the ground and runs on,
    and halving the threshold again moves no block by more than a centimetre
    (measured: 2 mm at most): the value is converged here."""
    default, site, half = _shoulder(0.5), _shoulder(0.05), _shoulder(0.025)
    assert np.mean(default < 1.0) == 1.0
    assert np.mean(site < 1.0) == 0.0 and np.nanmedian(site) > 100.0
    np.testing.assert_allclose(site, half, rtol=0, atol=0.01)


def test_the_site_file_gives_the_threshold_with_its_source(tmp_path):
    tsch = load_site(TSCHAMUT)
    assert tsch.rolling_threshold_m_s == 0.05 and "loglik_noise.py" in \
        tsch.rolling_threshold_source
    assert load_site("data/postignano_profile.csv").rolling_threshold_m_s == \
        crsp.ROLLING_THRESHOLD_M_S
    for doc, needle in (({"rolling_threshold_m_s": 0.05}, "'rolling_threshold_source'"),
                        ({"rolling_threshold_source": "x"}, "given without"),
                        ({"rolling_threshold_m_s": 0.0, "rolling_threshold_source": "x"},
                         "'rolling_threshold_m_s'"),
                        ({"rolling_threshold_m_s": "low", "rolling_threshold_source": "x"},
                         "finite number")):
        (tmp_path / "profile_site.json").write_text(json.dumps(doc))
        with pytest.raises(SiteError, match="profile_site.json") as e:
            load_site(str(tmp_path / "profile.csv"))
        assert needle in str(e.value)


def test_the_fit_simulates_with_the_sites_threshold_and_records_it(tmp_path, monkeypatch):
    """``fit_model`` builds its CRSP forward model with the site's threshold
    (the fit itself is not run here), and the calibration file records it."""
    import calib.inference.calibrate as calibrate
    from calib.files.fit_record import FitOptions, fit_document

    inputs = load_inputs("data/tschamut2014/observations.csv", None, str(tmp_path / "out"))
    seen = []

    def capture(forward, *args, **kwargs):
        seen.append(forward.rolling_threshold_m_s)
        raise KeyboardInterrupt  # stop before fitting

    monkeypatch.setattr(calibrate, "calibrate", capture)
    with pytest.raises(KeyboardInterrupt):
        calibrate.fit_model("crsp", inputs, inputs.entries(1.0), jax.random.key(0), quick=True)
    assert seen == [0.05]
    options = FitOptions({"command": "test", "seed": 0, "versions": {}, "inputs": {}},
                         "observations.csv", True, ("bayes",), True, 1.0)
    doc = fit_document(options, inputs, inputs.entries(1.0), {}, 0.0).doc
    assert doc["rolling_threshold_m_s"] == 0.05
    assert "loglik_noise.py" in doc["rolling_threshold_source"]


def test_calibration_files_carry_the_threshold_and_older_ones_the_default(tmp_path):
    path = write_calibration(tmp_path, crsp=(0.41, 0.87, 2.0), dem=None)
    assert load_calibration(path, "crsp").rolling_threshold_m_s == crsp.ROLLING_THRESHOLD_M_S
    doc = json.loads(pathlib.Path(path).read_text())
    for bad in (0.0, -1.0, 50.0, "x"):
        doc["rolling_threshold_m_s"] = bad
        with open(path, "w") as fh:
            json.dump(doc, fh)
        with pytest.raises(CalibrationError, match="rolling_threshold_m_s"):
            load_calibration(path, "crsp")
    doc["rolling_threshold_m_s"] = 0.05
    with open(path, "w") as fh:
        json.dump(doc, fh)
    assert load_calibration(path, "crsp").rolling_threshold_m_s == 0.05


def test_site_and_calibration_files_take_the_same_thresholds(tmp_path):
    """One range (``solvers.crsp.ROLLING_THRESHOLD_RANGE_M_S``) for both files:
    a calibration file holds the threshold its site stated, so a value one
    reader refuses the other refuses too, and its ends are taken by both."""
    lo, hi = crsp.ROLLING_THRESHOLD_RANGE_M_S
    (tmp_path / "site").mkdir()
    site_json = tmp_path / "site" / "profile_site.json"
    path = write_calibration(tmp_path, crsp=(0.41, 0.87, 2.0), dem=None)
    doc = json.loads(pathlib.Path(path).read_text())
    for value in (lo / 2, lo, 0.05, hi, hi * 1.01):
        site_json.write_text(json.dumps({"rolling_threshold_m_s": value,
                                         "rolling_threshold_source": "test"}))
        doc["rolling_threshold_m_s"] = value
        pathlib.Path(path).write_text(json.dumps(doc))
        taken = []
        for load, error in ((lambda: load_site(str(tmp_path / "site" / "profile.csv")),
                             SiteError),
                            (lambda: load_calibration(path, "crsp"), CalibrationError)):
            try:
                taken.append(load().rolling_threshold_m_s == value)
            except error:
                taken.append(False)
        assert taken == [lo <= value <= hi] * 2, (value, taken)


def _tschamut_calibration(folder, threshold=None) -> str:
    """A CRSP calibration on the Tschamut line at ``THETA`` whose fit released
    its rows at their tracked heights and speeds, with ``threshold`` (None: a
    file without the key)."""
    extra = {"rock_density_kg_m3": 2650.0,
             "release_groups": {"tolerance_m": 1.0, "models": ["crsp"],
                                "groups": [{"release_height_m": 0.0}]}}
    if threshold is not None:
        extra["rolling_threshold_m_s"] = threshold
    return write_calibration(folder, crsp=tuple(THETA[0]), dem=None,
                             profile=os.path.abspath(TSCHAMUT), extra=extra)


def test_the_predictive_check_simulates_with_the_calibrations_threshold(tmp_path):
    """The same held-out row (released on the shoulder's ground at 0.39 m/s)
    under two calibrations that differ only in their threshold: the file's
    value reaches the simulation."""
    held = Observations(np.array([0.3677]), np.array([100.0]), np.array([2.0]),
                        np.array([np.nan]), np.array([np.nan]), np.array([False]),
                        np.array(["test"]), release_x_m=np.array([SHOULDER_X_M]),
                        release_height_m=np.array([0.0]), release_speed_m_s=np.array([0.39]))
    out = {}
    for thr in (None, 0.05):
        folder = tmp_path / str(thr)
        folder.mkdir()
        cal = load_calibration(_tschamut_calibration(folder, thr), "crsp")
        pooled, *_ = predictive_runouts(cal, held, load_profile(TSCHAMUT), 1, 64, 0)
        out[thr] = pooled[0]
    assert np.mean(out[None] < 1.0) == 1.0
    assert np.mean(out[0.05] < 1.0) < 0.05


def test_the_hazard_run_uses_the_calibrations_threshold(tmp_path):
    """Every CRSP parameter set the hazard run builds carries the calibration's
    threshold."""
    from calib.hazard._run import _work_units

    cal = load_calibration(_tschamut_calibration(tmp_path, 0.05), "crsp")
    entries = Entries.at_sizes([0.3], 40.0, density_kg_m3=2650.0)
    units = list(_work_units(cal, draw_parameters(cal, 1, 0), load_profile(TSCHAMUT), entries,
                             None, None, [0.3], [100.0], 16, 0, 16, [0], 1, crsp.Settings(),
                             None))
    assert units
    for _, make_args, _ in units:
        np.testing.assert_array_equal(np.asarray(make_args()[0].rolling_threshold_m_s), 0.05)


def test_the_designs_impact_angles_use_the_calibrations_threshold(tmp_path, monkeypatch):
    """The design's own CRSP run (impact angles at a barrier) simulates with
    the calibration's threshold."""
    from calib.design._angles import impact_angles

    seen, real = [], crsp.run_blocks

    def run_blocks(params, *args, **kwargs):
        seen.append(float(params.rolling_threshold_m_s))
        return real(params, *args, **kwargs)

    monkeypatch.setattr(crsp, "run_blocks", run_blocks)
    cal = load_calibration(_tschamut_calibration(tmp_path, 0.05), "crsp")
    a = impact_angles(cal, THETA, list(cal.names), load_profile(TSCHAMUT),
                      SHOULDER_X_M + 20.0, 0.3677, 16, 0, SHOULDER_X_M)
    assert seen == [0.05] and a.angle_deg.size > 0


def test_discovery_candidates_run_with_the_sites_threshold():
    from calib.discovery.candidates import candidate_set

    entries = Entries.at_sizes([0.3677], SHOULDER_X_M, density_kg_m3=2650.0)
    cands, combine = candidate_set("crsp", ["vegetation_belt"], load_profile(TSCHAMUT), "fit",
                                   0.05)
    for c in [*cands, combine(["vegetation_belt"])]:
        assert c.forward(entries, 4, jax.random.key(0)).rolling_threshold_m_s == 0.05
    default, _ = candidate_set("crsp", ["vegetation_belt"], load_profile(TSCHAMUT), "fit")
    assert default[0].forward(entries, 4, jax.random.key(0)).rolling_threshold_m_s == \
        crsp.ROLLING_THRESHOLD_M_S


def test_the_fits_check_flags_a_threshold_that_is_not_converged():
    """Check 6 of ``calib.inference.adequacy``: the shoulder release at the
    solver's 0.5 m/s stalls and at a tenth of it runs on, so the check flags it
    and names the site file's key; at the site's 0.05 m/s it runs on either way
    and nothing is flagged; a release on the steep slope below moves by no
    more than the check's tolerance at either threshold."""
    from calib.inference.adequacy import _threshold_problem, threshold_convergence

    e = Entries.at_sizes([0.3677], SHOULDER_X_M, release_speed_m_s=0.39,
                         release_height_m=0.0, density_kg_m3=2650.0).concat(
        Entries.at_sizes([0.3677], 41.5, release_speed_m_s=0.8, release_height_m=0.3,
                         density_kg_m3=2650.0))
    records = {thr: threshold_convergence(
        CrspForward(load_profile(TSCHAMUT), e, 128, jax.random.key(3), box=CRSP_ROLLING_BOX,
                    rolling_threshold_m_s=thr), THETA[0]) for thr in (0.5, 0.05)}
    default, site = records[0.5], records[0.05]
    assert default["compared_m_s"] == pytest.approx(0.05)
    assert [x["flagged"] for x in default["entries"]] == [True, False], default
    assert default["entries"][0]["quantiles_m"][1] < 1.0 < 100.0 < \
        default["entries"][0]["quantiles_compared_m"][1]
    message = _threshold_problem(default)
    assert "not converged" in message and "rolling_threshold_m_s" in message
    assert "x = 38.7 m" in message
    assert site["n_flagged"] == 0 and _threshold_problem(site) is None, site


@pytest.mark.slow  # two hazard commands for one line of output, 16 s inside the default run
def test_the_hazard_run_says_when_the_site_and_the_calibration_disagree(tmp_path, capsys):
    """An older Tschamut calibration (fitted at the solver's 0.5 m/s) run where
    the site file now gives 0.05 m/s: the hazard run simulates the fitted model
    and says so in one line; a calibration at the site's value says nothing."""
    from calib.hazard.__main__ import main as hazard_main

    args = ["--n-posterior", "1", "--n-blocks", "64", "--block-sizes-m", "0.3",
            "--release-x-m", "40", "--stations-m", "60:120:30", "--no-progress"]
    for thr, said in ((None, True), (0.05, False)):
        folder = tmp_path / str(thr)
        folder.mkdir()
        assert hazard_main([_tschamut_calibration(folder, thr), *args,
                            "--out", str(folder / "hazard")]) == 0
        out = capsys.readouterr().out
        assert ("fitted at a CRSP rolling threshold of 0.5 m/s" in out
                and "gives 0.05 m/s" in out) == said, out


def test_the_threshold_check_measures_the_whole_distribution_not_one_quantile():
    """An entry with an atom of blocks stalled at the release: 6 % of 200
    blocks at 0 m at the fit's threshold, 4 % at a tenth of it, the rest
    unchanged. Its 5 % quantile jumps from 0 m to the others' runouts, but the
    distribution moves by W1 = the 4 moved blocks' runouts / 200, about
    0.02 x 81 m, under the check's 5 m: not flagged. Had 30 % stalled at the
    fit's threshold, W1 is about 22 m: flagged, with the distance in the
    message."""
    import dataclasses

    from calib.inference.adequacy import _threshold_problem, threshold_convergence

    runs = np.linspace(80.0, 100.0, 200)

    def stalled(fraction):
        r = runs.copy()
        r[:round(fraction * r.size)] = 0.0
        return r

    @dataclasses.dataclass(frozen=True)
    class Forward:
        rolling_threshold_m_s: float
        first: float  # stalled fraction at the fit's threshold
        entries: object = dataclasses.field(default_factory=lambda: type(
            "E", (), {"release_x_m": np.array([38.6]), "sizes_m": np.array([0.31])})())
        n_blocks: int = 200

        def runouts(self, theta):
            f = self.first if self.rolling_threshold_m_s == 0.05 else 0.04
            return stalled(f)[None, None, :]

    atom = threshold_convergence(Forward(0.05, 0.06), THETA[0])
    x, = atom["entries"]
    assert x["quantiles_m"][0] == 0.0 and x["quantiles_compared_m"][0] > 79.0  # the jump
    assert x["shift_m"] == pytest.approx(runs[8:12].sum() / 200, abs=0.05)
    assert 1.0 < x["shift_m"] < 5.0 and not x["flagged"]
    assert _threshold_problem(atom) is None
    real = threshold_convergence(Forward(0.05, 0.30), THETA[0])
    x, = real["entries"]
    assert x["shift_m"] == pytest.approx(runs[8:60].sum() / 200, abs=0.5) and x["flagged"]
    assert "Wasserstein-1" in _threshold_problem(real)
