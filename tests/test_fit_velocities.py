"""Passage speeds in the calibration: ``calib.fit --velocities`` scores each speed
row against the simulated speeds of its entry at its station, in every summed
log-likelihood of the fit (``calib.inference.likelihood.RowLikelihood``), and
records the file; ``calib.discover --velocities`` prints a refit command that
carries them."""

from __future__ import annotations

import argparse
import dataclasses
import json

import jax
import numpy as np
import pytest
from cli_run import run_cli

from calib.files.observations import Observations, Velocities
from calib.inference.likelihood import (
    RowLikelihood,
    VelocityRows,
    velocity_log_likelihood,
)
from calib.model.entries import Entries

PROFILE = "data/postignano_profile.csv"


def _rows():
    obs = Observations.points([0.5, 1.0, 1.0], [120.0, 150.0, 160.0], 5.0)
    vel = Velocities(np.array([110.0, 110.0, 150.0]), np.array([1.0, 0.5, 1.0]),
                     np.array([12.0, 9.0, 4.0]), np.array([1.0, 1.0, 2.0]), ("test",) * 3)
    return obs, vel


def test_the_summed_log_likelihood_counts_the_speed_rows():
    """summed = the runout rows' log-likelihood + each speed row's
    ``velocity_log_likelihood`` against its entry's blocks at its station; the
    speeds are required once there are speed rows; the bootstrap noise takes them."""
    obs, vel = _rows()
    rows = VelocityRows.of(vel, entry=[1, 0, 1])  # entries: 0.5 m, 1.0 m
    lik = RowLikelihood(obs, np.array([0, 1, 1]), rows)
    assert (lik.n_runout, lik.n_rows, lik.stations_m) == (3, 6, (110.0, 150.0))
    rng = np.random.default_rng(0)
    runs = rng.uniform(100, 180, (2, 2, 64))  # (T, S, n)
    speeds = rng.uniform(0, 20, (2, 2, 2, 64))  # (T, S, K, n)
    speeds[..., ::3] = np.nan  # blocks that did not pass
    plain = RowLikelihood(obs, np.array([0, 1, 1]))
    by_hand = plain.summed(runs) + np.array([sum(
        float(velocity_log_likelihood(speeds[t, e, k][None], np.array([v]), np.array([s]))[0])
        for e, k, v, s in zip([1, 0, 1], [0, 0, 1], vel.velocity_m_s, vel.velocity_sd_m_s,
                              strict=True)) for t in range(2)])
    np.testing.assert_allclose(lik.summed(runs, speeds), by_hand, rtol=1e-10)
    assert lik.all_rows(runs, speeds).shape == (2, 6)
    with pytest.raises(ValueError, match="speeds are needed"):
        lik.summed(runs)
    noise = lik.noise_var(runs, speeds)
    assert noise.shape == (2,) and np.all(noise > 0)


def test_speed_rows_are_simulated_at_the_median_release_of_the_rows():
    e = dataclasses.replace(Entries.at_sizes(np.array([0.5, 1.0, 1.0]), 0.0,
                                             density_kg_m3=2700.0),
                            index=np.array([0, 1, 2, 2]), release_x_m=np.array([10.0, 20.0, 40.0]))
    out, entry = e.with_speed_entries([1.0, 0.3, 1.0])
    assert out.n == 5 and np.array_equal(out.index, e.index)
    assert np.array_equal(entry, [4, 3, 4])  # distinct sizes ascending, after the rows'
    np.testing.assert_allclose(out.sizes_m[3:], [0.3, 1.0])
    np.testing.assert_allclose(out.release_x_m[3:], 30.0)  # median of 10, 20, 40, 40
    assert out.density_kg_m3 == 2700.0


def test_the_design_is_scored_with_the_speeds():
    """A fit's first design (``calib.inference.design_waves.Design``) with speed
    rows records every point's passage speeds at the rows' stations, and its
    summed log-likelihood (what the log-likelihood GP that NUTS samples is
    fitted to) is that of the runout rows plus the speed rows."""
    from calib.inference.design_waves import Design
    from calib.model.forward import CrspForward
    from calib.model.priors import CRSP_ROLLING_BOX
    from calib.model.unfinished import UnfinishedTally
    from solvers.profile import load_profile

    obs, vel = _rows()
    entries = Entries.one_per_size(obs, 0.0)
    entries, entry = entries.with_speed_entries(vel.block_size_m)
    rows = VelocityRows.of(vel, entry)
    lik = RowLikelihood(obs, entries.index, rows)
    fw = CrspForward(load_profile(PROFILE), entries, 32, jax.random.key(3), box=CRSP_ROLLING_BOX,
                     stations_x_m=lik.stations_m)
    tally = UnfinishedTally(tuple(map(float, entries.sizes_m)))
    d = Design(fw, lik, lambda stage, runs, *a: tally.add(runs, None, ()), 4, seed=1)
    assert d.v.shape == (4, entries.n, 2, 32)
    runout_only = RowLikelihood(obs, entries.index).summed(d.r)
    speed_part = np.asarray(lik.all_rows(d.r, d.v))[:, 3:].sum(1)
    np.testing.assert_allclose(d.ll, runout_only + speed_part, rtol=1e-10)
    assert np.all(np.abs(speed_part) > 0)
    d.simulate(fw.design_points(2, seed=5))
    assert d.v.shape[0] == d.r.shape[0] == d.ll.shape[0] == 6


