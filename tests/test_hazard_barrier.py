"""A protection barrier in the hazard run (``calib.hazard --barrier-x-m X
--barrier-height-m H --barrier-capacity-kJ E``, ``solvers/crsp/_barrier.py``) and its
residual hazard in the design (``calib.design --with-barrier``).

Invariants on small runs of the Postignano profile (3 draws x 2 sizes x 400 blocks,
the same seed with and without the barrier: common random numbers, so a block the
barrier does not touch is the same block in both runs): a barrier of height 0 gives
the tables of the run without it; an unlimited one lets no block past; any barrier
leaves everything upslope of it unchanged and does not raise the exceedance
downslope of it beyond the Monte Carlo error of the blocks it touches. Bad input:
one line, exit 2, nothing written."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pandas as pd
import pytest
from cli_run import run_cli
from test_hazard_fixtures import posterior_rows, write_calibration

from calib.hazard import (
    draw_parameters,
    exceedance_table,
    hazard_table,
    load_calibration,
    run_hazard,
)
from calib.hazard.__main__ import main
from calib.hazard._results import hazard_dataset
from calib.hazard._run import Barrier
from solvers import crsp, load_profile

X = 100.0  # every block reaches it; they stop between 110 and 150 m without it
STATIONS = np.arange(0.0, 301.0, 10.0)
# the small run of tests/test_hazard_cli.py (one compiled pool for all these runs)
SMALL = ["--n-posterior", "3", "--n-blocks", "400", "--block-sizes-m", "0.5,2.0",
         "--stations-m", "0:300:10", "--no-progress"]
SETTINGS = crsp.Settings(max_events=5000)  # the command's default --max-events
KITS = os.path.abspath("data/barrier_kits.csv")


@pytest.fixture(scope="module")
def cal_path(tmp_path_factory):
    return write_calibration(tmp_path_factory.mktemp("cal"), crsp_posterior=posterior_rows(50))


@pytest.fixture(scope="module")
def runs(cal_path):
    """barrier (None: without) -> (counts, results Dataset) of the small run."""
    cal = load_calibration(cal_path, "crsp")
    profile = load_profile(cal.profile_csv)
    draws = draw_parameters(cal, 3, 0)
    cache = {}

    def run(barrier=None):
        if barrier not in cache:
            c = run_hazard(cal, draws, profile, [0.5, 2.0], STATIONS, 400, 0, settings=SETTINGS,
                           barrier=barrier)
            cache[barrier] = c, hazard_dataset(c, profile)
        return cache[barrier]

    return run


# slow: 17 s; the solver's own case (tests/test_crsp_barrier.py, postignano) keeps height 0 in the
# default run
@pytest.mark.slow
def test_height_zero_gives_the_tables_of_the_run_without(runs):
    """Every block flies over a barrier of height 0: the tables are those of the run
    without it, value for value; hazard.nc records the barrier."""
    _, without = runs()
    _, zero = runs(Barrier(X, 0.0, 300.0))
    pd.testing.assert_frame_equal(hazard_table(zero), hazard_table(without))
    pd.testing.assert_frame_equal(exceedance_table(zero), exceedance_table(without))
    assert zero.attrs["barrier_x_m"] == X and zero.attrs["barrier_height_m"] == 0.0
    assert "barrier_x_m" not in without.attrs


def test_an_unlimited_barrier_lets_no_block_past(runs):
    """Unlimited height and capacity: no block passes a station beyond the barrier or
    stops beyond it; upslope of it every count is the run's without it; so the
    exceedance with it is at most the one without, station by station, draw by draw."""
    without, _ = runs()
    c, _ = runs(Barrier(X))
    beyond, upslope = STATIONS > X, STATIONS < X
    assert without.reach[..., beyond].sum() > 0  # without it, blocks go further
    assert c.reach[..., beyond].sum() == 0 and c.exceed[..., beyond].sum() == 0
    np.testing.assert_array_equal(c.reach[..., STATIONS <= X], without.reach[..., STATIONS <= X])
    np.testing.assert_array_equal(c.exceed[..., upslope], without.exceed[..., upslope])
    assert np.all(c.exceed <= without.exceed)
    assert (c.n_unfinished == 0).all() and (c.n_left_profile == without.n_left_profile).all()


def test_a_barrier_does_not_raise_the_exceedance_beyond_it(runs):
    """H = 2 m, capacity 300 kJ (the 0.5 m blocks are stopped below 2 m, most 2 m
    blocks break through): upslope of the barrier nothing changes; beyond it the
    paired difference of exceedance counts (with minus without, summed over draws)
    stays below 3 standard errors. Blocks that fly over the barrier are the same in
    both runs (common random numbers), so the difference comes from the blocks that
    hit the net, n_hit <= the blocks that reach it, each contributing -1, 0 or +1:
    its variance is at most n_hit."""
    without, _ = runs()
    c, _ = runs(Barrier(X, 2.0, 300.0))
    at = int(np.flatnonzero(STATIONS == X)[0])
    np.testing.assert_array_equal(c.reach[..., :at + 1], without.reach[..., :at + 1])
    np.testing.assert_array_equal(c.exceed[..., :at], without.exceed[..., :at])
    n_reach = without.reach[..., at].sum(axis=0)  # (T,) blocks at the barrier
    diff = (c.exceed - without.exceed).sum(axis=0)  # (T, S)
    beyond = STATIONS > X
    assert np.all(diff[:, beyond] <= 3.0 * np.sqrt(n_reach)[:, None]), diff[:, beyond]
    assert np.all(diff[:, beyond].min(axis=1) < 0)  # it stopped blocks of both sizes
    # and some 2 m blocks broke through, as the capacity says
    assert c.reach[:, 1, beyond].sum() > 0


# ------------------------------------------------------------------ the commands

@pytest.fixture(scope="module")
def pair(cal_path, tmp_path_factory):
    """hazard.nc without and with a barrier at 100 m (H 2 m, 300 kJ), the road at
    120 m (where some blocks arrive), and the design at 100 m with --with-barrier."""
    import contextlib
    import io

    from calib.design.__main__ import main as design

    out = tmp_path_factory.mktemp("pair")
    common = [cal_path, *SMALL, "--road-x-m", "120", "--release-rate-per-year", "1"]
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(common + ["--out", str(out / "without")]) == 0
        assert main(common + ["--barrier-x-m", "100", "--barrier-height-m", "2",
                              "--barrier-capacity-kJ", "300", "--out", str(out / "with")]) == 0
        assert design([str(out / "without" / "hazard.nc"), "--barrier-x-m", "100", "--kits",
                       KITS, "--with-barrier", str(out / "with" / "hazard.nc"), "--out",
                       str(out / "design")]) == 0
    return out


def test_design_shows_the_residual_hazard_at_the_road(pair):
    """design.json and design.md give, per size, P(runout beyond the road) and
    P(reach the road) with their bands without and with the barrier; with it they
    are lower (here the barrier stops most blocks that reached 120 m)."""
    r = json.loads((pair / "design" / "design.json").read_text())["residual"]
    assert r["road_x_m"] == 120.0 and r["barrier"] == {"x_m": 100.0, "height_m": 2.0,
                                                       "capacity_kJ": 300.0}
    rows = {row["block_size_m"]: row for row in r["rows"]}
    big = rows[2.0]
    for k in ("p_exceed_mean", "p_exceed_q05", "p_exceed_q95", "reach_prob_mean",
              "reach_prob_q05", "reach_prob_q95"):
        assert math.isfinite(big[k]) and math.isfinite(big[k + "_with_barrier"]), k
    assert big["reach_prob_mean"] > 0.05
    assert big["reach_prob_mean_with_barrier"] < big["reach_prob_mean"]
    assert big["p_exceed_mean_with_barrier"] < big["p_exceed_mean"]
    md = (pair / "design" / "design.md").read_text()
    assert "Barrier at x = 100 m (height 2 m, capacity 300 kJ)" in md and "P(reach)" in md
    summary = (pair / "with" / "summary.txt").read_text()
    assert "barrier at x = 100 m, height 2 m, capacity 300 kJ" in summary


def test_runs_of_other_event_budgets_are_not_common_random_numbers(pair):
    """Both runs record their CRSP event budget; the same budget compares them
    without a warning, another one is named in the warning (blocks cut short by
    one budget and not the other are different blocks)."""
    from calib.design._residual import check_compatible
    from calib.files.hazard_results import read_hazard_results

    without = read_hazard_results(str(pair / "without" / "hazard.nc"))
    with_barrier = read_hazard_results(str(pair / "with" / "hazard.nc"))
    assert without.attrs["crsp_max_events"] == with_barrier.attrs["crsp_max_events"] == 5000
    assert check_compatible(without, with_barrier) == []
    with_barrier.attrs["crsp_max_events"] = "profile"
    (warning,) = check_compatible(without, with_barrier)
    assert "differs from the run without the barrier in event budget" in warning


@pytest.mark.parametrize("extra, message", [
    (["--barrier-x-m", "400"], "--barrier-x-m 400: outside the profile [0, 300] m"),
    (["--barrier-x-m=-5"], "--barrier-x-m -5: outside the profile"),
    (["--barrier-x-m", "0"], "--barrier-x-m 0: at or above the release at x = 0 m"),
    (["--barrier-x-m", "3", "--release-zone-m", "0:5"], "--barrier-x-m 3: at or above the "
                                                        "release at x = 5 m"),
    (["--barrier-x-m", "nan"], "--barrier-x-m nan: expected a finite abscissa"),
    (["--barrier-height-m", "2"], "--barrier-height-m: needs --barrier-x-m"),
    (["--barrier-x-m", "100", "--barrier-capacity-kJ", "-1"], "--barrier-capacity-kJ -1: "
                                                              "expected a number >= 0"),
    (["--barrier-x-m", "100", "--model", "dem"], "the DEM hazard run takes fixed sizes"),
])
def test_bad_barrier_one_line_exit_2_nothing_written(cal_path, tmp_path, capsys, extra,
                                                      message):
    out = tmp_path / "out"
    rc, _, err = run_cli(main, [cal_path, *SMALL, *extra, "--out", str(out)], capsys)
    assert rc == 2, err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and not os.path.exists(out)
