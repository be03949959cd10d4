"""Field runs as observations (calib/field.py, python -m calib.field) and the
optional field columns of calib/files/observations.py."""

import math
import os

import numpy as np
import pandas as pd
import pytest
from cli_run import run_cli

from calib.field import main
from calib.files.field_runs import (
    FieldError,
    box_diameter_m,
    crsp_shape,
    field_observations,
    load_runs,
    observations_csv_text,
    sphere_diameter_m,
    take_runs,
)
from calib.files.observations import ObservationError, load_observations
from terrain.plan_line import read_profile_trace

RUNS_HEADER = ("run_id,block_id,mass_kg,release_x_m,release_y_m,release_z_m,release_vx_m_s,"
               "release_vy_m_s,release_vz_m_s,stop_x_m,stop_y_m,stop_z_m\n")
BLOCKS = ("block_id,name,mass_kg,size_x_m,size_y_m,size_z_m\n"
          "1,cube,,0.4,0.4,0.4\n"
          "2,plate,60,0.5,0.4,0.1\n")


def _read(path):
    with open(path) as fh:
        return fh.read()


def _profile(tmp_path, x0=0.0):
    """A straight profile along +east from (0, 0), 200 m, with its plan trace."""
    x = np.arange(0.0, 201.0, 10.0)
    lines = ["x_m,z_m,zone,east_m,north_m"]
    lines += [f"{x0 + v:.4f},{100 - 0.3 * v:.4f},{'a' if v < 200 else ''},{v:.4f},0.0000"
              for v in x]
    (tmp_path / "p.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "p_materials.csv").write_text(
        "zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg\na,0.4,0.8,0.5,30,30\n")
    return str(tmp_path / "p.csv")


def _runs(tmp_path, *rows, header=RUNS_HEADER):
    (tmp_path / "runs.csv").write_text(header + "".join(r + "\n" for r in rows))
    (tmp_path / "blocks.csv").write_text(BLOCKS)
    return str(tmp_path / "runs.csv"), str(tmp_path / "blocks.csv")


def _cli(argv, capsys):
    return run_cli(main, argv, capsys)


def test_equivalent_diameters():
    d, rho = 0.7, 2650.0
    mass = rho * math.pi / 6 * d**3
    assert sphere_diameter_m(mass, rho) == pytest.approx(d, rel=1e-12)
    assert sphere_diameter_m(40.0, 2650.0) == pytest.approx(0.30662, abs=1e-5)
    assert box_diameter_m([2.0, 4.0, 8.0]) == pytest.approx(4.0, rel=1e-12)


@pytest.mark.parametrize("size, shape", [
    ((1.0, 1.0, 1.0), "sphere"),
    ((0.37, 0.32, 0.37), "sphere"),      # Tschamut block 1
    ((0.5, 0.3, 0.39), "sphere"),        # block 2: b/a 0.78, c/b 0.77
    ((1.0, 0.5, 0.45), "cylinder"),      # one long axis
    ((1.0, 0.9, 0.3), "disc"),           # flat
    ((1.0, 0.5, 0.2), "disc"),           # bladed: flat wins
    ((0.46, 0.3, 0.2), "disc"),          # Tschamut "Plate": c/b = 2/3 exactly, on the boundary
])
def test_shape_classes(size, shape):
    assert crsp_shape(size) == shape