@pytest.fixture
def speed_data(tmp_path):
    data = tmp_path / "rows.csv"  # test rows, not observations
    data.write_text("block_size_m,runout_m,runout_sd_m,source\n" + "".join(
        f"{d},{r},10,test row\n" for d, r in zip([0.4, 1.0, 2.0] * 3, [100, 120, 150, 105, 125,
                                                                      160, 95, 115, 140],
                                                 strict=True)))
    speeds = tmp_path / "speeds.csv"
    speeds.write_text("station_x_m,block_size_m,velocity_m_s,velocity_sd_m_s,source\n"
                      "110,1.0,12.0,1,test row\n110,2.0,14.0,1,test row\n")
    return data, speeds


# a whole fit with speeds (tiny budgets), 147 s on 2 cores (2026-12-06), mostly
# compilation; the speeds' design and the refusals stay in the default run
@pytest.mark.slow
def test_fit_with_speeds_runs_bayes_and_records_them(speed_data, tmp_path, capsys,
                                                     monkeypatch):
    """calib.fit --velocities (tiny budgets): Bayesian only, said in a line; the
    calibration file records the speeds' file, count and stations."""
    import calib.inference.calibrate as calibrate
    from calib.fit import main

    # the stage sizes of the main job's end-to-end test (tests/test_calib_fit_cli.py)
    tiny = calibrate.Budget(n_design=16, n_design2=8, n_design3=8, n_blocks_design=32,
                            nuts_warmup=100, nuts_samples=100, nuts_chains=2, refinements=1,
                            n_realisations=8, realisation_waves=0, grad_starts=1,
                            grad_steps=2, grad_k=1, n_blocks_grad=32, n_check=32,
                            n_predictive_draws=4, n_blocks_predictive=32)
    monkeypatch.setattr(calibrate, "presets", lambda model, quick: tiny)
    data, speeds = speed_data
    out = tmp_path / "r"
    rc, text, err = run_cli(main, [
        str(data), "--profile", PROFILE, "--model", "crsp", "--velocities", str(speeds),
        "--out", str(out), "--no-progress"], capsys)
    print(text[-3000:], err[-3000:])
    assert rc == 0, err
    assert "the fit is Bayesian" in text
    assert "fitted with 2 passage speeds at 110 m" in text
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["methods"] == ["bayes"]
    assert doc["velocities"]["csv"] == str(speeds)
    assert doc["velocities"]["n_observations"] == 2
    assert doc["velocities"]["stations_m"] == [110.0]
    assert "velocities" in doc["inputs"]
    assert doc["crsp"]["Kn"]["q05"] is not None


@pytest.mark.parametrize("extra, says", [
    (["--model", "dem"], "--velocities: passage speeds are fitted with --model crsp only"),
    (["--model", "crsp", "--method", "gradient"], "--velocities: the gradient stage fits"),
])
def test_fit_refuses_speeds_it_cannot_fit(speed_data, tmp_path, capsys, extra, says):
    from calib.fit import main

    data, speeds = speed_data
    out = tmp_path / "r"
    rc, text, err = run_cli(main, [str(data), "--profile", PROFILE, "--velocities",
                                   str(speeds), "--out", str(out), *extra], capsys)
    assert rc == 2 and says in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_fit_names_the_bad_speed_row(speed_data, tmp_path, capsys):
    from calib.fit import main

    data, speeds = speed_data
    speeds.write_text("station_x_m,block_size_m,velocity_m_s,velocity_sd_m_s\n"
                      "110,1.0,12.0,1\n900,1.0,3.0,1\n")
    out = tmp_path / "r"
    rc, text, err = run_cli(main, [str(data), "--profile", PROFILE, "--model", "crsp",
                                   "--velocities", str(speeds), "--out", str(out)], capsys)
    assert rc == 2 and f"{speeds}: line 3, column 'station_x_m'" in err, err
    assert not out.exists()


def test_discovery_refit_command_carries_the_speeds():
    from calib.discover import refit_command

    args = argparse.Namespace(data="rows.csv", profile="p.csv", model="crsp",
                              rolling_resistance="profile", release_tolerance_m=1.0,
                              velocities="speeds.csv", seed=0)
    assert refit_command(args, ("vegetation_belt",)) == (
        "python -m calib.fit rows.csv --profile p.csv --model crsp --method both "
        "--rolling-resistance profile --effect vegetation_belt --alpha-law power --seed 0 "
        "--holdout-fraction 0.0 --release-tolerance-m 1.0 --velocities speeds.csv")


def test_the_inputs_carry_the_speeds_checked_on_their_profile(speed_data, tmp_path):
    """``load_inputs`` reads the speeds with the rows and the profile, into the one
    typed ``Inputs`` the fit and discover take; a station off that profile is
    an ``InputError`` by line, whichever command reads it."""
    from calib.files.inputs import InputError, load_inputs

    data, speeds = speed_data
    inputs = load_inputs(str(data), PROFILE, str(tmp_path / "r"), str(speeds))
    assert inputs.speeds.path == str(speeds) and inputs.speeds.n_obs > 0
    assert np.all((inputs.speeds.station_x_m > inputs.profile.x_m[0])
                  & (inputs.speeds.station_x_m < inputs.profile.x_m[-1]))
    assert load_inputs(str(data), PROFILE, str(tmp_path / "r")).speeds is None
    speeds.write_text("station_x_m,block_size_m,velocity_m_s,velocity_sd_m_s\n"
                      "110,1.0,12.0,1\n-5,1.0,3.0,1\n")
    with pytest.raises(InputError, match="line 3, column 'station_x_m'"):
        load_inputs(str(data), PROFILE, str(tmp_path / "r"), str(speeds))
