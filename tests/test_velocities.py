"""Passage speeds at stations as a second observation type: the table, its
likelihood, the solver output behind it, and the two commands that use it."""

from __future__ import annotations

import json
import os

import jax
import numpy as np
import pytest
from cli_run import run_cli, run_module

from calib.files.observations import ObservationError, load_velocities
from calib.inference.likelihood import V_MAX_M_S, VELOCITY_EPS, velocity_log_likelihood
from calib.model.forward import CrspForward
from solvers.profile import load_profile

PROFILE_CSV = "data/postignano_profile.csv"
PROFILE = load_profile(PROFILE_CSV)
HEADER = "station_x_m,block_size_m,velocity_m_s,velocity_sd_m_s,source\n"


_cli = run_module


def test_load_velocities_reads_rows_and_stations(tmp_path):
    p = tmp_path / "v.csv"
    p.write_text(HEADER + "110,0.5,12.5,1,video\n60,2.0,20,0.5,video\n110,2.0,25,1,radar\n")
    v = load_velocities(p)
    assert v.n_obs == 3 and v.source == ("video", "video", "radar")
    np.testing.assert_array_equal(v.stations_m, [60.0, 110.0])
    np.testing.assert_array_equal(v.station_index, [1, 0, 1])
    np.testing.assert_array_equal(v.velocity_sd_m_s, [1.0, 0.5, 1.0])


@pytest.mark.parametrize("body, needle", [
    ("station_x_m,block_size_m,velocity_m_s\n110,1,10\n", "missing column 'velocity_sd_m_s'"),
    (HEADER + "110,1,10,1,a\n110,1,-3,1,b\n", "line 3, column 'velocity_m_s'"),
    (HEADER + "110,1,10,0,a\n", "line 2, column 'velocity_sd_m_s'"),
    (HEADER + "110,big,10,1,a\n", "line 2, column 'block_size_m': expected a number"),
    (HEADER + ",1,10,1,a\n", "line 2, column 'station_x_m'"),
    (HEADER, "no observation rows"),
    ("", "empty file"),
])
def test_load_velocities_names_file_line_and_column(tmp_path, body, needle):
    p = tmp_path / "v.csv"
    p.write_text(body)
    with pytest.raises(ObservationError) as e:
        load_velocities(p)
    assert str(p) in str(e.value) and needle in str(e.value)


def test_velocity_likelihood_by_hand_conditional_on_passing():
    u = np.array([10.0, 12.0, 15.0, np.nan])  # the 4th block did not pass
    got = float(velocity_log_likelihood(jax.numpy.asarray(u[None]), jax.numpy.array([11.0]),
                                        jax.numpy.array([1.0]))[0])
    passed = u[:3]
    h = max(0.9 * np.std(passed, ddof=1) * 3 ** -0.2, 0.1)
    s2 = 1.0 + h**2
    kde = np.mean(np.exp(-0.5 * (11.0 - passed) ** 2 / s2) / np.sqrt(2 * np.pi * s2))
    assert got == pytest.approx(np.log((1 - VELOCITY_EPS) * kde + VELOCITY_EPS / V_MAX_M_S))
    # no simulated block passes: only the defensive uniform is left, finite
    none = float(velocity_log_likelihood(jax.numpy.full((1, 4), np.nan), jax.numpy.array([11.0]),
                                         jax.numpy.array([1.0]))[0])
    assert none == pytest.approx(np.log(VELOCITY_EPS / V_MAX_M_S))


@pytest.mark.slow  # 31 s
def test_crsp_simulate_gives_the_runouts_and_speeds_of_blocks_that_pass():
    fw = CrspForward(PROFILE, np.array([0.2, 2.0]), 24, jax.random.key(3),
                     stations_x_m=(60.0, 200.0))
    theta = np.array([[0.41, 0.87, 0.4], [0.45, 0.95, 0.3]])
    runs, speeds = fw.simulate(theta)
    assert runs.shape == (2, 2, 24) and speeds.shape == (2, 2, 2, 24)
    plain = CrspForward(PROFILE, np.array([0.2, 2.0]), 24, jax.random.key(3)).runouts(theta)
    np.testing.assert_allclose(runs, plain, atol=1e-6)  # stations do not change the motion
    assert np.all(np.isfinite(speeds[:, :, 0])) and np.all(speeds[:, :, 0] > 0)
    # blocks start at the first vertex (x = 0), so the runout is the final abscissa:
    # a block passes 200 m exactly when it ends beyond it
    passed = np.isfinite(speeds[:, :, 1])
    np.testing.assert_array_equal(passed, runs > 200.0)
    assert passed.any() and (~passed).any()
    r, v = fw.replicate_sims(theta[0], 3, jax.random.key(9))
    assert r.shape == (3, 2, 24) and v.shape == (3, 2, 2, 24)
    np.testing.assert_array_equal(r, fw.replicates(theta[0], 3, jax.random.key(9)))