def test_projection_runout_offsets_and_diameters(tmp_path):
    prof = _profile(tmp_path, x0=5.0)  # x_m starts at 5: abscissae are shifted by 5
    runs, blocks = _runs(
        tmp_path,
        "r1,1,,10,3,0,0.3,0.4,0,90,-4,0",       # mass from blocks: empty there -> dimensions
        "r2,2,50,20,-25,0,,,,130,2,0",           # own mass; no velocity
        "r3,2,,15,0,0,1,2,2,15,0,0")             # mass from blocks (60 kg); runout 0
    x, trace = read_profile_trace(prof)
    np.testing.assert_allclose(trace.north_m, 0.0)
    obs = field_observations(load_runs(runs, blocks), x, trace, density_kg_m3=2500.0,
                             runout_sd_m=3.0, max_offset_m=20.0, source="test")
    r1, r2, r3 = obs
    assert r1["release_x_m"] == pytest.approx(15.0) and r1["runout_m"] == pytest.approx(80.0)
    assert (r1["release_offset_m"], r1["stop_offset_m"]) == pytest.approx((3.0, -4.0))
    assert r1["block_size_m"] == pytest.approx(0.4)          # (a b c)^(1/3) of the cube
    assert r1["release_speed_m_s"] == pytest.approx(0.5)
    assert r1["shape"] == "sphere" and not r1["beyond_max_offset"]
    assert r2["block_size_m"] == pytest.approx((6 * 50 / (math.pi * 2500)) ** (1 / 3))
    assert r2["runout_m"] == pytest.approx(110.0) and r2["beyond_max_offset"]
    assert math.isnan(r2["release_speed_m_s"]) and r2["shape"] == "disc"
    assert r3["mass_kg"] == 60 and r3["runout_m"] == 0 and r3["release_speed_m_s"] == 3.0
    assert r1["source"] == "test: run r1" and r1["runout_sd_m"] == 3.0


def test_cli_writes_observations_that_load_and_warns_about_offsets(tmp_path, capsys):
    prof = _profile(tmp_path)
    runs, blocks = _runs(tmp_path, "r1,1,70,10,3,0,0.3,0.4,0,90,-4,0",
                         "r2,2,50,20,-25,0,,,,130,2,0")
    out = str(tmp_path / "obs.csv")
    rc, stdout, err = _cli([runs, "--blocks", blocks, "--profile", prof, "--out", out], capsys)
    assert rc == 0, err
    assert "warning: 1 of 2 runs" in err and "r2 (25.0 m)" in err and "r1" not in err
    assert "largest lateral offset 25.0 m (run r2)" in stdout
    obs = load_observations(out)
    np.testing.assert_allclose(obs.runout_m, [80.0, 110.0])
    np.testing.assert_allclose(obs.release_x_m, [10.0, 20.0])
    np.testing.assert_allclose(obs.release_speed_m_s, [0.5, np.nan])
    assert list(obs.run_id) == ["r1", "r2"] and list(obs.shape) == ["sphere", "disc"]
    np.testing.assert_allclose(obs.runout_sd_m, 2.0)


def test_release_height_is_the_lowest_point_above_the_profile_ground(tmp_path, capsys):
    """h = z_release - d / 2 - ground(x_release): r1 (the 0.4 m cube) released
    with its centre 0.6 m above the ground at east 10 m (ground 97 m) is 0.4 m
    high; r2, below the ground, is recorded as measured (-1.165 m, counted: the
    profile's error, which the solver draws around); a runs file without the z
    column gives no heights."""
    prof = _profile(tmp_path)
    runs, blocks = _runs(tmp_path, "r1,1,,10,3,97.6,0.3,0.4,0,90,-4,0",
                         "r2,2,50,20,-25,93,,,,130,2,0", "r3,2,50,20,0,,,,,130,2,0")
    out = str(tmp_path / "obs.csv")
    rc, stdout, err = _cli([runs, "--blocks", blocks, "--profile", prof, "--out", out], capsys)
    assert rc == 0, err
    obs = load_observations(out)
    assert obs.release_height_m[1] == pytest.approx(-1.165, abs=1e-3)
    np.testing.assert_allclose(obs.release_height_m[[0, 2]], [0.4, np.nan], atol=1e-9)
    assert "for 2 runs: -1.17 to 0.40 m; 1 releases lie below the profile's ground (by up " \
           "to 1.17 m), recorded as measured (negative)" in stdout
    # the column named off, or absent: no heights
    rc, stdout, err = _cli([runs, "--blocks", blocks, "--profile", prof, "--out", out,
                            "--release-z-col", ""], capsys)
    assert rc == 0 and np.isnan(load_observations(out).release_height_m).all()
    assert "release_height_m" not in stdout
    x, trace = read_profile_trace(prof)
    rows = field_observations(load_runs(runs, blocks), x, trace)  # no profile heights
    assert all(math.isnan(r["release_height_m"]) for r in rows)


