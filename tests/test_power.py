"""``python -m calib.power``: the detection-rate table, seed parsing, resuming,
runs dispatched to a local cluster of processes (``solvers.dispatch``: the
serial run's records, resuming, a failed run named in one line), and bad input
(one line, exit 2, nothing written)."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pandas as pd
import pytest
from cli_run import run_cli, run_module

from calib.discovery.power_study import detection_table
from calib.power import parse_seeds
from solvers.cli import CliError

PROFILE = "data/postignano_profile.csv"


def _cli(*args):
    return run_module("calib.power", *args)


def test_power_needs_a_profile(tmp_path):
    """No site is the default slope: without --profile the command says so in one
    line (exit 2), and its --help shows an example that names one."""
    r = _cli("--effects", "none", "--out", str(tmp_path / "pw"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "required: --profile" in r.stderr
    assert "--profile data/postignano_profile.csv" in _cli("--help").stdout


def test_parse_seeds_lists_and_ranges():
    assert parse_seeds("3001-3003") == [3001, 3002, 3003]
    assert parse_seeds("4, 9,1") == [4, 9, 1]
    for bad in ("5-2", "a,b", ",", "1-x"):
        with pytest.raises(CliError):
            parse_seeds(bad)


def test_detection_table_counts_rates_and_exact_intervals():
    runs = [{"effect": "fragmentation", "strength": 1.0, "n_obs": 60, "seed": k,
             "named": named, "gains": {"fragmentation": [g, 2.0], "vegetation_belt": [0.0, 1.0]}}
            for k, (named, g) in enumerate([("fragmentation", 10.0), ("none", 2.0),
                                            ("fragmentation", 12.0), ("vegetation_belt", 1.0)])]
    runs += [{"effect": "none", "strength": 1.0, "n_obs": 60, "seed": 9, "named": "none",
              "gains": {"fragmentation": [0.5, 1.0]}}]
    table = {c["effect"]: c for c in detection_table(runs)}
    f = table["fragmentation"]
    assert (f["runs"], f["named_right"], f["rate"]) == (4, 2, 0.5)
    assert f["named"] == {"none": 1, "fragmentation": 2, "vegetation_belt": 1}
    assert f["median_gain_nats"] == pytest.approx(6.0)  # median of 10, 2, 12, 1
    assert f["median_gain_se"] == pytest.approx(3.0)
    # Clopper-Pearson 90 % for 2 of 4: the 5 % and 95 % beta quantiles
    from scipy.stats import beta

    assert f["rate_q05"] == pytest.approx(beta.ppf(0.05, 2, 3))
    assert f["rate_q95"] == pytest.approx(beta.ppf(0.95, 3, 2))
    n = table["none"]
    assert (n["named_right"], n["rate"], n["median_gain_nats"]) == (1, 1.0, None)


def test_detection_table_counts_the_folds_and_runs_the_khat_bar_flags():
    """Per cell: every candidate's first-step folds, those above the bar (as the
    run flagged them), those above 0.7 (a NaN k-hat counts as above), the runs
    with a flagged fold and the right verdicts of the others; None for records
    without k-hats (older studies)."""
    def run(seed, named, khats, flagged):
        return {"effect": "vegetation_belt", "strength": 1.0, "n_obs": 60, "seed": seed,
                "named": named, "gains": {"vegetation_belt": [12.0, 5.0]},
                "khat_by_fold": khats, "psis_flagged_folds": flagged}

    clean = {"none": [0.1, 0.2, 0.3, 0.4, 0.5], "vegetation_belt": [0.2] * 5}
    bad = {"none": [1.2, 2.4, 0.3, None, 0.5], "vegetation_belt": [0.66, 0.2, 0.2, 0.2, 0.2]}
    runs = [run(1, "vegetation_belt", clean, {"none": [], "vegetation_belt": []}),
            run(2, "vegetation_belt", bad, {"none": [0, 1, 3], "vegetation_belt": [0]}),
            run(3, "none", clean, {"none": [], "vegetation_belt": []})]
    c = detection_table(runs)[0]
    assert (c["folds"], c["folds_above_bar"], c["folds_khat_above_0_7"]) == (30, 4, 3)
    assert (c["runs_warned"], c["named_right"], c["named_right_unwarned"]) == (1, 2, 1)
    old = [{k: v for k, v in r.items() if k not in ("khat_by_fold", "psis_flagged_folds")}
           for r in runs]
    c = detection_table(old)[0]
    assert c["folds"] is None and c["runs_warned"] is None and c["named_right"] == 2
    assert c["folds_fresh_draws"] is None


def test_detection_table_counts_the_folds_scored_on_fresh_draws():
    """``folds_fresh_draws``: the folds of a cell's runs scored on fresh draws of
    their training posterior; None where a run's record lacks them."""
    def run(seed, fresh):
        r = {"effect": "none", "strength": 1.0, "n_obs": 60, "seed": seed, "named": "none",
             "gains": {}, "khat_by_fold": {"none": [0.1] * 5, "fragmentation": [0.2] * 5},
             "psis_flagged_folds": {"none": [], "fragmentation": []}}
        return r if fresh is None else r | {"fresh_draw_folds": fresh}

    runs = [run(1, {"none": [0, 2], "fragmentation": [4]}),
            run(2, {"none": [], "fragmentation": []})]
    assert detection_table(runs)[0]["folds_fresh_draws"] == 3
    assert detection_table(runs + [run(3, None)])[0]["folds_fresh_draws"] is None


