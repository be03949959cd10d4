"""``calib.design``'s impact angle and its library path: the run with the barrier element
crosses the barrier with the hazard run's blocks (common random numbers: per draw,
as many crossings as the hazard run's passers at that station), the angles are
those of the velocity at the crossing, and the command puts them on the sheet.
Small CRSP runs on Postignano (a few seconds)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_hazard_fixtures import posterior_rows, write_calibration

from calib.design import (
    DesignOptions,
    design_at,
    design_block,
    impact_angles,
    load_kits,
    scan_rows,
)
from calib.design.__main__ import main
from calib.files.hazard_results import write_hazard_results
from calib.hazard import (
    HAZARD_SETTINGS,
    draw_parameters,
    hazard_dataset,
    load_calibration,
    run_hazard,
)
from solvers import crsp, load_profile

X_M, ROAD_M, SIZE_M, N, SEED = 100.0, 230.0, 1.0, 200, 3


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("angles")
    cal = load_calibration(write_calibration(folder, crsp_posterior=posterior_rows(10)), "crsp")
    profile = load_profile(cal.profile_csv)
    draws = draw_parameters(cal, 2, SEED)
    counts = run_hazard(cal, draws, profile, [SIZE_M], [50.0, X_M, ROAD_M], N, SEED)
    ds = hazard_dataset(counts, profile, seed=SEED, road_x_m=ROAD_M, road_label="road",
                        record={"rock_density_kg_m3": 2350.0})
    return cal, profile, draws, ds, folder


def test_crossings_are_the_hazard_runs_passers(run):
    cal, profile, draws, ds, _ = run
    a = impact_angles(cal, draws.values, draws.names, profile, X_M, SIZE_M, N, SEED,
                      float(ds.attrs["release_x_m"]))
    reach = ds["n_reach"].sel(block_size_m=SIZE_M, x_m=X_M).values
    assert reach.sum() > 0
    np.testing.assert_array_equal(np.bincount(a.draw, minlength=2), reach)
    assert np.all(np.abs(a.angle_deg) < 90.0)
    # the talus (8 to 110 m) falls 85.6 m over 102 m: 40 deg
    assert a.ground_slope_deg == pytest.approx(np.degrees(np.arctan2(85.556, 101.962)))
    p = a.percentiles()
    assert p[5.0] <= p[50.0] <= p[95.0]
    assert a.percentiles(True)[50.0] == pytest.approx(p[50.0] - a.ground_slope_deg)
    rec = a.record()
    assert rec["n_crossings"] == reach.sum() and len(rec["median_band_deg"]) == 2
    with pytest.raises(ValueError, match="at or above the release"):
        impact_angles(cal, draws.values, draws.names, profile, 0.0, SIZE_M, N, SEED, 0.0)


def test_the_angles_follow_the_hazard_runs_shape(run, tmp_path):
    """A hazard run of discs: the impact-angle run crosses a barrier at 120 m (just
    below the talus, where a few blocks of each draw pass) with the hazard run's disc
    passers (per draw), not the spheres' (which pass less often there), and the design
    command reads the shape from the file."""
    cal, profile, draws, _, _ = run
    x_m = 120.0
    counts = run_hazard(cal, draws, profile, [SIZE_M], [50.0, X_M, x_m, ROAD_M], N, SEED,
                        shapes=("disc",))
    ds = hazard_dataset(counts, profile, seed=SEED, road_x_m=ROAD_M, road_label="road",
                        record={"rock_density_kg_m3": 2350.0})
    reach = ds["n_reach"].sel(block_size_m=SIZE_M, x_m=x_m).values
    release = float(ds.attrs["release_x_m"])
    disc = impact_angles(cal, draws.values, draws.names, profile, x_m, SIZE_M, N, SEED,
                         release, shape="disc")
    sphere = impact_angles(cal, draws.values, draws.names, profile, x_m, SIZE_M, N, SEED,
                           release)
    print("disc passers per draw", reach, "sphere crossings",
          np.bincount(sphere.draw, minlength=2))
    assert reach.sum() > 0
    np.testing.assert_array_equal(np.bincount(disc.draw, minlength=2), reach)
    assert not np.array_equal(np.bincount(sphere.draw, minlength=2), reach)
    rec, _, _ = _sheet_with_angles(ds, tmp_path, x_m, cal.path)
    assert rec["impact_angle"]["n_crossings"] == int(reach.sum())


def test_library_design_of_a_run_in_memory(run):
    """The typed path a notebook takes: a run's Dataset, the design block, the design
    and a scan, no file in between."""
    _, _, _, ds, _ = run
    kits = load_kits("data/barrier_kits.csv")
    block, _ = design_block(ds, "run")
    d = design_at(ds, X_M, block, DesignOptions(kits=kits))
    assert d.values.n_passers == int(ds["n_reach"].sel(x_m=X_M).sum())
    assert d.protected_distance_m == ROAD_M - X_M
    assert d.kit is None or d.kit["passes"]
    rows = scan_rows(ds, block, [50.0, X_M], DesignOptions(kits=kits))
    assert [r["x_m"] for r in rows] == [50.0, X_M]
    assert rows[1]["E_sd_kJ"] == d.values.design["E_sd_kJ"]


def _sheet_with_angles(ds, folder, x_m: float, cal_path: str):
    """``calib.design`` of ``ds`` (written to ``folder``) with a barrier at ``x_m`` and
    the impact angle from ``cal_path``: (design.json's record, the sheet's folder, the
    hazard file)."""
    path = str(folder / "hazard.nc")
    write_hazard_results(ds, path)
    out = folder / "design"
    assert main([path, "--barrier-x-m", str(x_m), "--out", str(out), "--calibration",
                 cal_path, "--angle-blocks", str(N)]) == 0
    return json.loads((out / "design.json").read_text()), out, path


def test_command_puts_the_impact_angle_on_the_sheet(run, capsys):
    cal, _, _, ds, folder = run
    rec, out, path = _sheet_with_angles(ds, folder, X_M, cal.path)
    assert rec["impact_angle"]["n_crossings"] == int(ds["n_reach"].sel(x_m=X_M).sum())
    # the hazard file records the event budget its blocks ran with; the angles use it
    assert ds.attrs["crsp_max_events"] == HAZARD_SETTINGS.max_events
    assert rec["impact_angle"]["crsp_max_events"] == HAZARD_SETTINGS.max_events
    assert "impact angle below the horizontal" in capsys.readouterr().out
    assert "## Impact angle" in (out / "design.md").read_text()
    assert main([path, "--barrier-x-m", str(X_M), "--out", str(folder / "plain")]) == 0
    assert "Not computed" in (folder / "plain" / "design.md").read_text()


@pytest.mark.slow  # two solver programs of their own (about 25 s)
def test_the_angles_use_the_event_budget_the_hazard_run_used(tmp_path):
    """A hazard run with a budget of 25 events per block (``--max-events 25``) cuts
    some blocks short of the barrier (184 of 200 per draw pass x = 100 m, against
    200 with the default budget): the design's impact-angle run, read from the
    file, simulates with the same budget and crosses with the same blocks."""
    cal = load_calibration(write_calibration(tmp_path, crsp_posterior=posterior_rows(10)),
                           "crsp")
    profile = load_profile(cal.profile_csv)
    draws = draw_parameters(cal, 2, SEED)
    counts = run_hazard(cal, draws, profile, [SIZE_M], [50.0, X_M, ROAD_M], N, SEED,
                        settings=crsp.Settings(max_events=25))
    ds = hazard_dataset(counts, profile, seed=SEED, road_x_m=ROAD_M, road_label="road",
                        record={"rock_density_kg_m3": 2350.0})
    assert ds.attrs["crsp_max_events"] == 25
    n_reach = int(ds["n_reach"].sel(x_m=X_M).sum())
    assert 0 < n_reach < 2 * N  # the budget cut some blocks short
    path = str(tmp_path / "hazard.nc")
    write_hazard_results(ds, path)
    out = tmp_path / "design"
    assert main([path, "--barrier-x-m", str(X_M), "--out", str(out), "--calibration",
                 cal.path, "--angle-blocks", str(N)]) == 0
    rec = json.loads((out / "design.json").read_text())["impact_angle"]
    assert rec["crsp_max_events"] == 25 and rec["n_crossings"] == n_reach
