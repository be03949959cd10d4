"""The predictive check: scores on known ensembles, per-row releases in
the forward model, and ``python -m calib.validate`` end to end and on bad input."""

from __future__ import annotations

import json
import os
import shlex
import sys
import types

import jax
import numpy as np
import pytest
from test_hazard_fixtures import write_calibration

from calib.files.observations import Observations
from calib.inference.predictive_check import score_rows
from calib.model.entries import Entries
from calib.model.forward import CrspForward
from calib.validate import build_parser, main, print_summary, run_validation
from solvers.profile import load_profile

PROFILE = load_profile("data/postignano_profile.csv")


def _calib_rows(values, sizes):
    return Observations.points(np.asarray(sizes, float), np.asarray(values, float), 1.0)


def test_scores_of_a_known_ensemble():
    """Ensemble uniform on [0, 100] (measurement sd ~0): y = 30 has PIT 0.3, lies in
    the 50 % band (25-75) and the 90 % band (5-95); the error of the mean is +20 m;
    the CRPS of U(0, 100) at 30 is (30^2 + 70^2) / 200 - 100 / 6 = 12.33 m."""
    obs = Observations.points([1.0], [30.0], 1e-9)
    ens = np.linspace(0.0, 100.0, 100001)[None]
    calib = _calib_rows([10.0, 20.0, 30.0, 40.0], [1.0] * 4)
    row = score_rows(obs, ens, np.array([0]), calib).rows.iloc[0]
    assert abs(row["pit"] - 0.3) < 1e-3 and row["in_50"] and row["in_90"]
    assert abs(row["error_of_mean_m"] - 20.0) < 1e-2
    assert abs(row["crps_m"] - ((30**2 + 70**2) / 200 - 100 / 6)) < 1e-2
    # climatology {10, 20, 30, 40} at 30: E|X - 30| - E|X - X'| / 2 = 10 - 12.5 / 2
    assert abs(row["crps_climatology_m"] - (10.0 - 6.25)) < 1e-9
    assert row["baseline_size"] == "size"


def test_rows_whose_quantiles_rest_on_few_blocks_are_flagged_and_named(capsys):
    """10 finished blocks behind row 2, 100 behind row 1: only row 2 is flagged
    (solvers.percentiles.few_blocks), listed in the summary and named on stderr."""
    obs = Observations.points([1.0, 1.0], [30.0, 40.0], 1.0)
    ens = np.full((2, 100), np.nan)  # NaN: unfinished blocks, left out
    ens[0] = np.linspace(0.0, 100.0, 100)
    ens[1, :10] = np.linspace(0.0, 100.0, 10)
    check = score_rows(obs, ens, np.array([0, 1]), _calib_rows([10.0, 20.0, 30.0], [1.0] * 3))
    assert list(check.rows["few_blocks"]) == [False, True]
    assert check.summary["few_blocks_rows"] == [[2, 10]]
    print_summary({**check.summary, "model": "crsp", "draws": "posterior", "n_draws": 1,
                   "n_blocks_per_draw_and_group": 100}, "out")
    err = capsys.readouterr().err
    assert "rest on fewer than 20 blocks" in err and "row 2 (10 blocks)" in err
    assert "row 1" not in err


def test_skill_ranks_a_sharp_right_forecast_above_climatology_and_a_biased_one_below():
    rng = np.random.default_rng(0)
    y = 100.0 + 10.0 * rng.standard_normal(40)
    obs = Observations.points(np.ones(40), y, 1.0)
    calib = _calib_rows(100.0 + 10.0 * rng.standard_normal(30), np.ones(30))
    idx = np.arange(40)
    right = (y[:, None] + 2.0 * rng.standard_normal((40, 2000)))  # knows each row
    biased = 160.0 + 2.0 * rng.standard_normal((40, 2000))
    good = score_rows(obs, right, idx, calib).summary
    bad = score_rows(obs, biased, idx, calib).summary
    assert good["skill_vs_climatology"] > 0.5
    assert bad["skill_vs_climatology"] < 0 and bad["n_below_90"] == 40
    assert bad["mean_error_of_mean_m"] > 50 and bad["coverage_90"] == 0.0