@pytest.mark.parametrize("row, needle", [
    ("r1,2,50,90,0,0,,,,10,0,0", "line 2: column 'stop_x_m': the stop of run r1 lies upslope"),
    ("r1,9,,10,0,0,,,,90,0,0", "line 2: column 'block_id': block '9' is not in"),
    ("r1,2,-5,10,0,0,,,,90,0,0", "line 2: column 'mass_kg': expected a positive value"),
    ("r1,2,nan,10,0,0,,,,90,0,0", "line 2: column 'mass_kg': expected a finite number"),
    ("r1,2,abc,10,0,0,,,,90,0,0", "line 2: column 'mass_kg': expected a number"),
    ("r1,2,50,10,0,0,,,,,0,0", "line 2: column 'stop_x_m': missing value"),
    ("r1,2,50,-10,0,0,,,,90,0,0", "the release of run r1 projects to -10.00 m along the"),
    ("r1,2,50,10,0,0,,,,250,0,0", "the stop of run r1 projects to 250.00 m"),
])
def test_bad_runs_exit_2_naming_file_line_and_column(tmp_path, capsys, row, needle):
    prof = _profile(tmp_path)
    runs, blocks = _runs(tmp_path, "r0,2,50,10,0,0,,,,90,0,0", row)
    needle = needle.replace("line 2", "line 3")  # the bad run is the second data row
    out = str(tmp_path / "out" / "obs.csv")
    rc, _, err = _cli([runs, "--blocks", blocks, "--profile", prof, "--out", out], capsys)
    assert rc == 2
    assert err.count("\n") == 1 and needle in err and "runs.csv" in err
    assert not os.path.exists(tmp_path / "out")


@pytest.mark.parametrize("blocks_text, needle", [
    ("block_id,mass_kg\n1,\n", "column 'mass_kg': run r1 has no mass and no dimensions"),
    ("block_id,mass_kg\n1,-3\n", "blocks.csv: line 2: column 'mass_kg': expected a positive"),
    ("block_id,size_x_m,size_y_m,size_z_m\n1,0.3,NaN,0.2\n",
     "blocks.csv: line 2: column 'size_y_m': expected a finite number"),
    ("block_id,size_x_m,size_y_m,size_z_m\n1,0.3,-0.1,0.2\n",
     "blocks.csv: line 2: column 'size_y_m': expected a positive value"),
    ("block_id,size_x_m,size_y_m,size_z_m\n1,0.3,,0.2\n",
     "blocks.csv: line 2: column 'size_y_m': missing value (a block needs all three"),
])
def test_missing_or_bad_mass_and_dimensions_are_refused(tmp_path, blocks_text, needle):
    runs, _ = _runs(tmp_path, "r1,1,,10,0,0,,,,90,0,0")
    (tmp_path / "blocks.csv").write_text(blocks_text)
    with pytest.raises(FieldError) as exc:
        load_runs(runs, str(tmp_path / "blocks.csv"))
    assert needle in str(exc.value)


def test_observation_loader_reads_the_optional_field_columns(tmp_path):
    base = load_observations("data/postignano.csv")  # no field columns: as before
    assert np.isnan(base.release_x_m).all() and list(base.shape) == ["", ""]
    p = tmp_path / "o.csv"
    p.write_text("block_size_m,runout_m,runout_sd_m,shape\n0.3,50,2,cube\n")
    with pytest.raises(ObservationError, match="line 2, column 'shape': expected one of"):
        load_observations(p)
    p.write_text("block_size_m,runout_m,runout_sd_m,release_speed_m_s\n0.3,50,2,-1\n")
    with pytest.raises(ObservationError, match="column 'release_speed_m_s'"):
        load_observations(p)
    # a height below the profile's ground is kept as measured (the raster's error)
    p.write_text("block_size_m,runout_m,runout_sd_m,release_height_m\n0.3,50,2,\n0.3,50,2,-0.1\n")
    np.testing.assert_array_equal(load_observations(p).release_height_m, [np.nan, -0.1])
    p.write_text("block_size_m,runout_m,runout_sd_m,release_height_m\n0.3,50,2,\n0.3,50,2,inf\n")
    with pytest.raises(ObservationError, match="line 3, column 'release_height_m'"):
        load_observations(p)


# ---------------------------------------------------------------- the shipped case

DATA = "data/tschamut2014"


