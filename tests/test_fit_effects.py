"""A candidate effect outside discovery: ``calib.fit --effect`` fits it,
calibration.json records it (``crsp.effects``), and the predictive check and
the hazard run simulate exactly the model that was fitted."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from cli_run import run_cli
from test_hazard_fixtures import write_calibration

from calib.files.calibration_file import (
    CalibrationError,
    CalibrationFile,
    draw_parameters,
    load_calibration,
)
from calib.files.observations import Observations
from calib.model.effects import (
    CRSP_EFFECTS,
    EFFECTS,
    check_combination,
    crsp_overrides,
    draw_overrides,
    effect_columns,
    effect_names,
    full_box,
    model_label,
)
from calib.model.forward import CrspForward
from calib.model.priors import CRSP_BOX, CRSP_ROLLING_BOX
from solvers import crsp
from solvers.profile import load_profile

PROFILE = load_profile("data/postignano_profile.csv")
BASE = (0.41, 0.87, 2.0)


# --- the registry: effects alone and together ------------------------------------------

@pytest.mark.parametrize("name", [e for e in CRSP_EFFECTS if e != "none"])
def test_each_effect_declares_its_columns_and_what_the_solver_can_run(name):
    e = EFFECTS[name]
    assert e.crsp_box(PROFILE).names == e.columns == effect_columns(name)
    assert set(e.valid) == set(e.columns)


def test_distinct_effects_combine_column_after_column():
    both = ("size_dissipation", "vegetation_belt")
    box = full_box(both, PROFILE)
    assert box.names == CRSP_BOX.names + ("gamma", "belt_start_m", "belt_loss")
    assert model_label(both) == "size_dissipation+vegetation_belt" and model_label(()) == "none"
    assert effect_names("none") == () and effect_names("fragmentation") == ("fragmentation",)
    over = crsp_overrides(both, np.array([[0.3, 150.0, 0.5]]), PROFILE)
    assert set(over) == {"restitution_size_exponent", "belt_start_m", "belt_end_m",
                         "belt_loss"}
    assert over["restitution_size_exponent"][0] == 0.3 and over["belt_loss"][0] == 0.5
    with pytest.raises(ValueError, match="given twice"):
        effect_names(("fragmentation", "fragmentation"))
    with pytest.raises(ValueError, match="one parameter"):
        check_combination(("size_dissipation", "rolling_resistance"), CRSP_ROLLING_BOX.names)
    with pytest.raises(ValueError, match="have 3 column"):
        crsp_overrides(both, np.zeros((1, 2)), PROFILE)


def test_one_draw_maps_onto_the_solver_as_the_fit_maps_its_thetas():
    """``draw_overrides`` (the hazard run's parameters of one draw) gives the
    Params that ``CrspForward.params`` (the fit's) gives for the same theta,
    field by field, for a combined model on the rolling baseline."""
    effects = ("fragmentation", "vegetation_belt", "size_dissipation")
    fw = CrspForward(PROFILE, np.array([1.0]), 4, jax.random.key(0), box=CRSP_ROLLING_BOX,
                     effect=effects)
    theta = np.array([0.35, 0.85, 0.6, 22.0, 2.5, 140.0, 0.3, 0.2])
    assert fw.box.dim == theta.size
    fit = fw.params(theta[None])
    one = crsp.params_from_profile(PROFILE, **draw_overrides(effects, fw.names, theta, PROFILE))
    for f in crsp.Params._fields:
        if f.startswith("release"):
            continue  # set per entry by the forward, per size by the hazard run
        if getattr(one, f) is None:  # an element off in both (no barrier)
            assert getattr(fit, f) is None, f
            continue
        np.testing.assert_allclose(np.asarray(getattr(fit, f))[0], np.asarray(getattr(one, f)),
                                   rtol=1e-12, err_msg=f)
    with pytest.raises(ValueError, match="do not end with the columns"):
        draw_overrides(("size_dissipation",), CRSP_BOX.names, BASE, PROFILE)


# --- calibration.json: written, read, refused ------------------------------------------

def _with_effects(folder, values, effects, *, posterior=None, name="calibration.json"):
    """A CRSP calibration of ``BASE`` plus the effects' ``values`` (map), written
    like calib.fit writes it (``crsp.effects`` and one key per column)."""
    names = CRSP_BOX.names + effect_columns(effects)
    path = write_calibration(folder, crsp=BASE + tuple(values), dem=None, crsp_names=names,
                             crsp_posterior=posterior, name=name)
    with open(path) as fh:
        doc = json.load(fh)
    doc["crsp"]["effects"] = list(effects)
    with open(path, "w") as fh:
        json.dump(doc, fh)
    return path


def test_a_calibration_with_effects_is_read_with_their_columns(tmp_path):
    post = np.column_stack([np.full(5, 0.41), np.full(5, 0.87), np.full(5, 2.0),
                            np.linspace(0.1, 0.5, 5), np.full(5, 140.0), np.full(5, 0.4)])
    path = _with_effects(tmp_path, (0.3, 140.0, 0.4), ("size_dissipation", "vegetation_belt"),
                         posterior=post)
    cal = load_calibration(path)
    assert cal.effects == ("size_dissipation", "vegetation_belt")
    assert cal.names == CRSP_BOX.names + ("gamma", "belt_start_m", "belt_loss")
    assert cal.base_names == CRSP_BOX.names
    np.testing.assert_array_equal(cal.point, BASE + (0.3, 140.0, 0.4))
    np.testing.assert_allclose(cal.posterior, post)
    d = draw_parameters(cal, 3, seed=0)
    assert d.names == cal.names and d.values.shape == (3, 6)
    plain = load_calibration(write_calibration(tmp_path, crsp=BASE, dem=None, name="p.json"))
    assert plain.effects == () and plain.base_names == plain.names == CRSP_BOX.names
    assert CalibrationFile.from_json(path).calibration().effects == cal.effects


@pytest.mark.parametrize("effects, extra, needle", [
    (["teleportation"], {}, "unknown effect 'teleportation'"),
    (["size_dissipation", "size_dissipation"], {"gamma": 0.1}, "given twice"),
    ("size_dissipation", {"gamma": 0.1}, "expected a list of effect names"),
    (["rolling_resistance"], {"delta_mu": 0.2, "rolling_friction_deg": 20.0}, "one parameter"),
    (["vegetation_belt"], {"belt_start_m": 140.0}, "crsp.belt_loss"),
    (["vegetation_belt"], {"belt_start_m": 140.0, "belt_loss": 1.5}, "crsp.belt_loss.map"),
])
def test_a_calibration_naming_an_effect_the_solver_cannot_run_is_refused(
        tmp_path, effects, extra, needle):
    path = write_calibration(tmp_path, crsp=BASE, dem=None)
    with open(path) as fh:
        doc = json.load(fh)
    doc["crsp"]["effects"] = effects
    doc["crsp"].update({k: {"map": v} for k, v in extra.items()})
    with open(path, "w") as fh:
        json.dump(doc, fh)
    with pytest.raises(CalibrationError) as e:
        load_calibration(path)
    msg = str(e.value)
    assert msg.startswith(path) and needle in msg and "\n" not in msg, msg


def test_a_dem_section_with_effects_is_refused(tmp_path):
    path = write_calibration(tmp_path, crsp=None)
    with open(path) as fh:
        doc = json.load(fh)
    doc["dem"]["effects"] = ["fragmentation"]
    with open(path, "w") as fh:
        json.dump(doc, fh)
    with pytest.raises(CalibrationError, match="key 'dem.effects': the DEM runs no effect"):
        load_calibration(path, "dem")


# --- validate and hazard simulate the fitted model -------------------------------------

HELD = Observations.points(np.array([0.4, 2.0]), np.array([150.0, 200.0]), 5.0)


def _validate_runouts(path):
    from calib.inference.predictive_check import predictive_runouts

    cal = load_calibration(path)
    return predictive_runouts(cal, HELD, PROFILE, 1, 32, seed=0)[0]


def _hazard_counts(path):
    from calib.hazard._run import run_hazard

    cal = load_calibration(path)
    draws = draw_parameters(cal, 1, 0)
    # two sizes, 400 blocks, stations every 10 m to 300 m: the compiled program of the
    # small hazard runs of tests/test_hazard.py and tests/test_hazard_cli.py
    c = run_hazard(cal, draws, PROFILE, np.array([0.4, 2.0]), np.arange(0.0, 301.0, 10.0),
                   400, seed=0)
    return np.stack([c.reach, c.exceed, c.e30])


@pytest.mark.parametrize("run", [_validate_runouts, _hazard_counts], ids=["validate", "hazard"])
def test_validate_and_hazard_run_the_effect_and_nothing_when_it_is_off(tmp_path, run):
    """gamma = 0.5 (K (d / 1 m)^0.5: 0.4 m blocks keep less energy, 2 m blocks
    more) changes the simulated runouts; gamma = 0 is the plain model to the
    last bit (same blocks, same keys). The old reader dropped crsp.effects and
    ran the plain model for all three."""
    plain = run(write_calibration(tmp_path, crsp=BASE, dem=None, name="plain.json"))
    on = run(_with_effects(tmp_path, (0.5,), ("size_dissipation",), name="on.json"))
    off = run(_with_effects(tmp_path, (0.0,), ("size_dissipation",), name="off.json"))
    np.testing.assert_array_equal(off, plain)
    assert not np.array_equal(on, plain)
    both = ("size_dissipation", "vegetation_belt")
    both_off = run(_with_effects(tmp_path, (0.0, 90.0, 0.0), both, name="both_off.json"))
    np.testing.assert_array_equal(both_off, plain)
    belt = run(_with_effects(tmp_path, (0.0, 90.0, 0.6), both, name="belt.json"))
    assert not np.array_equal(belt, plain)


# --- the command --------------------------------------------------------------------------

@pytest.mark.parametrize("args, needle", [
    (["--model", "dem", "--effect", "fragmentation"], "--model crsp only"),
    (["--model", "crsp", "--effect", "rolling_resistance"], "--rolling-resistance profile"),
    (["--model", "crsp", "--effect", "fragmentation", "--effect", "fragmentation"],
     "given twice"),
    (["--model", "crsp", "--effect", "teleportation"], "invalid choice"),
])
def test_fit_refuses_effects_it_cannot_fit_in_one_line(tmp_path, capsys, args, needle):
    from calib.fit import main

    out = tmp_path / "r"
    rc, _, err = run_cli(main, ["data/postignano.csv", *args, "--out", str(out)], capsys)
    assert rc == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_fit_help_names_the_effects(capsys):
    from calib.fit import main

    rc, out, _ = run_cli(main, ["--help"], capsys)
    assert rc == 0 and "--effect" in out
    for e in CRSP_EFFECTS[1:]:
        assert e in out


def test_fit_with_effects_writes_and_reads_them(tmp_path, capsys, monkeypatch):
    """calib.fit --effect size_dissipation --effect fragmentation (tiny budgets):
    the effects' columns are fitted, written like the baseline's, recorded in
    crsp.effects, and read back (the predictive check and the hazard run of such a
    file: ``test_validate_and_hazard_run_the_effect_and_nothing_when_it_is_off``)."""
    import calib.inference.calibrate as calibrate
    from calib.fit import main

    tiny = calibrate.Budget(n_design=12, n_design2=0, n_design3=0, n_blocks_design=16,
                            nuts_warmup=30, nuts_samples=30, nuts_chains=1, n_realisations=4,
                            realisation_waves=0, grad_starts=1, grad_steps=1, grad_k=1,
                            n_blocks_grad=16, n_check=16, n_predictive_draws=2,
                            n_blocks_predictive=16)  # one block count: one compilation
    monkeypatch.setattr(calibrate, "presets", lambda model, quick: tiny)
    data = tmp_path / "rows.csv"  # test rows, not observations: 10 stops of 3 sizes
    data.write_text("block_size_m,runout_m,runout_sd_m,source\n" + "".join(
        f"{d},{r},10,test row\n" for d, r in zip([0.4, 1.0, 2.0] * 3 + [1.0],
                                                 [100, 120, 150, 105, 125, 160, 95, 115, 140,
                                                  130], strict=True)))
    out = tmp_path / "r"
    rc, text, err = run_cli(main, [
        str(data), "--profile", "data/postignano_profile.csv", "--model", "crsp", "--method",
        "gradient", "--rolling-resistance", "profile", "--effect", "size_dissipation",
        "--effect", "fragmentation", "--out", str(out), "--no-progress"], capsys)
    print(text[-3000:], err[-3000:])
    assert rc == 0, err
    doc = json.loads((out / "calibration.json").read_text())
    sec = doc["crsp"]
    assert sec["effects"] == ["size_dissipation", "fragmentation"]
    assert sec["parameters"] == list(CRSP_BOX.names) + ["gamma", "log10_frag_energy_kJ"]
    for n in ("gamma", "log10_frag_energy_kJ"):
        assert set(sec[n]) == {"map", "mean", "q05", "q95"}
    assert sec["prior"]["gamma"] == [-0.6, 0.6]
    assert sec["prior"]["log10_frag_energy_kJ"] == [1.0, 4.0]
    assert "gamma" in text and "log10_frag_energy_kJ" in text
    cal = load_calibration(str(out / "calibration.json"))
    assert cal.effects == ("size_dissipation", "fragmentation")
    assert cal.names == tuple(sec["parameters"])
    assert "CRSP effects: size_dissipation, fragmentation" in text


def test_model_section_writes_the_effects_and_the_posterior_columns():
    """The writer's half (posterior CSV and section) from a fit object: the
    effects' columns sit in ``parameters``, as keys and as CSV columns."""
    from calib.files.calibration_file import posterior_csv_text
    from calib.files.fit_record import model_section

    effects = ("vegetation_belt",)
    fw = CrspForward(PROFILE, np.array([1.0]), 4, jax.random.key(0), effect=effects)
    names = fw.names
    samples = np.tile(np.array([0.4, 0.9, 1.0, 140.0, 0.3]), (4, 1))

    @dataclasses.dataclass
    class _Post:
        samples: np.ndarray
        ok: bool = True
        problems: tuple = ()
        divergences: int = 0
        accept_prob: float = 0.8
        n_chains: int = 1
        criteria: dict = dataclasses.field(default_factory=dict)

        def summary(self):
            return {}

    @dataclasses.dataclass
    class _Fit:
        names: tuple
        estimate: np.ndarray
        posterior: _Post
        estimate_source: str = "posterior mean"
        quality: tuple = ()
        unfinished: dict | None = None
        adequacy: dict | None = None
        timings_s: dict = dataclasses.field(default_factory=dict)
        budget: object = dataclasses.field(default_factory=lambda: type("B", (), {})())
        check_runouts: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((1, 2)))
        gradient: object = None
        emulator_check: dict | None = None
        focus: dict | None = None
        chain_screen: dict | None = None
        estimate_choice: dict | None = None

    sec = model_section("crsp", _Fit(names, samples[0], _Post(samples)), fw)
    assert sec["effects"] == ["vegetation_belt"]
    assert sec["parameters"][-2:] == ["belt_start_m", "belt_loss"]
    assert sec["belt_loss"]["mean"] == pytest.approx(0.3)
    assert posterior_csv_text(names, samples).splitlines()[0] == \
        "Kn,Kt,roughness_m,belt_start_m,belt_loss"