@pytest.mark.slow  # a whole quick power study, 23 s: run with -m slow
def test_power_quick_run_writes_table_and_resumes(tmp_path):
    out = tmp_path / "pw"
    args = ["--profile", PROFILE, "--effects", "none", "--n-obs", "12", "--seeds", "5",
            "--quick", "--no-progress", "--out", str(out)]
    r = _cli(*args)
    assert r.returncode == 0, r.stderr
    df = pd.read_csv(out / "power.csv")
    assert list(df["effect"]) == ["none"] and int(df["runs"][0]) == 1
    doc = json.loads((out / "power.json").read_text())
    assert doc["runs"][0]["named"] in ("none", "size_dissipation", "fragmentation",
                                       "rolling_resistance", "vegetation_belt")
    noise = doc["runs"][0]["loglik_noise_sd_nats"]
    assert set(noise) == set(doc["runs"][0]["ess"]) and all(v > 0 for v in noise.values())
    assert doc["cells"][0]["median_loglik_noise_sd_none_nats"] == noise["none"]
    assert set(doc["runs"][0]["effective_rows"]) == set(doc["runs"][0]["gains"])
    assert doc["budget"] == "crsp-quick"  # the preset's own blocks: no suffix
    (rec,) = os.listdir(out / "runs")
    # a second call finds the finished run and does not redo it
    mtime = os.path.getmtime(out / "runs" / rec)
    r2 = _cli(*args)
    assert r2.returncode == 0, r2.stderr
    assert os.path.getmtime(out / "runs" / rec) == mtime
    assert "none" in r2.stdout and "named right" in r2.stdout


@pytest.mark.parametrize("args,needle", [
    (["--effects", "avalanche"], "--effects: avalanche"),
    (["--strengths", "0"], "--strengths"),
    (["--n-obs", "2.5"], "--n-obs"),
    (["--seeds", "9-1"], "--seeds"),
    (["--sd-m", "-1"], "--sd-m: expected a positive number of metres, got -1"),
    (["--profile", "nope.csv"], "nope.csv"),
    (["--n-blocks", "0"], "--n-blocks"),
    (["--workers", "0"], "--workers: expected a whole number of at least 1, got 0"),
    (["--scheduler", "nowhere"], "--scheduler: no Dask scheduler answers at 'nowhere'"),
    (["--scheduler", "tcp://127.0.0.1:8786", "--serial"], "--scheduler: the cluster has"),
])
def test_power_bad_input_is_one_line_exit_2_nothing_written(tmp_path, args, needle, capsys):
    """``main`` in this process; ``test_power_needs_a_profile`` runs a real one. A
    scheduler that does not answer leaves the process's Dask settings as they were
    (a Client that failed to connect had made itself the scheduler of every later
    Dask computation in the process)."""
    import dask

    from calib.power import main

    before = dask.config.get("scheduler", None)
    out = tmp_path / "pw"
    rc, _, err = run_cli(main, ["--profile", PROFILE, *args, "--out", str(out),
                                "--no-progress"], capsys)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and lines[0].startswith("python -m calib.power")
    assert not out.exists()
    assert dask.config.get("scheduler", None) == before


# ------------------------------------------------ runs dispatched to worker processes

def _stand_in_run(profile, effect, strength, n_obs, seed, sd_m, fit_seed, budget, speeds=None,
                  budget_name=None) -> dict:
    """``one_run`` in miniature: what it names comes from its own seed only; it
    also says which process made it, with how many cores and BLAS threads."""
    if seed == 13:
        raise ValueError(f"no data for seed {seed}")
    x = float(np.random.default_rng(seed).normal())
    return {"effect": effect, "strength": strength, "n_obs": n_obs, "seed": seed,
            "named": effect if x > 0 else "none", "gains": {effect: [x, 1.0]},
            "budget": budget_name, "pid": os.getpid(), "cores": len(os.sched_getaffinity(0)),
            "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS")}