def test_shipped_tschamut_observations_load_and_are_all_62_runs():
    obs = load_observations(f"{DATA}/observations.csv")
    assert obs.n_obs == 62 and len(set(obs.run_id)) == 62
    raw_ids = [line.split(",")[0] for line in _read(f"{DATA}/runs.csv").splitlines()[1:]]
    assert list(obs.run_id) == raw_ids
    assert (obs.runout_m > 0).all() and (obs.runout_sd_m == 2.0).all()
    # three blocks: 40, 69 and 79 kg at 2650 kg/m^3
    np.testing.assert_allclose(obs.sizes_m, sphere_diameter_m([40, 69, 79], 2650.0), atol=1e-4)
    assert set(obs.shape) == {"sphere", "disc"}
    assert np.isfinite(obs.release_x_m).all() and np.isfinite(obs.release_speed_m_s).all()
    assert (obs.release_height_m >= 0).all() and obs.release_height_m.max() < 3.0


def test_regenerating_the_shipped_observations_reproduces_them(tmp_path, capsys):
    out = str(tmp_path / "observations.csv")
    rc, _, err = _cli([f"{DATA}/runs.csv", "--blocks", f"{DATA}/blocks.csv",
                       "--profile", f"{DATA}/profile.csv",
                       "--profile", f"{DATA}/east_spot_profile.csv", "--source",
                       "Tschamut 2014 (Volkwein & Gerber 2018, EnviDat, doi:10.16904/envidat.34)",
                       "--out", out], capsys)
    assert rc == 0, err
    # the same table; the profile column names the same files, relative to each table
    mine, shipped = load_observations(out), load_observations(f"{DATA}/observations.csv")
    absolute = lambda o: [os.path.abspath(p) for p in o.profile]  # noqa: E731
    assert absolute(mine) == absolute(shipped)
    strip = lambda text: [line.rsplit(",", 1)[0] for line in text.splitlines()]  # noqa: E731
    assert strip(_read(out)) == strip(_read(f"{DATA}/observations.csv"))


def test_runs_go_on_the_profile_nearest_their_release(capsys):
    """The 12 runs let go from the spot 34 m east of the others' line go on that
    spot's own profile, and lie on it: release offsets 0.06-2.03 m (34 m before), heights
    above its ground (on the one line they lay up to 1.09 m below it)."""
    obs = load_observations(f"{DATA}/observations.csv")
    east = np.array([p.endswith("east_spot_profile.csv") for p in obs.profile])
    assert east.sum() == 12 and all(p.endswith("profile.csv") for p in obs.profile)
    df = pd.read_csv(f"{DATA}/observations.csv")
    off = np.abs(df["release_offset_m"].to_numpy(float))
    assert off[east].max() < 2.5 and off[~east].max() < 21.0
    assert obs.release_height_m[east].min() > 0.0


def test_observations_on_profiles_is_what_the_command_writes(tmp_path, capsys):
    """The library call (``observations_on_profiles``, what the notebook runs) gives
    the rows the command writes, each run on the profile nearest its release, with
    the profile column relative to the table's folder; a profile no run's release
    is nearest to is refused."""
    from calib.files.field_runs import observations_on_profiles

    source = "Tschamut 2014 (Volkwein & Gerber 2018, EnviDat, doi:10.16904/envidat.34)"
    profiles = [f"{DATA}/profile.csv", f"{DATA}/east_spot_profile.csv"]
    runs = load_runs(f"{DATA}/runs.csv", f"{DATA}/blocks.csv")
    rows = observations_on_profiles(runs, profiles, str(tmp_path), source=source)
    out = str(tmp_path / "cli.csv")
    rc, _, err = _cli([f"{DATA}/runs.csv", "--blocks", f"{DATA}/blocks.csv", "--profile",
                       profiles[0], "--profile", profiles[1], "--source", source, "--out", out],
                      capsys)
    assert rc == 0, err
    assert observations_csv_text(rows) == _read(out)
    on = [os.path.abspath(os.path.join(tmp_path, r["profile"])) for r in rows]
    assert sorted(set(on)) == sorted(os.path.abspath(p) for p in profiles)
    with pytest.raises(FieldError, match="east_spot_profile.csv: no run's release"):
        observations_on_profiles(take_runs(runs, [0]), profiles, str(tmp_path))
