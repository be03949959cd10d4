"""Every row simulated from its own release point, in every consumer:
the DEM forward model per (size, release) entry, and the discrepancy workflow
(``calib.discover``) grouping rows by (size class, release) as ``calib.fit`` does."""

from __future__ import annotations

import json
import subprocess
import sys

import jax
import numpy as np
import pytest

import calib  # noqa: F401  (x64)
from calib.discovery.candidate_fit import Candidate
from calib.discovery.discrepancy import discover
from calib.files.observations import Observations
from calib.inference.budget import DiscoveryBudget as Budget
from calib.model.entries import Entries
from calib.model.forward import DemForward, as_entries
from calib.model.priors import Box
from solvers.profile import load_profile

PROFILE = load_profile("data/postignano_profile.csv")


def test_entry_releases_broadcast_and_count():
    sizes = np.array([0.5, 1.0, 1.0])
    np.testing.assert_array_equal(as_entries(sizes, PROFILE).release_x_m, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(Entries.at_sizes(sizes, 20.0).release_x_m, [20.0] * 3)
    np.testing.assert_array_equal(Entries.at_sizes(sizes, (1.0, 2.0, 3.0)).release_x_m,
                                  [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="2 values for 3 entries"):
        Entries.at_sizes(sizes, (1.0, 2.0))


def test_dem_forward_runs_each_entry_from_its_release():
    """Two entries of the same 1 m block: the one released at the profile's first
    vertex gives the same runout as a forward with no release (same blocks,
    common random numbers); the one released at 150 m, on the gentle lower
    slope, stops sooner."""
    key = jax.random.key(0)
    alpha = np.array([[0.5, 0.5]])
    own = DemForward(PROFILE, Entries.at_sizes([1.0, 1.0], (0.0, 150.0)), 1, key,
                     form="constant").runouts_at_alpha(alpha)[0]
    top = DemForward(PROFILE, np.array([1.0]), 1, key, form="constant").runouts_at_alpha(
        alpha[:, :1])[0]
    print("runouts from 0 m and 150 m:", own[:, 0], "from the top alone:", top[0])
    assert np.all(np.isfinite(own))
    np.testing.assert_array_equal(own[0], top[0])
    assert own[1, 0] < own[0, 0] - 20.0


def test_dem_forward_releases_each_entry_at_its_speed_and_height():
    """A 1 m block released at 150 m on the gentle lower slope: from 3 m up at
    4 m/s it travels further than by the DEM's own rule (1 cm up, 0-1 m/s);
    an entry whose speed and height are NaN is the rule's, to the bit."""
    key = jax.random.key(0)
    alpha = np.array([[0.5, 0.5]])
    fw = DemForward(PROFILE, Entries.at_sizes([1.0, 1.0], 150.0,
                                              release_speed_m_s=(float("nan"), 4.0),
                                              release_height_m=(float("nan"), 3.0)),
                    1, key, form="constant")
    r = fw.runouts_at_alpha(alpha)[0]
    rule = DemForward(PROFILE, Entries.at_sizes([1.0], 150.0), 1, key,
                      form="constant").runouts_at_alpha(alpha[:, :1])[0]
    print("by the rule:", r[0, 0], "from 3 m at 4 m/s:", r[1, 0])
    np.testing.assert_array_equal(r[0], rule[0])
    assert np.all(np.isfinite(r)) and r[1, 0] > r[0, 0] + 5.0
    with pytest.raises(ValueError, match="release_height_m: 1 values for 2 entries"):
        Entries.at_sizes([1.0, 1.0], 150.0, release_height_m=(1.0,))


class _Falls:
    """A cheap forward model: a block released at x stops at 150 m, so its runout
    is scale * (150 - x) plus 3 m of noise (common random numbers per entry).
    Records the releases it is built with."""

    built: list = []

    def __init__(self, entries, n_blocks, key):
        entries = as_entries(entries, PROFILE)
        self.sizes_m = self.sizes = entries.sizes_m
        self.release = entries.release_x_m
        _Falls.built.append(tuple(self.release))
        self.noise = np.asarray(jax.random.normal(key, (self.sizes.size, n_blocks)))

    def runouts(self, theta):
        scale = np.atleast_2d(theta)[:, :1]
        return (scale * (150.0 - self.release[None, :]))[:, :, None] + 3.0 * self.noise[None]


def _rows():
    """12 rows of 1 m blocks, half released at 0 m and half at 100 m, each
    stopping near x = 150 m (the truth: scale 1)."""
    rng = np.random.default_rng(1)
    release = np.repeat([0.0, 100.0], 6)
    y = 150.0 - release + rng.normal(0.0, 3.0, 12)
    nan = np.full(12, np.nan)
    return Observations(np.full(12, 1.0), y, np.full(12, 3.0), nan, nan, np.zeros(12, bool),
                        ("synthetic",) * 12, release_x_m=release)


def test_discover_simulates_each_row_from_its_own_release():
    """With the rows' releases, the candidates are built on (size class, release)
    groups, the baseline recovers the truth, the stops are placed at release +
    runout (all near 150 m) and the gap is the noise's; without them (every
    block from the first vertex, the old behaviour) the one scale cannot fit
    both halves."""
    obs = _rows()
    cands = [Candidate("none", Box(("scale",), (0.5,), (2.0,)), _Falls)]
    budget = Budget(n_sobol=64, n_warm=0, n_refine=(32,), n_blocks=32, n_draws=8,
                    n_blocks_check=32, k_folds=3, noise_reps=0, smooth_loglik=False)
    _Falls.built.clear()
    d = discover(cands, obs, PROFILE, jax.random.key(0), budget, release_tolerance_m=1.0)
    assert {0.0, 100.0} == {x for rel in _Falls.built for x in rel}
    np.testing.assert_array_equal(d.entries.release_x_m, [0.0, 100.0])
    np.testing.assert_array_equal(d.entries.index, np.repeat([0, 1], 6))
    base = d.fits["none"]
    print("estimate", base.estimate, "gap", base.gap)
    assert abs(base.estimate[0] - 1.0) < 0.05
    assert base.gap < 3.0
    assert base.class_samples.shape == (1, 2 * base.samples.shape[1] * 6)
    parts = d.where_before["by_slope_part"]
    at_150 = [p for p in parts if p["x_from_m"] <= 150.0 < p["x_to_m"]][0]
    assert at_150["observed"] >= 11, parts  # one row may fall just below the part's edge
    assert not d.where_before["flagged"], d.where_before["flagged"]

    _Falls.built.clear()
    one = discover(cands, obs, PROFILE, jax.random.key(0), budget, release_tolerance_m=None)
    assert one.entries is None and {x for rel in _Falls.built for x in rel} == {0.0}
    print("one release: estimate", one.fits["none"].estimate, "gap", one.fits["none"].gap)
    assert one.fits["none"].gap > 5 * base.gap


@pytest.fixture(scope="module")
def tschamut_discover(tmp_path_factory):
    out = tmp_path_factory.mktemp("disc")
    proc = subprocess.run([sys.executable, "-m", "calib.discover",
                           "data/tschamut2014/observations.csv", "--quick", "--effects",
                           "size_dissipation", "--out", str(out), "--no-progress"],
                          capture_output=True, text=True, timeout=900)
    return proc, out


# slow: a quick `calib.discover` on the 62 Tschamut runs, 70 s; the default run keeps
# test_discover_simulates_each_row_from_its_own_release
@pytest.mark.slow
def test_discover_on_a_field_campaign_releases_each_run_from_its_point(tschamut_discover):
    """On the Tschamut runs (62 rows, 3 blocks, releases spread along the slope)
    the candidates simulate one group per (block, release within 1 m), each
    within 1 m of its rows' releases, and the summary says so."""
    from calib.files.observations import load_observations

    proc, out = tschamut_discover
    print(proc.stdout[-2000:], proc.stderr[-2000:])
    assert proc.returncode == 0, proc.stderr
    assert "each row simulated from its own release" in proc.stdout
    rec = json.loads((out / "discovery.json").read_text())
    groups = rec["release_groups"]["groups"]
    obs = load_observations("data/tschamut2014/observations.csv")
    assert sum(g["n_runout_rows"] for g in groups) == obs.n_obs
    assert len(groups) > np.unique(obs.block_size_m).size
    for g in groups:
        near = np.abs(obs.release_x_m - g["release_x_m"]) <= 1.0
        assert np.any(near & (obs.block_size_m == g["block_size_m"])), g
        assert g["release_height_m"] >= 0.0, g  # the runs' tracked release heights


def test_a_dem_calibration_says_whether_it_released_each_row_from_its_point(tmp_path):
    """calibration.json's ``release_groups.models`` tells validate how the DEM was
    fitted: listed, held-out rows are released from their own points; not listed
    (files of the one-release DEM fit), rows released elsewhere are refused with
    a line that says to refit, not simulated from the wrong point."""
    from test_hazard_fixtures import write_calibration

    from calib.files.calibration_file import load_calibration
    from calib.inference.predictive_check import predictive_runouts

    path = write_calibration(tmp_path, crsp=(0.41, 0.87, 2.0), dem=(0.40, 0.5))
    with open(path) as fh:
        doc = json.load(fh)
    doc["release_x_m"] = 0.0
    grouped = dict(doc, release_groups={"tolerance_m": 1.0, "models": ["crsp", "dem"]})
    for name, d in (("old.json", doc), ("grouped.json", grouped)):
        with open(tmp_path / name, "w") as fh:
            json.dump(d, fh)
    old = load_calibration(str(tmp_path / "old.json"), "dem")
    new = load_calibration(str(tmp_path / "grouped.json"), "dem")
    assert load_calibration(str(tmp_path / "old.json"), "crsp").own_releases
    assert not old.own_releases and new.own_releases
    held = Observations.points(np.array([1.0]), np.array([20.0]), 2.0)
    held = Observations(held.block_size_m, held.runout_m, held.runout_sd_m, held.runout_min_m,
                        held.runout_max_m, held.is_interval, held.source,
                        release_x_m=np.array([150.0]))
    with pytest.raises(ValueError, match="refit"):
        predictive_runouts(old, held, PROFILE, 1, 1, 0)


def test_velocity_rows_get_their_own_entries_at_the_median_release():
    """With passage speeds, the runout rows' (size class, release) groups come
    first, then one entry per velocity size class released at the median of the
    runout rows' releases (speeds have no release of their own)."""
    from calib.discovery.discrepancy import _entries

    obs = _rows()  # 12 rows of 1 m: 6 released at 0 m, 6 at 100 m
    class_sizes = np.array([0.5, 1.0])
    row_class = np.ones(12, int)
    vel_class = np.array([0, 1, 0])
    e = _entries(obs, PROFILE, class_sizes, row_class, vel_class, 1.0)
    np.testing.assert_array_equal(e.sizes_m, [1.0, 1.0, 0.5, 1.0])
    np.testing.assert_array_equal(e.release_x_m, [0.0, 100.0, 50.0, 50.0])
    np.testing.assert_array_equal(e.index, list(np.repeat([0, 1], 6)) + [2, 3, 2])
    assert np.all(np.isnan(e.release_speed_m_s))
    assert _entries(obs, PROFILE, class_sizes, row_class, vel_class, None) is None


def test_discover_groups_rows_by_release_height_and_speed_for_both_solvers():
    """Both solvers release a group from its rows' height and at their speed
    (the DEM since ``solvers.dem.Block.release_height_m``), so discover groups
    rows of one size at one abscissa but different heights apart, for either."""
    import dataclasses

    from calib.discovery.discrepancy import _entries

    obs = dataclasses.replace(_rows(), release_height_m=np.tile([0.0, 2.4], 6),
                              release_speed_m_s=np.full(12, 0.5))
    class_sizes, row_class = np.array([1.0]), np.zeros(12, int)
    g = _entries(obs, PROFILE, class_sizes, row_class, None, 1.0)
    assert len(g.sizes_m) == 4
    np.testing.assert_array_equal(np.unique(g.release_height_m), [0.0, 2.4])
    np.testing.assert_array_equal(g.release_speed_m_s, 0.5)
