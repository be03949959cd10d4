"""Rows on their own profiles: field runs let go from spots far
apart across a slope each follow their spot's fall line. From the runs file to
the observations (``calib.field`` with several ``--profile``), the release
groups, the forward models and the fit's check."""

from __future__ import annotations

import json
import os
import types

import jax
import numpy as np
import pytest
from cli_run import run_cli

import calib  # noqa: F401  (x64)
from calib.field import main as field_main
from calib.files.inputs import own_profile
from calib.files.observations import ObservationError, load_observations, on_command_profile
from calib.inference.calibrate import _row_entries
from calib.inference.fit_check import check_entries
from calib.model.entries import Entries
from calib.model.forward import CrspForward, DemForward, release_slopes_deg
from calib.model.priors import CRSP_ROLLING_BOX
from solvers.profile import load_profile
from terrain.cut import main as cut_main

DATA = "data/tschamut2014"
LINE = load_profile(f"{DATA}/profile.csv")
EAST = own_profile(f"{DATA}/east_spot_profile.csv")
THETA = np.array([[0.3, 0.8, 0.2, 20.0], [0.5, 0.9, 0.05, 30.0]])


def _text(path) -> str:
    with open(path) as f:
        return f.read()




# slow: 21 s; the hold-out fit of tests/test_validate.py runs the Tschamut rows on their own
# profiles in the default run
@pytest.mark.slow
def test_an_entry_runs_on_its_own_profile_alone():
    """An entry on its own profile gets exactly the runouts of a forward on that
    profile alone, whatever the other entries are (common random numbers: same
    key, same blocks); entries on the command's profile, given as None or as
    the profile itself, are untouched."""
    kw = dict(n_blocks=64, key=jax.random.key(5), box=CRSP_ROLLING_BOX)
    both = CrspForward(LINE, Entries([0.3677, 0.3677, 0.3066], (41.5, 40.2, 41.0),
                                     (0.8, 0.3, 0.5), (1.3, 0.4, 1.2), (None, EAST, LINE), None),
                       **kw)
    r = both.runouts(THETA)
    alone_east = CrspForward(EAST, Entries([0.3677], 40.2, 0.3, 0.4, None, None), **kw)
    alone_line = CrspForward(LINE, Entries([0.3677, 0.3066], (41.5, 41.0), (0.8, 0.5),
                                           (1.3, 1.2), None, None), **kw)
    np.testing.assert_array_equal(r[:, 1], alone_east.runouts(THETA)[:, 0])
    np.testing.assert_array_equal(r[:, [0, 2]], alone_line.runouts(THETA))
    same = CrspForward(LINE, Entries([0.3677], 41.5, 0.8, 1.3, (LINE,), None), **kw)
    np.testing.assert_array_equal(same.runouts(THETA)[:, 0], r[:, 0])


# slow: the DEM on two profiles, 21 s; the default run keeps the CRSP case
@pytest.mark.slow
def test_dem_entries_on_their_own_profiles():
    """The DEM forward splits the same way: the entry on the spot's profile is
    that profile's forward alone."""
    kw = dict(n_blocks=2, key=jax.random.key(2), form="constant")
    both = DemForward(LINE, Entries([0.4, 0.4], (41.5, 40.2), None, None, (None, EAST), None),
                      **kw)
    alone = DemForward(EAST, Entries.at_sizes([0.4], 40.2), **kw)
    a = np.array([[0.6, 0.6]])
    np.testing.assert_array_equal(both.runouts_at_alpha(a)[:, 1],
                                  alone.runouts_at_alpha(a[:, :1])[:, 0])


def test_entry_profiles_must_be_one_per_entry():
    with pytest.raises(ValueError, match="profiles: 1 for 2 entries"):
        Entries([0.3, 0.4], 40.0, None, None, (EAST,), None)


def test_release_groups_split_rows_of_different_profiles():
    """Rows of one size released at one abscissa on two profiles are two
    releases; the groups say which profile each runs on."""
    obs = types.SimpleNamespace(block_size_m=np.ones(4), n_obs=4,
                                release_x_m=np.array([40.0, 40.2, 40.1, 40.0]),
                                profile=np.array(["", "b.csv", "", "b.csv"], dtype=object))
    g = Entries.from_rows(obs, 0.0, tol_m=1.0, profile_of=lambda p: EAST)
    assert g.profile_csv.tolist() == ["", "b.csv"] and g.profiles == (None, EAST)
    assert g.index.tolist() == [0, 1, 0, 1]
    np.testing.assert_allclose(g.release_x_m, [40.05, 40.1])


