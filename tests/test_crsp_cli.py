"""CRSP command line: output file, summary, and one-line errors with exit 2."""

import os

import pandas as pd
import pytest
from cli_run import run_cli, run_module

from solvers.cli import RUN_COLUMNS, station_column_names

PROFILE = "data/postignano_profile.csv"


def _run(*args):
    return run_module("solvers.crsp", "--no-progress", *args)


def test_cli_writes_one_row_per_block(tmp_path):
    """One row per block, the run columns, then each station's columns. Four
    stations and 64 blocks: on 2 cores the compiled program of
    ``tests/test_crsp.py::test_station_records_match_per_block_passage`` and of the
    no-barrier runs of ``tests/test_crsp_barrier.py`` (the run's compilation cache
    holds it when one of them ran first: 15 s -> 6 s)."""
    out = tmp_path / "runouts.csv"
    r = _run("--profile", PROFILE, "--n-blocks", "64", "--block-size-m", "1", "--Kn", "0.41",
             "--Kt", "0.87", "--roughness-m", "2.0", "--seed", "0", "--out", str(out),
             "--stations-m", "110,170,200,230")
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip() == ""
    df = pd.read_csv(out)
    assert len(df) == 64
    assert list(df.columns[:9]) == [*RUN_COLUMNS, "n_impacts", "n_events"]
    assert (df.block_size_m == 1.0).all() and (df.fragment == 0).all()
    # station columns: the names python -m solvers.dem writes too (energy per block here)
    names = [*station_column_names(110).values(), *station_column_names(230).values()]
    assert names == ["passed_110m", "energy_kJ_110m", "velocity_m_s_110m", "bounce_height_m_110m",
                     "passed_230m", "energy_kJ_230m", "velocity_m_s_230m", "bounce_height_m_230m"]
    middle = [*station_column_names(170).values(), *station_column_names(200).values()]
    assert list(df.columns[-16:]) == [*names[:4], *middle, *names[4:]]
    assert "median" in r.stdout and "blocks/s" in r.stdout


def test_radius_is_read_as_the_diameter(capsys):
    """``--radius-m`` (deprecated, one release) gives the size as the radius r:
    the command reads d = 2 r, and the sphere it simulates has radius d / 2."""
    from solvers.crsp.__main__ import build_parser

    args = build_parser().parse_args(["--profile", PROFILE, "--radius-m", "0.5", "--out", "o"])
    assert args.block_size_m == 1.0
    assert "--radius-m is deprecated" in capsys.readouterr().err


@pytest.mark.parametrize("args, needle", [
    (["--profile", "missing.csv"], "missing.csv: file not found"),
    (["--profile", PROFILE, "--n-blocks", "0"], "--n-blocks must be positive"),
    (["--profile", PROFILE, "--block-size-m", "-1"], "--block-size-m"),
    (["--profile", PROFILE, "--Kn", "1.4"], "restitution"),
    (["--profile", PROFILE, "--stations-m", "400"], "outside the profile"),
    (["--profile", PROFILE, "--stations-m", "a,b"], "--stations-m"),
    (["--profile", PROFILE, "--release-x-m", "300"], "--release-x-m"),
    (["--profile", PROFILE, "--bogus"], "unrecognized arguments"),
])
def test_cli_bad_arguments_one_line_exit_2(tmp_path, args, needle, capsys):
    """``main`` in this process (a real process's exit status:
    ``test_bad_arguments_exit_2_in_a_real_process``)."""
    from solvers.crsp.__main__ import main

    out = tmp_path / "o.csv"
    rc, _, err = run_cli(main, ["--no-progress", *args, "--out", str(out)], capsys)
    assert rc == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], err
    assert not os.path.exists(out)


def test_bad_arguments_exit_2_in_a_real_process(tmp_path):
    out = tmp_path / "o.csv"
    r = _run("--profile", PROFILE, "--n-blocks", "0", "--out", str(out))
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--n-blocks must be positive" in lines[0], r.stderr
    assert not os.path.exists(out)