def _without(recs, *keys):
    return [{k: v for k, v in r.items() if k not in keys} for r in recs]


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="needs CPU affinity (Linux)")
def test_two_local_workers_give_the_serial_records_resume_and_name_a_failed_run(
        tmp_path, monkeypatch, capsys):
    """On a LocalCluster of two processes the runs give the serial study's
    records; a run already on disk (a killed study's) is not redone; a failing
    run is named in one line (exit 1, its traceback in a file) after every
    other run is saved, and a re-run finds those. Each worker has its share of
    the cores (affinity and BLAS threads set before the run). The runs are a
    stand-in for ``one_run`` that costs nothing."""
    from calib.discovery import power_study
    from calib.power import main

    monkeypatch.setattr(power_study, "one_run", _stand_in_run)
    serial, cluster = tmp_path / "serial", tmp_path / "cluster"
    args = ["--profile", PROFILE, "--effects", "fragmentation", "--n-obs", "12", "--quick",
            "--no-progress"]
    rc, _, err = run_cli(main, args + ["--seeds", "1-5", "--serial", "--out", str(serial)],
                         capsys)
    assert rc == 0, err
    want = json.loads((serial / "power.json").read_text())["runs"]
    assert {r["pid"] for r in want} == {os.getpid()}
    (first,) = [f for f in os.listdir(serial / "runs") if "_seed1_" in f]
    (cluster / "runs").mkdir(parents=True)
    shutil.copy2(serial / "runs" / first, cluster / "runs" / first)  # finished earlier
    rc, _, err = run_cli(main, args + ["--seeds", "1,2,3,4,5,13", "--workers", "2",
                                       "--out", str(cluster)], capsys)
    assert rc == 1 and err.count("\n") == 1, err
    assert err.startswith("python -m calib.power: error: run fragmentation strength 1 n 12 "
                          "seed 13 failed: ValueError: no data for seed 13; traceback in ")
    (trace,) = [f for f in os.listdir(cluster / "runs") if f.endswith(".error.txt")]
    assert "_seed13_" in trace and "ValueError" in (cluster / "runs" / trace).read_text()
    assert not (cluster / "power.csv").exists()
    rc, _, err = run_cli(main, args + ["--seeds", "1-5", "--workers", "2", "--out",
                                       str(cluster)], capsys)
    assert rc == 0, err
    got = json.loads((cluster / "power.json").read_text())["runs"]
    keys = ("pid", "cores", "blas_threads")
    assert _without(got, *keys) == _without(want, *keys)
    assert got[0] == want[0]  # the run found on disk, not redone
    share = max(1, len(os.sched_getaffinity(0)) // 2)
    assert all(r["pid"] != os.getpid() and r["cores"] == share
               and r["blas_threads"] == str(share) for r in got[1:])


@pytest.mark.slow  # a quick study serially, then on two worker processes
def test_power_on_two_local_workers_matches_the_serial_study_and_resumes(tmp_path, monkeypatch):
    """The same study, run serially and on a LocalCluster of two processes that
    finds one run finished (a killed study): the same records (all but their
    run time) and the same table; the finished run is not redone. Each
    worker's first run is the first of its process, so a run that depended on
    what ran before it in the process would differ from the serial one.

    The compiled programs are shared through JAX's persistent compilation
    cache (it changes no result) so that the workers do not compile again."""
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "xla"))
    monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    args = ["--profile", PROFILE, "--effects", "none", "--n-obs", "12", "--seeds", "5-7",
            "--quick", "--n-blocks", "4", "--no-progress"]
    serial, cluster = tmp_path / "serial", tmp_path / "cluster"
    r = _cli(*args, "--serial", "--out", str(serial))
    assert r.returncode == 0, r.stderr
    (first,) = [f for f in os.listdir(serial / "runs") if "_seed5_" in f]
    (cluster / "runs").mkdir(parents=True)
    shutil.copy2(serial / "runs" / first, cluster / "runs" / first)
    mtime = os.path.getmtime(cluster / "runs" / first)
    r = _cli(*args, "--workers", "2", "--out", str(cluster))
    assert r.returncode == 0, r.stderr
    assert os.path.getmtime(cluster / "runs" / first) == mtime
    a, b = (json.loads((d / "power.json").read_text()) for d in (serial, cluster))
    assert _without(a["runs"], "seconds") == _without(b["runs"], "seconds")
    assert a["cells"] == b["cells"]
    pd.testing.assert_frame_equal(pd.read_csv(serial / "power.csv"),
                                  pd.read_csv(cluster / "power.csv"))