def test_observations_resolve_profiles_against_their_folder(tmp_path):
    """A row's profile is relative to the observation file's folder; a missing
    file names the line and the column; rows naming the command's own profile
    file run on it."""
    sub = tmp_path / "site"
    sub.mkdir()
    (sub / "p.csv").write_text(_text(f"{DATA}/profile.csv"))
    head = "block_size_m,runout_m,runout_sd_m,release_x_m,profile\n"
    (sub / "obs.csv").write_text(head + "0.3,50,2,40,p.csv\n0.3,60,2,40,\n")
    obs = load_observations(sub / "obs.csv")
    assert obs.profile.tolist() == [os.path.normpath(str(sub / "p.csv")), ""]
    assert not any(on_command_profile(obs, str(sub / "p.csv")).profile)
    (sub / "bad.csv").write_text(head + "0.3,50,2,40,p.csv\n0.3,60,2,40,nowhere.csv\n")
    with pytest.raises(ObservationError, match="line 3, column 'profile': no such profile "
                                               "file 'nowhere.csv'"):
        load_observations(sub / "bad.csv")


def test_the_check_simulates_groups_on_their_profiles():
    """The fit's check: the figure's sizes on the command's profile, every group
    on its own; the forward built on the groups is recognised as such only
    with the same profiles; the stall check reads each release's slope on its
    own profile (the spot's profile at 40.2 m is 38 deg, the line's 44 deg)."""
    obs = types.SimpleNamespace(block_size_m=np.array([0.3, 0.3]), n_obs=2,
                                release_x_m=np.array([40.2, 40.2]),
                                profile=np.array(["", f"{DATA}/east_spot_profile.csv"], object))
    g = Entries.from_rows(obs, 0.0, profile_of=own_profile)
    checked, entry = check_entries(g, np.array([0.3]))
    # the group on the command's profile at the median release is the figure's
    # entry; the one at the same abscissa on the spot's profile is not
    assert checked.profiles == (None, EAST) and entry.tolist() == [0, 1]
    fw = CrspForward(LINE, g, 4, jax.random.key(0))
    assert _row_entries(fw, obs) is g
    with pytest.raises(ValueError, match="forward must be built on the rows' entries"):
        _row_entries(CrspForward(LINE, np.array([0.3, 0.3]), 4, jax.random.key(0)),
                     types.SimpleNamespace(n_obs=2, sizes_m=np.array([0.3])))
    slopes = release_slopes_deg(LINE, g.release_x_m, g.profiles)
    assert 36 < slopes[1] < 40 and slopes[0] > 40, slopes


# ------------------------------------------------------------ from the runs file

def test_field_puts_each_run_on_the_profile_nearest_its_release(tmp_path, capsys):
    out = tmp_path / "out" / "obs.csv"
    rc, text, err = run_cli(field_main, [f"{DATA}/runs.csv", "--blocks", f"{DATA}/blocks.csv",
                                      "--profile", f"{DATA}/profile.csv",
                                      "--profile", f"{DATA}/east_spot_profile.csv",
                                      "--out", str(out)], capsys)
    assert rc == 0, err
    assert "(50 on data/tschamut2014/profile.csv, 12 on data/tschamut2014/east_spot_profile" \
        in text
    obs = load_observations(out)
    assert sorted({os.path.basename(p) for p in obs.profile}) == ["east_spot_profile.csv",
                                                                  "profile.csv"]
    assert all(os.path.isfile(p) for p in obs.profile)
    # a profile no run is nearest to is refused, nothing written
    out2 = tmp_path / "obs2.csv"
    rc, _, err = run_cli(field_main, [f"{DATA}/runs.csv", "--blocks", f"{DATA}/blocks.csv",
                                   "--profile", f"{DATA}/east_spot_profile.csv",
                                   "--profile", f"{DATA}/east_spot_profile.csv",
                                   "--profile", f"{DATA}/profile.csv", "--out", str(out2)],
                       capsys)
    assert rc == 0  # a repeated profile counts once
    one = tmp_path / "one.csv"
    rc, _, _ = run_cli(field_main, [f"{DATA}/runs.csv", "--blocks", f"{DATA}/blocks.csv",
                                 "--profile", f"{DATA}/profile.csv", "--out", str(one)], capsys)
    assert rc == 0 and "profile" not in _text(one).splitlines()[0]  # one profile: no column


