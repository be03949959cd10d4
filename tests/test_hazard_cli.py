"""``python -m calib.hazard``: outputs, same seed -> same bytes, two host devices ->
same bytes, and bad input -> one line, exit 2, nothing written."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from test_hazard_fixtures import posterior_rows, write_calibration

from calib.hazard.__main__ import main

# the static shapes of test_hazard.py's small run (2 sizes, one chunk of 400 blocks, 31
# stations): in one pytest process the in-process runs reuse its compiled pool
SMALL = ["--n-posterior", "3", "--n-blocks", "400", "--block-sizes-m", "0.5,2.0",
         "--stations-m", "0:300:10", "--no-progress"]
OUTPUTS = ("exceedance.csv", "hazard_table.csv", "exceedance.png", "envelopes.png",
           "summary.txt")


def _subprocess(args, env_extra=None):
    env = dict(os.environ)
    env.update(env_extra or {})
    return subprocess.run([sys.executable, "-m", "calib.hazard", *args], capture_output=True,
                          text=True, env=env)


@pytest.fixture(scope="module")
def cal_path(tmp_path_factory):
    return write_calibration(tmp_path_factory.mktemp("cal"), crsp_posterior=posterior_rows(50))


class _Out:
    def __init__(self, stdout):
        self.stdout = stdout


@pytest.fixture(scope="module")
def run_a(cal_path, tmp_path_factory):
    """The command run in-process (``main``); its exit status in a real process is
    checked by the subprocess tests below."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("a")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main([cal_path, *SMALL, "--release-rate-per-year", "0.2", "--out", str(out)]) == 0
    return out, _Out(buf.getvalue())


def test_a_library_run_is_the_commands_run(cal_path, run_a):
    """``run_hazard`` with its defaults, on the command's calibration, draws, sizes,
    stations, block count and seed, simulates the command's compiled program (both
    use ``HAZARD_SETTINGS``) and counts the same blocks at every station."""
    from calib.hazard import draw_parameters, load_calibration, run_hazard
    from calib.hazard._units import _slotted_chunk
    from solvers import load_profile

    out, _ = run_a
    cal = load_calibration(cal_path, "crsp")
    n_programs = _slotted_chunk._cache_size()
    counts = run_hazard(cal, draw_parameters(cal, 3, 0), load_profile(cal.profile_csv),
                        [0.5, 2.0], np.arange(0.0, 301.0, 10.0), 400, 0)
    assert _slotted_chunk._cache_size() == n_programs
    table = pd.read_csv(out / "hazard_table.csv").sort_values(["block_size_m", "x_m"])
    reached = np.asarray(counts.reach).sum(axis=0)  # (sizes, stations), over the draws
    np.testing.assert_array_equal(table["n_blocks_reached"].to_numpy(), reached.ravel())


def _read(folder, name):
    with open(os.path.join(folder, name), "rb") as fh:
        return fh.read()


def test_cli_writes_tables_figures_and_summary(run_a):
    out, r = run_a
    for name in OUTPUTS:
        assert os.path.getsize(out / name) > 0, name
    assert not [f for f in os.listdir(out) if f.startswith(".tmp-")]
    exc = pd.read_csv(out / "exceedance.csv")
    assert list(exc.columns) == ["model", "block_size_m", "x_m", "p_exceed_mean",
                                 "p_exceed_q05", "p_exceed_q50", "p_exceed_q95"]
    assert len(exc) == 2 * 31  # 2 sizes x 31 stations (the road at 230 m among them)
    table = pd.read_csv(out / "hazard_table.csv")
    for col in ("reach_prob_mean", "n_blocks_reached", "energy_p50_kJ", "energy_p95_kJ",
                "energy_p99_kJ",
                "bounce_height_p95_m", "velocity_p95_m_s", "p_E_gt_30kJ_given_reach",
                "p_E_gt_300kJ_given_reach", "intensity_class", "freq_reach_per_yr",
                "freq_E_gt_30kJ_per_yr", "freq_E_gt_300kJ_per_yr", "hazard_level",
                "p_left_profile", "p_unfinished"):
        assert col in table.columns, col
    assert set(table.x_m) >= {230.0}
    assert "P(reach road)" in r.stdout and "1 device(s)" in r.stdout
    assert _read(out, "summary.txt").decode().strip() in r.stdout