@pytest.fixture(scope="module")
def belt_with_speeds(tmp_path_factory):
    out = tmp_path_factory.mktemp("vel")
    proc = _cli("calib.synth", "--effect", "vegetation_belt", "--n-obs", "24", "--seed", "21",
                "--profile", PROFILE_CSV, "--velocity-stations-m", "110", "--n-velocity", "12",
                "--out", str(out / "s.csv"))
    return proc, out


# slow: synthetic rows with speeds, 23 s; the default run keeps the speeds' bad-input refusals
@pytest.mark.slow
def test_synth_writes_speeds_that_hide_the_effect(belt_with_speeds):
    proc, out = belt_with_speeds
    assert proc.returncode == 0, proc.stderr
    v = load_velocities(out / "s_velocities.csv")
    assert v.n_obs == 12 and set(v.station_x_m) == {110.0}
    assert sorted(set(v.block_size_m)) == [0.2, 0.4, 0.7, 1.0, 1.4, 2.0]
    text = (out / "s_velocities.csv").read_text()
    assert "belt" not in text and "vegetation" not in text
    truth = json.loads((out / "s.truth.json").read_text())
    assert truth["velocity_stations_m"] == [110.0] and truth["n_velocity"] == 12


@pytest.mark.parametrize("args, needle", [
    (["--velocity-stations-m", "400"], "outside the profile"),
    (["--velocity-stations-m", "x"], "--velocity-stations-m"),
    (["--velocity-stations-m", "110", "--n-velocity", "0"], "--n-velocity"),
    (["--velocity-stations-m", "110", "--model", "dem"], "CRSP only"),
    (["--velocity-stations-m", "110", "--velocity-sd-m-s", "0"], "--velocity-sd-m-s"),
])
def test_synth_bad_velocity_input_is_one_line_exit_2(tmp_path, args, needle, capsys):
    from calib.synth import main

    rc, _, err = run_cli(main, ["--effect", "none", "--profile", PROFILE_CSV, *args,
                                "--out", str(tmp_path / "s.csv")], capsys)
    assert rc == 2
    assert needle in err and len(err.strip().splitlines()) == 1, err
    assert os.listdir(tmp_path) == []


@pytest.mark.slow  # a quick `calib.discover` with speeds, 31 s
def test_discover_scores_the_speeds_with_every_candidate(belt_with_speeds):
    _, out = belt_with_speeds
    proc = _cli("calib.discover", str(out / "s.csv"), "--quick", "--velocities",
                str(out / "s_velocities.csv"), "--effects", "vegetation_belt",
                "--out", str(out / "d"), "--no-progress")
    assert proc.returncode == 0, proc.stderr
    r = json.loads((out / "d" / "discovery.json").read_text())
    assert r["n_velocity_observations"] == 12 and r["velocity_stations_m"] == [110.0]
    belt = next(c for c in r["candidates"] if c["effect"] == "vegetation_belt")
    assert np.isfinite(belt["delta_velocity_rows"])
    assert "12 passage speeds at 110 m" in proc.stdout
    assert "from the passage speeds: vegetation_belt" in proc.stdout


@pytest.mark.parametrize("extra, body, needle", [
    ([], HEADER + "110,1,10,1,a\n500,1,10,1,a\n", "line 3, column 'station_x_m'"),
    ([], HEADER + "110,1,10,-1,a\n", "column 'velocity_sd_m_s'"),
    (["--model", "dem"], HEADER + "110,1,10,1,a\n", "crsp model only"),
])
def test_discover_bad_velocities_is_one_line_exit_2(tmp_path, extra, body, needle, capsys):
    """``main`` in this process: a refusal costs no interpreter start."""
    from calib.discover import main

    p = tmp_path / "v.csv"
    p.write_text(body)
    out = tmp_path / "d"
    rc, _, err = run_cli(main, ["data/postignano.csv", "--velocities", str(p), *extra,
                                "--out", str(out), "--no-progress"], capsys)
    assert rc == 2
    assert needle in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_discover_refuses_speeds_for_a_model_that_cannot_record_them():
    from calib.discovery.dem_candidates import dem_candidates
    from calib.discovery.discrepancy import discover
    from calib.files.observations import Observations, Velocities
    from calib.inference.budget import DISCOVERY_PRESETS as PRESETS

    obs = Observations.points(np.array([0.5, 2.0]), np.array([120.0, 200.0]), 10.0)
    vel = Velocities(np.array([110.0]), np.array([1.0]), np.array([20.0]), np.array([1.0]),
                     ("x",))
    with pytest.raises(ValueError, match="cannot record passage speeds"):
        discover(dem_candidates(PROFILE, ["none"]), obs, PROFILE, jax.random.key(0),
                 PRESETS["dem-quick"], velocities=vel)