def test_field_refuses_a_profile_no_run_belongs_to(tmp_path, capsys):
    far = tmp_path / "far.csv"
    rows = _text(f"{DATA}/east_spot_profile.csv").splitlines()
    head = rows[0].split(",")
    ie, in_ = head.index("east_m"), head.index("north_m")
    moved = [rows[0]]
    for r in rows[1:]:
        c = r.split(",")
        c[ie] = f"{float(c[ie]) + 500:.4f}"
        c[in_] = f"{float(c[in_]) + 500:.4f}"
        moved.append(",".join(c))
    far.write_text("\n".join(moved) + "\n")
    out = tmp_path / "obs.csv"
    rc, _, err = run_cli(field_main, [f"{DATA}/runs.csv", "--blocks", f"{DATA}/blocks.csv",
                                   "--profile", f"{DATA}/profile.csv", "--profile", str(far),
                                   "--out", str(out)], capsys)
    assert rc == 2 and f"--profile {far}: no run's release lies nearer" in err
    assert not out.exists()


def test_cut_along_one_spots_fall_line(tmp_path, capsys):
    """--fall-line-near E,N,R cuts the mean fall line of the runs released within
    R m of (E, N), and records it; no run there is one line, exit 2."""
    out = tmp_path / "spot.csv"
    rc, _, err = run_cli(cut_main, [f"{DATA}/terrain_proxy.asc", "--fall-line",
                                    f"{DATA}/runs.csv", "--fall-line-near", "59,257.5,10",
                                    "--margin-m", "40", "--zones", "steep:0:100,flat:100:",
                                    "--out", str(out)], capsys)
    assert rc == 0, err
    assert _text(out) == _text(f"{DATA}/east_spot_profile.csv")
    info = json.loads(_text(tmp_path / "spot.cut.json"))
    assert info["line"]["runs_released_near"] == {"east_m": 59.0, "north_m": 257.5,
                                                  "radius_m": 10.0}
    rc, _, err = run_cli(cut_main, [f"{DATA}/terrain_proxy.asc", "--fall-line",
                                    f"{DATA}/runs.csv", "--fall-line-near", "0,0,5",
                                    "--out", str(tmp_path / "none.csv")], capsys)
    assert rc == 2 and "no run is released within 5 m of (0, 0)" in err
    assert not (tmp_path / "none.csv").exists()


def test_split_rows_keep_their_profiles(tmp_path, capsys):
    """``calib.fit --holdout-fraction`` writes the row files into --out: their
    profile column is rewritten relative to it, so that the held-out rows
    (``calib.validate``) and the calibration rows still name the same files."""
    from calib.files.split import holdout_rows, rows_csv, subset

    out = tmp_path / "results"
    out.mkdir()
    obs = load_observations(f"{DATA}/observations.csv")
    fit_rows, held_rows = holdout_rows(obs.n_obs, 0.3, 1)
    fit_obs = subset(obs, fit_rows)
    (out / "calibration_rows.csv").write_text(rows_csv(obs, fit_rows, str(out)))
    (out / "heldout_rows.csv").write_text(rows_csv(obs, held_rows, str(out)))
    held = load_observations(out / "heldout_rows.csv")
    back = load_observations(out / "calibration_rows.csv")
    absolute = lambda o: [os.path.abspath(p) for p in o.profile]  # noqa: E731
    assert absolute(back) == absolute(fit_obs)
    assert set(absolute(held)) <= set(absolute(obs)) and len(held.profile) == 19
    assert sum(p.endswith("east_spot_profile.csv") for p in back.profile) == 11


def test_row_files_are_the_rows_as_validated(tmp_path):
    """The split's row files come from the rows read and validated, not from a
    second read of the file: a file changed after loading does not leak in, and
    the subset's cells are those of its rows."""
    from calib.files.split import rows_csv, subset

    src = tmp_path / "rows.csv"
    src.write_text("block_size_m,runout_m,runout_sd_m,source\n0.5,100,10,a\n1.0,150,10,b\n"
                   "2.0,200,10,c\n3.0,250,10,d\n")  # as many rows as columns
    obs = load_observations(src)
    src.write_text("block_size_m,runout_m,runout_sd_m,source\n9,9,9,x\n")
    rows = np.array([0, 2])
    assert rows_csv(obs, rows, str(tmp_path)) == ("block_size_m,runout_m,runout_sd_m,source\n"
                                                  "0.5,100,10,a\n2.0,200,10,c\n")
    assert subset(obs, rows).cells == (("0.5", "100", "10", "a"), ("2.0", "200", "10", "c"))
    assert subset(obs, rows).columns == obs.columns