def test_same_seed_same_bytes_other_seed_differs(cal_path, run_a, tmp_path, capsys):
    out_a, _ = run_a
    assert main([cal_path, *SMALL, "--release-rate-per-year", "0.2", "--out",
                 str(tmp_path / "b")]) == 0
    assert main([cal_path, *SMALL, "--release-rate-per-year", "0.2", "--seed", "1", "--out",
                 str(tmp_path / "c")]) == 0
    capsys.readouterr()
    for name in ("exceedance.csv", "hazard_table.csv"):
        assert _read(out_a, name) == _read(tmp_path / "b", name), name
    assert _read(out_a, "hazard_table.csv") != _read(tmp_path / "c", "hazard_table.csv")


@pytest.mark.slow  # an equivalence of device counts, 15 s: run with -m slow
def test_two_host_devices_give_the_same_bytes(cal_path, run_a, tmp_path):
    out_a, _ = run_a
    r = _subprocess([cal_path, *SMALL, "--release-rate-per-year", "0.2", "--out",
                     str(tmp_path)],
                    {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"})
    assert r.returncode == 0, r.stderr  # a real process: exit status 0
    assert "2 device(s)" in r.stdout
    for name in ("exceedance.csv", "hazard_table.csv", "summary.txt"):
        assert _read(out_a, name) == _read(tmp_path, name), name


# ------------------------------------------------------------------ bad input

def _bad_files(tmp_path):
    """name -> (calibration path, extra args, expected text in the error)."""
    (tmp_path / "ok").mkdir()
    cases = {"ok": write_calibration(tmp_path / "ok", crsp_posterior=posterior_rows(5))}
    (tmp_path / "bad.json").write_text('{"schema": "rockfall-calibration/1",\n "crsp": [}')
    (tmp_path / "schema.json").write_text(json.dumps({"schema": "other/2"}))
    (tmp_path / "dem_only").mkdir()
    cases["dem_only"] = write_calibration(tmp_path / "dem_only", crsp=None)
    (tmp_path / "kn").mkdir()
    cases["kn"] = write_calibration(tmp_path / "kn", crsp=(1.4, 0.87, 2.0))
    (tmp_path / "post").mkdir()
    rows = posterior_rows(6)
    cases["post"] = write_calibration(tmp_path / "post", crsp_posterior=rows)
    text = (tmp_path / "post" / "crsp_posterior.csv").read_text().splitlines()
    text[3] = "0.4,abc,2.0"  # line 4 of the file, column Kt
    (tmp_path / "post" / "crsp_posterior.csv").write_text("\n".join(text) + "\n")
    (tmp_path / "alpha").mkdir()
    cases["alpha"] = write_calibration(tmp_path / "alpha", dem=(0.0, 0.5))
    (tmp_path / "release").mkdir()
    cases["release"] = write_calibration(tmp_path / "release")
    doc = json.loads((tmp_path / "release" / "calibration.json").read_text())
    doc["release_x_m"] = 400.0  # a release the fit's profile does not reach
    (tmp_path / "release" / "calibration.json").write_text(json.dumps(doc))
    return cases


@pytest.fixture
def bad(tmp_path):
    return _bad_files(tmp_path)


@pytest.mark.parametrize("case, extra, needle", [
    ("missing.json", [], "missing.json: file not found"),
    ("bad.json", [], "bad.json: line 2, column"),
    ("schema.json", [], "key 'schema'"),
    ("dem_only", ["--model", "crsp"], "no 'crsp' section"),
    ("kn", [], "crsp.Kn.map: 1.4 outside"),
    ("post", ["--n-posterior", "3"], "crsp_posterior.csv: line 4, column Kt"),
    ("ok", ["--n-posterior", "6"], "has only 5 rows"),
    ("alpha", ["--model", "dem", "--n-posterior", "1"], "dem.alpha_law.a.map: 0 outside (0"),
    ("ok", ["--stations-m", "0:400:10"], "outside the profile"),
    ("ok", ["--stations-m", "a,b"], "--stations-m"),
    ("ok", ["--block-sizes-m", "0.5,-1"], "--block-sizes-m: sizes must be positive"),
    ("ok", ["--block-sizes-m", "0.5,x"], "--block-sizes-m"),
    ("ok", ["--n-blocks", "0"], "--n-blocks: expected a positive count"),
    ("ok", ["--n-posterior", "-2"], "--n-posterior: expected a positive count"),
    ("ok", ["--release-rate-per-year", "0"], "--release-rate-per-year"),
    ("ok", ["--dem-stiffness-scale", "1.5"],
     "--dem-stiffness-scale: expected a value in (0, 1], got 1.5"),
    ("ok", ["--dem-max-time-s", "0"], "--dem-max-time-s: expected a positive time, got 0"),
    ("ok", ["--road-x-m", "400"], "--road-x-m 400"),
    ("ok", ["--release-x-m", "400"], "--release-x-m 400: the release lies outside the profile"),
    ("ok", ["--release-x-m", "nan"], "--release-x-m nan: the release lies outside the profile"),
    ("ok", ["--release-x-m", "240", "--road-x-m", "230"],
     "--road-x-m 230: the station of interest lies at or above the release at x = 240 m"),
    ("release", [], "calibration.json: release_x_m 400: the release lies outside the profile "
                    "[0, 300) m"),
    ("ok", ["--bogus"], "unrecognized arguments"),
])
def test_bad_input_one_line_exit_2_nothing_written(bad, tmp_path, capsys, case, extra, needle):
    if case in bad:
        path = bad[case]
    else:
        path = str(tmp_path / case)
    out = tmp_path / "out"
    sizes = [] if "--n-blocks" in extra else ["--n-blocks", "5"]
    with pytest.raises(SystemExit) as exc:
        main([path, *extra, *sizes, "--no-progress", "--out", str(out)])
    assert exc.value.code == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and needle in err[0], err
    assert not out.exists()


def test_a_typed_release_past_the_station_names_the_flag(bad, tmp_path, capsys):
    """``--release-x-m 250`` on the Postignano profile releases below its station of
    interest (230 m, from the site file): the one line names the flag the user
    typed and its value, the station and where it came from, and the profile's
    range (it used to open with the site file, which is not at fault)."""
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        main([bad["ok"], "--release-x-m", "250", "--n-blocks", "5", "--no-progress",
              "--out", str(out)])
    assert exc.value.code == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1, err
    assert err[0].startswith("python -m calib.hazard: error: --release-x-m 250: "), err[0]
    assert "station of interest at x = 230 m" in err[0]
    assert "postignano_site.json: station_of_interest.x_m" in err[0]
    assert "the profile spans [0, 300) m" in err[0]
    assert not out.exists()


def test_bad_input_exit_status_in_a_real_process(tmp_path):
    out = tmp_path / "out"
    r = _subprocess([str(tmp_path / "nope.json"), "--out", str(out)])
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "nope.json: file not found" in r.stderr
    assert not out.exists() and r.stdout == ""


def test_design_values_are_numbers_where_blocks_pass(run_a):
    out, _ = run_a
    t = pd.read_csv(out / "hazard_table.csv")
    passed = t[t.reach_prob_mean > 0]
    assert len(passed) > 0
    for col in ("energy_p50_kJ", "energy_p95_kJ", "energy_p99_kJ", "velocity_p95_m_s"):
        assert np.all(np.isfinite(passed[col])), col
    assert np.all(passed.energy_p50_kJ <= passed.energy_p95_kJ)
    assert np.all(passed.energy_p95_kJ <= passed.energy_p99_kJ)
    assert np.all(passed.energy_p95_kJ_q05 <= passed.energy_p95_kJ_q95)


def test_release_abscissa_is_an_option(cal_path, run_a, tmp_path, capsys):
    """``--release-x-m`` releases every block there (a field site's release area
    is rarely the profile's first vertex): stations at or above it are not
    reached (undefined), the rest are, and the summary says where the blocks
    started. Without it the calibration's release is used (the first vertex
    for this file)."""
    out = tmp_path / "rel"
    assert main([cal_path, *SMALL, "--release-x-m", "100", "--out", str(out)]) == 0
    summary = (out / "summary.txt").read_text()
    assert "released at x = 100 m" in summary
    assert "released at x = 0 m" in (run_a[0] / "summary.txt").read_text()
    table = pd.read_csv(out / "hazard_table.csv")
    assert table[table.x_m <= 100.0].reach_prob_mean.isna().all()
    assert table[table.x_m > 100.0].reach_prob_mean.notna().all()
    exc = pd.read_csv(out / "exceedance.csv")
    assert (exc[exc.x_m <= 100.0].p_exceed_mean == 1.0).all()  # every block stops beyond
    base = pd.read_csv(run_a[0] / "exceedance.csv")
    below = exc.x_m > 100.0
    assert not np.allclose(base[below].p_exceed_mean, exc[below].p_exceed_mean)
