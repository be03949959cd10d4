"""The main job, ``python -m calib.fit``, end to end (small stage sizes; --quick in the
slow run) and its bad-input errors."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import json
import os
import subprocess

import pytest
from cli_run import run_cli, run_module

from calib.inference.budget import Budget

DATA = "data/postignano.csv"
PROFILE = "data/postignano_profile.csv"


def run(*args, cwd=None):
    return run_module("calib.fit", *args, cwd=cwd)


# Stage sizes for the end-to-end run of the default test run: every stage of both
# models runs and writes its outputs, on a few points and blocks (one block count per
# model: one compiled solver program each). The --quick budget, whose run takes about
# 4 minutes on 2 cores, is the slow test below; its figures are not these. One NUTS
# refinement, not two: its chains fail their diagnostics at 100 draws, and the path is
# the same the second time.
SMALL = {"crsp": Budget(n_design=16, n_design2=8, n_design3=8, n_blocks_design=32,
                        nuts_warmup=100, nuts_samples=100, nuts_chains=2, refinements=1,
                        n_realisations=8, realisation_waves=0, grad_starts=1, grad_steps=2,
                        grad_k=1, n_blocks_grad=32, n_check=32, n_predictive_draws=4,
                        n_blocks_predictive=32),
         "dem": Budget(n_design=6, n_design2=0, n_design3=0, n_blocks_design=2,
                       nuts_warmup=100, nuts_samples=100, nuts_chains=2, grad_starts=1,
                       grad_steps=1, grad_k=1, n_blocks_grad=2, n_check=2,
                       n_predictive_draws=2, n_blocks_predictive=2)}


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """The main job's ``main`` in this process on data/postignano.csv with the
    ``SMALL`` stage sizes: (exit status, stdout, stderr) and the output folder."""
    import calib.inference.calibrate as calibrate
    import calib.model.forward as forward
    from calib.fit import main

    out = tmp_path_factory.mktemp("results")
    stdout, stderr = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(stdout), \
            contextlib.redirect_stderr(stderr):
        mp.setattr(calibrate, "presets", lambda model, quick: SMALL[model])
        # at most 8 DEM blocks per compiled call, not 32: this budget's stages simulate
        # 4-24 blocks at a time, and a call costs in proportion to its lanes, padding
        # included (the DEM's stage times summed 80 s -> 48 s with one 8-lane width; with
        # calls as wide as the largest side, at most 32, this test took 151 s against
        # 142 s at most 8: more widths, more programs to compile). A block's result does
        # not depend on the lanes that share its call (solvers.dem._sums), so the runouts
        # are those of the default.
        mp.setattr(forward, "DemForward", functools.partial(forward.DemForward, lane_batch=8))
        try:
            rc = main([DATA, "--out", str(out), "--no-progress"])
        except SystemExit as e:
            rc = e.code
    return subprocess.CompletedProcess([], rc, stdout.getvalue(), stderr.getvalue()), out


def _check_every_output(proc, out, n_draws_min):
    """What one run of the main job must write, whatever its budget."""
    print(proc.stdout[-3000:], proc.stderr[-3000:])
    assert proc.returncode == 0, proc.stderr
    names = set(os.listdir(out))
    assert {"calibration.json", "crsp_posterior.csv", "dem_posterior.csv", "crsp_posterior.nc",
            "dem_posterior.nc", "runout_vs_size.png", "alpha_law.png", "crsp_pairs.png",
            "dem_pairs.png"} <= names
    assert not [n for n in names if n.startswith(".")], names  # no temporary leftovers
    cal = json.loads((out / "calibration.json").read_text())
    for p in ("Kn", "Kt", "roughness_m"):
        assert set(cal["crsp"][p]) >= {"map", "mean", "q05", "q95"}
        assert cal["crsp"][p]["q05"] <= cal["crsp"][p]["mean"] <= cal["crsp"][p]["q95"]
    law = cal["dem"]["alpha_law"]
    assert law["form"] == "power" and {"a", "b"} <= set(law)
    assert set(cal["dem"]["alpha_at_L"]) == {"0.2", "0.9", "1.8"}
    for v in cal["dem"]["alpha_at_L"].values():
        assert 0 <= v["q05"] <= v["q95"] <= 0.95
    # Table 1 comes from the site file (calib/files/site.py), not from a default
    assert {L: v["reference"] for L, v in cal["dem"]["alpha_at_L"].items()} == {
        "0.2": 0.90, "0.9": 0.43, "1.8": 0.30}
    assert len(cal["fit_quality"]["crsp"]) == 2 and len(cal["fit_quality"]["dem"]) == 2
    assert cal["seed"] == 0 and cal["versions"]["jax"]
    assert "ok" in cal["crsp"]["bayes"] and "rhat" in cal["crsp"]["bayes"]["summary"]["Kn"]
    assert {"ess_bulk", "ess_tail"} <= set(cal["crsp"]["bayes"]["summary"]["Kn"])
    # the same draws as InferenceData, with the chains and the emulated log-likelihood
    from calib.files.inference_data import read_inference_data

    for m in ("crsp", "dem"):
        assert cal[m]["posterior_netcdf"] == f"{m}_posterior.nc"
        idata = read_inference_data(str(out / cal[m]["posterior_netcdf"]))
        post = idata["posterior"]
        assert list(post.data_vars) == cal[m]["parameters"]
        assert post.sizes["chain"] * post.sizes["draw"] == cal[m]["bayes"]["n_draws"]
        if m == "crsp":  # emulated as the rows' sum inside the focus region
            assert cal[m]["bayes"]["focus"] is not None
            assert len(cal[m]["bayes"]["focus"]["realisation_waves"]) <= 1  # both budgets
            assert "median_range" in cal[m]["bayes"]["focus"]["realisations"]
            assert idata["log_likelihood"]["total"].sizes["draw"] == post.sizes["draw"]
        else:  # the DEM's posterior averaged over its emulator's realisations
            assert cal[m]["bayes"]["emulator"]["expected_posterior"]["n_realisations"] > 1
            assert idata["log_likelihood"]["total"].sizes["draw"] == post.sizes["draw"]
        assert int(idata["sample_stats"]["diverging"].sum()) == cal[m]["bayes"]["divergences"]
    # the summary table and stage times are printed
    assert "90% interval" in proc.stdout and "stage times" in proc.stdout
    # diagnostics that fail are said loudly
    for m in ("crsp", "dem"):
        if not cal[m]["bayes"]["ok"]:
            assert f"{m.upper()} POSTERIOR DIAGNOSTICS FAILED" in proc.stderr
    rows = (out / "crsp_posterior.csv").read_text().splitlines()
    assert rows[0] == "Kn,Kt,roughness_m,rolling_friction_deg" and len(rows) > n_draws_min
    assert 5.0 <= cal["crsp"]["rolling_friction_deg"]["map"] <= 40.0
    # the fit says whether it can fit: bound mass and predictive coverage
    for m in ("crsp", "dem"):
        a = cal[m]["adequacy"]
        assert set(a["bounds"]) == set(cal[m]["parameters"])
        assert a["coverage"]["levels"]["0.9"]["n_rows"] == 2
        assert "posterior predictive" in a["predictive"]
        if not a["ok"]:
            assert f"{m.upper()} CALIBRATION: the model may not" in proc.stderr
    # the rolling threshold's convergence at the estimate (CRSP only): Postignano's
    # two sizes, the solver's 0.5 m/s against 0.05 m/s
    thr = cal["crsp"]["adequacy"]["rolling_threshold"]
    assert (thr["threshold_m_s"], len(thr["entries"])) == (0.5, 2)
    assert thr["compared_m_s"] == pytest.approx(0.05)
    assert cal["dem"]["adequacy"]["rolling_threshold"] is None
    assert "inside their predictive bands" in proc.stdout
    return cal


def test_main_job_writes_every_output(small_run):
    proc, out = small_run
    cal = _check_every_output(proc, out, n_draws_min=50)
    for m in ("crsp", "dem"):  # the SMALL stage sizes reached the job and its record
        assert cal[m]["budget"] == dataclasses.asdict(SMALL[m])
    focus = cal["crsp"]["bayes"]["focus"]
    assert len(focus["refined"]) <= SMALL["crsp"].refinements
    # every NUTS run is counted: the first, and one after each repair
    assert focus["nuts_runs"] == 1 + sum(len(focus.get(k) or []) for k in (
        "refined", "best_point_waves", "realisation_waves", "widened"))


def test_the_rolling_prior_starts_where_a_block_can_rest_on_the_profile(small_run):
    """Postignano's profile falls at 6.0 deg or more everywhere: below that
    rolling resistance angle no block comes to rest on it (tests/
    test_rolling_parameter.py), so the fit's prior starts there, not at the
    published 5 deg, and the summary says so; no posterior draw lies below it."""
    import numpy as np
    import pandas as pd

    from calib.model.priors import flattest_slope_deg
    from solvers.profile import load_profile

    proc, out = small_run
    floor = flattest_slope_deg(load_profile(PROFILE))
    cal = json.loads((out / "calibration.json").read_text())
    lower, upper = cal["crsp"]["prior"]["rolling_friction_deg"]
    assert (lower, upper) == (pytest.approx(floor, abs=1e-5), 40.0)
    assert "CRSP rolling resistance: prior from 6.0 deg, the flattest slope" in proc.stdout
    draws = pd.read_csv(out / "crsp_posterior.csv")["rolling_friction_deg"].to_numpy()
    assert np.all(draws >= lower)


def test_the_summary_counts_every_nuts_run(capsys):
    """The summary says how often NUTS ran (the record's count, every repair
    wave included) and names each kind of wave."""
    from calib.fit import _print_nuts_repairs

    focus = {"nuts_runs": 4,
             "refined": [{"problems_before": ["R-hat"], "n_points": 32}],
             "best_point_waves": [{"best_loglik": -760.0, "chain_loglik": -828.0,
                                   "bar_nats": 13.8}],
             "realisation_waves": [{"median_range": {"Kn": (0.31, 0.59)},
                                    "n_realisations": 16}],
             "widened": []}
    _print_nuts_repairs({"crsp": {"bayes": {"focus": focus, "ok": True}}}, ("crsp",))
    out = capsys.readouterr().out
    assert "CRSP NUTS ran 4 times" in out
    for kind in ("refinement waves", "best-point waves", "realisation waves"):
        assert f"CRSP {kind}" in out


@pytest.mark.slow
def test_quick_run_writes_every_output(tmp_path):
    """The --quick budget as a user runs it (a fresh process, about 4 minutes)."""
    out = tmp_path / "results"
    proc = run(DATA, "--quick", "--out", str(out), "--no-progress")
    _check_every_output(proc, out, n_draws_min=100)


def test_help_explains():
    proc = run("--help")
    assert proc.returncode == 0
    for word in ("--model", "--method", "--quick", "--alpha-law", "runout_sd_m"):
        assert word in proc.stdout


@pytest.mark.parametrize("content,needle", [
    (None, "no such file"),
    ("", "empty file"),
    ("block_size_m,runout_m\n0.5,100\n", "runout_sd_m"),
    ("block_size_m,runout_m,runout_sd_m\n-0.5,100,10\n", "line 2, column 'block_size_m'"),
    ("block_size_m,runout_m,runout_sd_m\nnan,100,10\n", "line 2, column 'block_size_m'"),
    ("block_size_m,runout_min_m,runout_max_m\n0.5,150,120\n", "line 2, column 'runout_min_m'"),
    ("block_size_m,runout_m,runout_sd_m\n0.5,100,10\n1.0,450,10\n",
     "line 3, column 'runout_m': runout 450 m lies beyond the end of the profile"),
])
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, content, needle, capsys):
    """The command's ``main`` in this process (a fresh interpreter per case would
    cost a JAX import each); test_help_explains runs the command as a process."""
    from calib.fit import main

    data = tmp_path / "site.csv"
    if content is not None:
        data.write_text(content)
    out = tmp_path / "out"
    rc, _, err = run_cli(main, [str(data), "--profile", os.path.abspath(PROFILE), "--out",
                                str(out), "--quick"], capsys)
    assert rc == 2, err
    assert needle in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    assert not out.exists()


def test_a_profile_where_no_block_can_rest_is_refused(tmp_path, capsys):
    """A profile steeper than the rolling resistance prior's 40 deg everywhere:
    no fitted angle lets a block come to rest on it, so the observed runouts
    cannot be fitted; one line naming the profile, exit 2, nothing written."""
    from calib.fit import main

    profile = tmp_path / "wall_profile.csv"
    profile.write_text("x_m,z_m,zone\n0,300,rock\n100,180,rock\n200,0,\n")  # 50.2, 60.9 deg
    (tmp_path / "wall_materials.csv").write_text(
        "zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg\nrock,0.4,0.9,0.5,30,30\n")
    data = tmp_path / "wall.csv"
    data.write_text("block_size_m,runout_m,runout_sd_m\n0.5,150,10\n")
    out = tmp_path / "out"
    rc, _, err = run_cli(main, [str(data), "--profile", str(profile), "--model", "crsp",
                                "--out", str(out), "--quick", "--no-progress"], capsys)
    assert rc == 2, err
    assert "wall_profile.csv: no block can come to rest on the profile below a rolling " \
           "resistance angle of 50.2 deg, above the prior's 40 deg" in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists()


def test_missing_default_profile_is_explained(tmp_path, capsys):
    from calib.fit import main

    data = tmp_path / "elsewhere.csv"
    data.write_text("block_size_m,runout_m,runout_sd_m\n0.5,100,10\n")
    rc, _, err = run_cli(main, [str(data), "--out", str(tmp_path / "out")], capsys)
    assert rc == 2
    assert "elsewhere_profile.csv: no such profile file (give --profile)" in err


def test_notebook_01_calibration_runs(small_run, tmp_path):
    """notebooks/01_calibration.py (jupytext) executes top to bottom on the main job's
    outputs."""
    import jupytext
    import nbclient

    proc, out = small_run
    assert proc.returncode == 0
    nb = jupytext.read("notebooks/01_calibration.py")
    os.environ["NOTEBOOK_RESULTS"] = str(out)
    try:
        nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                resources={"metadata": {"path": os.getcwd()}}).execute()
    finally:
        del os.environ["NOTEBOOK_RESULTS"]
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                   for o in c.get("outputs", []))
    assert "Kn" in text and "Table 1" in text and "prior range" in text


def test_run_fit_refuses_bad_input_in_one_line_and_writes_nothing(tmp_path):
    """run_fit (the command's work, what the notebooks call): a bad row or an effect
    with the DEM is one CliError line before anything runs; nothing is written."""
    from calib.fit import run_fit
    from solvers.cli import CliError

    bad = tmp_path / "rows.csv"
    bad.write_text("block_size_m,runout_m,runout_sd_m\n0.2,abc,15\n")
    out = tmp_path / "out"
    with pytest.raises(CliError, match=r"rows.csv: line 2.*runout_m"):
        run_fit(str(bad), str(out), profile=PROFILE)
    with pytest.raises(CliError, match="--effect fragmentation: effects are fitted with "
                                       "--model crsp only"):
        run_fit(DATA, str(out), effects=("fragmentation",))
    assert not out.exists()


@pytest.mark.parametrize("value", ["0", "-5", "nan", "inf"])
def test_a_dem_time_that_is_not_a_positive_time_is_refused(tmp_path, capsys, value):
    from calib.fit import main

    out = tmp_path / "out"
    rc, _, err = run_cli(main, [DATA, "--model", "dem", f"--dem-max-time-s={value}",
                                "--out", str(out), "--no-progress"], capsys)
    assert rc == 2, err
    assert f"--dem-max-time-s: expected a positive time, got {float(value):g}" in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists()


def _dem_run_of_fit(argv, monkeypatch):
    """The ``DemRun`` of the DEM forward model ``calib.fit argv`` makes (the fit is
    stopped once it is made)."""
    import calib.inference.calibrate as calibrate
    from calib.fit import build_parser, run_fit, run_options

    class Made(Exception):
        pass

    def made(forward, *args, **kwargs):
        raise Made(forward.run)

    monkeypatch.setattr(calibrate, "calibrate", made)
    with pytest.raises(Made) as exc:
        run_fit(**run_options(build_parser().parse_args(argv)))
    return exc.value.args[0]


def test_the_dem_runs_the_sites_simulated_time(tmp_path, monkeypatch):
    """Without --dem-max-time-s the DEM runs the site file's dem_max_time_s
    (Postignano's 200 s); the option overrides it; a profile whose site file gives
    none runs the default 150 s."""
    import shutil

    assert _dem_run_of_fit([DATA, "--model", "dem", "--out", str(tmp_path / "a")],
                           monkeypatch).max_time_s == 200.0
    assert _dem_run_of_fit([DATA, "--model", "dem", "--dem-max-time-s", "170", "--out",
                            str(tmp_path / "b")], monkeypatch).max_time_s == 170.0
    shutil.copy(DATA, tmp_path / "rows.csv")
    shutil.copy("data/postignano_profile.csv", tmp_path / "rows_profile.csv")
    shutil.copy("data/postignano_materials.csv", tmp_path / "rows_materials.csv")
    assert _dem_run_of_fit([str(tmp_path / "rows.csv"), "--model", "dem", "--out",
                            str(tmp_path / "c")], monkeypatch).max_time_s == 150.0


def test_the_dem_is_fitted_with_the_simulated_time_it_is_given(tmp_path, monkeypatch):
    """--dem-max-time-s reaches the DEM forward model the fit runs (whose ``run``
    calibration.json records as dem.run, read back by calib.validate and
    calib.hazard: tests/test_calibration_file.py); the fit is stopped once the
    forward model is made."""
    import calib.inference.calibrate as calibrate
    from calib.fit import build_parser, run_fit, run_options

    class Made(Exception):
        pass

    def made(forward, *args, **kwargs):
        raise Made(forward.run)

    monkeypatch.setattr(calibrate, "calibrate", made)
    args = build_parser().parse_args([DATA, "--model", "dem", "--dem-max-time-s", "210",
                                      "--out", str(tmp_path / "out")])
    with pytest.raises(Made) as exc:
        run_fit(**run_options(args))
    assert exc.value.args[0].max_time_s == 210.0
    assert exc.value.args[0].stiffness_scale == 0.01  # the rest as the default