def test_per_size_baseline_falls_back_to_all_rows():
    obs = Observations.points([2.0], [200.0], 1.0)
    calib = _calib_rows([100.0, 110.0, 120.0, 210.0], [0.5, 0.5, 0.5, 2.0])
    rows = score_rows(obs, np.full((1, 10), 200.0), np.array([0]), calib).rows
    assert rows.loc[0, "baseline_size"] == "overall"
    assert rows.loc[0, "crps_climatology_size_m"] == rows.loc[0, "crps_climatology_m"]


def test_groups_of_rows_with_and_without_release():
    obs = types.SimpleNamespace(block_size_m=np.array([1.0, 1.0, 0.5, 1.0]), n_obs=4,
                                release_x_m=np.array([5.0, np.nan, 5.0, 5.0]))
    e = Entries.from_rows(obs, 0.0)
    assert np.isnan(e.release_speed_m_s).all() and np.isnan(e.release_height_m).all()
    assert not any(e.profile_csv) and e.profiles == (None,) * 3
    assert e.sizes_m.tolist() == [0.5, 1.0, 1.0] and e.release_x_m.tolist() == [5.0, 0.0, 5.0]
    assert e.index.tolist() == [2, 1, 0, 2]


def test_release_groups_within_a_tolerance():
    """Rows of one size within tol of their group's lowest release share it,
    released at the mean; other sizes never join; every row's release error
    is at most tol."""
    rel = np.array([10.0, 10.4, 10.9, 11.2, 10.2, 30.0])
    obs = types.SimpleNamespace(block_size_m=np.array([1.0, 1.0, 1.0, 1.0, 0.5, 1.0]),
                                n_obs=6, release_x_m=rel,
                                release_speed_m_s=np.array([1.0, np.nan, 2.0, 0.5, np.nan,
                                                            np.nan]))
    g = Entries.from_rows(obs, 0.0, tol_m=1.0)
    assert g.sizes_m.tolist() == [0.5, 1.0, 1.0, 1.0]
    np.testing.assert_allclose(g.release_x_m, [10.2, (10.0 + 10.4 + 10.9) / 3, 11.2, 30.0])
    assert g.index.tolist() == [1, 1, 1, 2, 0, 3]
    # the mean of the speeds its rows give; NaN (the solver's default) where none does
    np.testing.assert_array_equal(g.release_speed_m_s, [np.nan, 1.5, 0.5, np.nan])
    assert np.all(np.abs(g.release_x_m[g.index] - rel) <= 1.0)
    with pytest.raises(ValueError, match="tolerance"):
        Entries.from_rows(obs, 0.0, tol_m=-1.0)


def test_forward_runs_each_group_from_its_release():
    """Release at the profile's start: the same blocks as the forward without
    releases (common random numbers); released at 150 m on the gentle lower slope,
    1 m blocks stop within a few metres."""
    theta = np.array([[0.41, 0.87, 2.0]])
    key = jax.random.key(5)
    plain = CrspForward(PROFILE, np.array([1.0]), 32, key).runouts(theta)[0, 0]
    both = CrspForward(PROFILE, Entries.at_sizes([1.0, 1.0], (0.0, 150.0)), 32,
                       key).runouts(theta)[0]
    np.testing.assert_array_equal(both[0], plain)
    assert np.nanmax(both[1]) < 20.0 < np.nanmin(both[0])
    # a release speed per entry: NaN keeps the default (same blocks), 6 m/s differs
    fast = CrspForward(PROFILE, Entries.at_sizes([1.0, 1.0], 0.0,
                                                 release_speed_m_s=(np.nan, 6.0)),
                       32, key).runouts(theta)[0]
    np.testing.assert_array_equal(fast[0], plain)
    assert not np.array_equal(fast[1], plain)


