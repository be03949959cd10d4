"""``python -m calib.power``: the detection-rate table, seed parsing, resuming,
and bad input (one line, exit 2, nothing written)."""

from __future__ import annotations

import json
import os

import pandas as pd
import pytest
from cli_run import run_module

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
])
def test_power_bad_input_is_one_line_exit_2_nothing_written(tmp_path, args, needle):
    out = tmp_path / "pw"
    r = _cli("--profile", PROFILE, *args, "--out", str(out), "--no-progress")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and lines[0].startswith("python -m calib.power")
    assert not out.exists()