@pytest.fixture(scope="module")
def cal_path(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cal")
    post = np.array([[0.41, 0.87, 2.0], [0.45, 0.9, 1.0], [0.35, 0.85, 3.0]])
    return write_calibration(folder, crsp_posterior=post)


def test_command_writes_scores_figures_and_provenance(cal_path, tmp_path, capsys):
    held = tmp_path / "held.csv"
    held.write_text("block_size_m,runout_m,runout_sd_m\n0.2,110,5\n2.0,220,15\n")
    out = tmp_path / "val"
    assert main([cal_path, str(held), "--n-posterior", "3", "--n-blocks", "16",
                 "--out", str(out)]) == 0
    assert set(os.listdir(out)) == {"validation.csv", "validation.json", "pit_histogram.png",
                                    "intervals.png"}
    s = json.loads((out / "validation.json").read_text())
    assert s["n_scored"] == 2 and s["n_draws"] == 3
    assert len(s["provenance"]["inputs"]["heldout"]["sha256"]) == 64
    assert s["provenance"]["versions"]["scoringrules"]
    assert "mean CRPS" in capsys.readouterr().out


def test_the_recorded_command_repeats_the_check_whoever_ran_it(cal_path, tmp_path, monkeypatch):
    # calib.fit runs the check of its held-out rows inside its own process: the
    # command recorded must be this one's, not the fit's arguments after it
    held = tmp_path / "held rows.csv"
    held.write_text("block_size_m,runout_m,runout_sd_m\n0.2,110,5\n2.0,220,15\n")
    monkeypatch.setattr(sys, "argv", ["calib/fit.py", "data.csv", "--holdout-fraction", "0.3"])
    args = build_parser().parse_args([cal_path, str(held), "--n-posterior", "2", "--n-blocks",
                                      "8", "--seed", "4", "--out", str(tmp_path / "v")])
    cmd = run_validation(args)["provenance"]["command"]
    words = shlex.split(cmd)
    assert words[:3] == ["python", "-m", "calib.validate"] and "--holdout-fraction" not in words
    assert vars(build_parser().parse_args(words[3:])) == vars(args)  # the same check again


@pytest.mark.parametrize("content, needle", [
    ("block_size_m,runout_m,runout_sd_m\n0.2,abc,5\n", "runout_m"),
    ("block_size_m,runout_m,runout_sd_m,release_x_m\n0.2,110,5,400\n", "release_x_m"),
])
def test_bad_input_one_line_exit_2_nothing_written(cal_path, tmp_path, capsys, content, needle):
    held = tmp_path / "held.csv"
    held.write_text(content)
    out = tmp_path / "val"
    with pytest.raises(SystemExit) as e:
        main([cal_path, str(held), "--n-posterior", "1", "--n-blocks", "4", "--out", str(out)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_holdout_split_is_reproducible_disjoint_and_complete():
    from calib.files.split import holdout_rows

    a_fit, a_held = holdout_rows(62, 0.3, 4)
    b_fit, b_held = holdout_rows(62, 0.3, 4)
    np.testing.assert_array_equal(a_held, b_held)
    assert len(a_held) == 19 and not set(a_fit) & set(a_held)
    assert sorted(set(a_fit) | set(a_held)) == list(range(62))
    assert not np.array_equal(holdout_rows(62, 0.3, 5)[1], a_held)
    with pytest.raises(ValueError, match="fewer than 2"):
        holdout_rows(2, 0.5, 0)
    with pytest.raises(ValueError, match="fraction"):
        holdout_rows(10, 1.0, 0)


def test_fit_with_holdout_fraction_writes_the_split_and_validates(tmp_path, capsys,
                                                                  monkeypatch):
    """calib.fit --holdout-fraction: the held-out rows are not fitted, the
    calibration records its own rows as its data, and the check runs at the end
    (the command's main in this process, on small stage sizes with one block count:
    one compiled solver program)."""
    import pandas as pd
    from cli_run import run_cli

    import calib.inference.calibrate as calibrate
    from calib.fit import main as fit_main

    small = calibrate.Budget(n_design=12, n_design2=0, n_design3=0, n_blocks_design=16,
                             grad_starts=1, grad_steps=2, grad_k=1, n_blocks_grad=16,
                             n_check=16, n_predictive_draws=2, n_blocks_predictive=16)
    monkeypatch.setattr(calibrate, "presets", lambda model, quick: small)
    data = tmp_path / "site.csv"
    pd.DataFrame({"block_size_m": [0.2, 0.2, 0.5, 1.0, 1.0, 2.0, 2.0, 2.0],
                  "runout_m": [110, 112, 115, 120, 135, 150, 210, 230],
                  "runout_sd_m": [5] * 8, "source": ["test"] * 8}).to_csv(data, index=False)
    out = tmp_path / "res"
    rc, text, err = run_cli(fit_main, [
        str(data), "--profile", "data/postignano_profile.csv", "--model", "crsp", "--method",
        "gradient", "--holdout-fraction", "0.25", "--seed", "3", "--out", str(out),
        "--no-progress"], capsys)
    assert rc == 0, err[-2000:]
    cal = json.loads((out / "calibration.json").read_text())
    fit_rows = pd.read_csv(out / "calibration_rows.csv")
    held = pd.read_csv(out / "heldout_rows.csv")
    assert len(fit_rows) == 6 and len(held) == 2 and cal["n_observations"] == 6
    assert cal["data_csv"] == str(out / "calibration_rows.csv")
    s = json.loads((out / "validation" / "validation.json").read_text())
    assert s["n_scored"] == 2 and "mean CRPS" in text


def test_validate_simulates_with_the_fitted_rolling_angle(tmp_path):
    """A four-parameter calibration: the predictive runouts use its rolling angle
    (on smooth ground 2 m blocks run further at 10 deg than at 40 deg), not the
    profile's own 30 deg."""
    held = tmp_path / "held.csv"
    held.write_text("block_size_m,runout_m,runout_sd_m\n2.0,200,5\n")
    medians = []
    for phi in (10.0, 40.0):
        folder = tmp_path / f"phi{phi:g}"
        folder.mkdir()
        path = write_calibration(folder, crsp=(0.41, 0.87, 0.25, phi))
        assert main([path, str(held), "--n-posterior", "1", "--n-blocks", "64",
                     "--out", str(folder / "val")]) == 0
        s = json.loads((folder / "val" / "validation.json").read_text())
        medians.append(s["mean_error_of_mean_m"])
    assert medians[0] > medians[1] + 5.0, medians


def test_interval_only_heldout_rows_are_reported_not_a_traceback(cal_path, tmp_path):
    held = tmp_path / "held.csv"
    held.write_text("block_size_m,runout_min_m,runout_max_m\n0.2,100,120\n")
    out = tmp_path / "val"
    assert main([cal_path, str(held), "--n-posterior", "1", "--n-blocks", "8",
                 "--out", str(out)]) == 0
    s = json.loads((out / "validation.json").read_text())
    assert s["n_scored"] == 0 and s["n_interval_rows"] == 1


def test_calibrate_scores_each_row_against_its_own_release():
    """Two rows of one size, released at the top (x = 0) and on the gentle lower
    slope (x = 150 m): with release groups the check simulates each row from its
    own point (long vs short runout), and each row's fit quality reads its own
    group; the figure's sizes are simulated at the median release."""
    from calib.inference.calibrate import Budget, calibrate
    from calib.model.priors import CRSP_BOX

    obs = Observations(np.array([1.0, 1.0]), np.array([100.0, 5.0]), np.array([2.0, 2.0]),
                       np.full(2, np.nan), np.full(2, np.nan), np.zeros(2, bool),
                       ("top", "low"), release_x_m=np.array([0.0, 150.0]),
                       release_speed_m_s=np.array([1.5, np.nan]))
    groups = Entries.from_rows(obs, 0.0)
    assert groups.release_x_m.tolist() == [0.0, 150.0]
    fw = CrspForward(PROFILE, groups, 16, jax.random.key(3), box=CRSP_BOX)
    budget = Budget(grad_starts=1, grad_steps=1, grad_k=1, n_blocks_grad=16, n_check=64)
    fit = calibrate(fw, obs, jax.random.key(4), ("gradient",), budget)
    top, low = fit.quality
    assert low["sim_median_m"] < 20.0 < top["sim_median_m"]
    assert fit.check_sizes_m.tolist() == [1.0]
    # the figure's sizes (other entries than the groups) run without the groups' speeds
    fit = calibrate(fw, obs, jax.random.key(4), ("gradient",), budget,
                    extra_sizes_m=(0.5, 2.0))
    assert fit.check_sizes_m.tolist() == [0.5, 1.0, 2.0]
    with pytest.raises(ValueError, match="entries"):
        calibrate(CrspForward(PROFILE, np.array([1.0, 1.0]), 16, jax.random.key(3)), obs,
                  jax.random.key(4), ("gradient",), budget)


def test_calibrate_without_groups_is_the_one_release_grouping():
    """A forward on one entry per size (no row index) scores every row of a size
    against its size's blocks: the same fit as with the one-per-size entries
    (``Entries.one_per_size``); the rows read the figure's simulation (its sizes
    include theirs), so the check simulates the figure's sizes only. A forward
    on other sizes than the rows' is refused."""
    from calib.inference.calibrate import Budget, calibrate

    obs = Observations.points([0.5, 2.0, 0.5], [60.0, 112.0, 70.0], 10.0)
    groups = Entries.one_per_size(obs, float(PROFILE.x_m[0]))
    assert groups.sizes_m.tolist() == [0.5, 2.0] and groups.index.tolist() == [0, 1, 0]
    assert groups.release_x_m.tolist() == [float(PROFILE.x_m[0])] * 2
    assert np.isnan(groups.release_speed_m_s).all()
    fw = CrspForward(PROFILE, obs.sizes_m, 16, jax.random.key(3))
    budget = Budget(grad_starts=1, grad_steps=1, grad_k=1, n_blocks_grad=16, n_check=32)
    plain = calibrate(fw, obs, jax.random.key(4), ("gradient",), budget, extra_sizes_m=(1.0,))
    given = calibrate(CrspForward(PROFILE, groups, 16, jax.random.key(3)), obs,
                      jax.random.key(4), ("gradient",), budget, extra_sizes_m=(1.0,))
    assert plain.quality == given.quality
    np.testing.assert_array_equal(plain.check_runouts, given.check_runouts)
    assert plain.check_sizes_m.tolist() == [0.5, 1.0, 2.0]
    assert plain.unfinished["stages"]["check"]["n_blocks"] == 3 * 32
    with pytest.raises(ValueError, match="entries"):
        calibrate(CrspForward(PROFILE, np.array([0.5, 1.0, 2.0]), 16, jax.random.key(3)),
                  obs, jax.random.key(4), ("gradient",), budget)


def test_fit_checks_the_posterior_and_the_point_estimate(tmp_path):
    """After a Bayesian fit, ``calib.fit --holdout-fraction`` scores the
    posterior predictive (validation/) and the point estimate alone
    (validation/point_estimate/, ``POINT_ESTIMATE_BLOCKS`` = 2000 CRSP blocks per
    row group by default): on Tschamut a posterior that failed its checks scored
    skill -2.04 where its estimate scored -0.08. Here 200 blocks: the compiled
    program of the posterior's check (256 slots) instead of one of its own."""
    from calib.fit import POINT_ESTIMATE_BLOCKS, validate_heldout

    rng = np.random.default_rng(0)
    post = np.column_stack([rng.uniform(0.3, 0.5, 60), rng.uniform(0.8, 0.9, 60),
                            rng.uniform(0.5, 2.0, 60)])
    write_calibration(tmp_path, crsp_posterior=post)
    (tmp_path / "heldout_rows.csv").write_text(
        "block_size_m,runout_m,runout_sd_m\n0.2,110,15\n2.0,220,15\n")
    assert POINT_ESTIMATE_BLOCKS == 2000
    done = validate_heldout(str(tmp_path), "crsp", 0, posterior=True, point_estimate_blocks=200)
    assert [folder for _, folder in done] == [str(tmp_path / "validation"),
                                              str(tmp_path / "validation" / "point_estimate")]
    main_check = json.loads((tmp_path / "validation" / "validation.json").read_text())
    point = json.loads((tmp_path / "validation" / "point_estimate" /
                        "validation.json").read_text())
    assert [s["n_draws"] for s, _ in done] == [main_check["n_draws"], point["n_draws"]]
    assert main_check["draws"] == "posterior" and main_check["n_draws"] == 50
    assert point["draws"] == "point estimate" and point["n_blocks_per_draw_and_group"] == 200


def test_read_summary_checks_the_schema(tmp_path):
    """read_summary (the notebooks' reader of validation.json) hands back the summary
    of the schema run_validation writes, and refuses another file."""
    from calib.validate import SCHEMA, read_summary

    good = tmp_path / "validation.json"
    good.write_text(json.dumps({"schema": SCHEMA, "n_scored": 3}))
    assert read_summary(str(good))["n_scored"] == 3
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"schema": "rockfall-calibration/1"}))
    for path, needle in ((other, "schema"), (tmp_path / "missing.json", "cannot read")):
        with pytest.raises(ValueError, match=needle):
            read_summary(str(path))
