"""A calibration says when it cannot fit: posterior mass at the prior
bounds and posterior predictive coverage of the calibration rows."""

from __future__ import annotations

import numpy as np
import pandas as pd

from calib.files.observations import load_observations
from calib.inference.adequacy import adequacy_record, bound_mass, predictive_coverage
from calib.model.priors import CRSP_BOX


def _obs(tmp_path, sizes, runouts, sd=3.0):
    path = tmp_path / "obs.csv"
    pd.DataFrame({"block_size_m": sizes, "runout_m": runouts,
                  "runout_sd_m": np.full(len(sizes), sd)}).to_csv(path, index=False)
    return load_observations(str(path))


def test_uniform_posterior_is_not_flagged_and_piled_posterior_is():
    rng = np.random.default_rng(0)
    uniform = CRSP_BOX.from_unit(rng.random((4000, 3)))
    b = bound_mass(uniform, CRSP_BOX)
    for name in CRSP_BOX.names:
        assert abs(b[name]["lower"] - 0.02) < 0.01 and abs(b[name]["upper"] - 0.02) < 0.01
        assert not b[name]["flagged"]
    piled = uniform.copy()
    piled[:, 1] = CRSP_BOX.hi[1] - 0.001 * rng.random(4000)  # Kt against its upper bound
    b = bound_mass(piled, CRSP_BOX)
    assert b["Kt"]["flagged"] and b["Kt"]["upper"] == 1.0
    assert not b["Kn"]["flagged"]


def test_a_narrow_posterior_inside_the_band_but_away_from_the_bound_is_not_flagged():
    """Roughness S spans 0.01-4 m, so its 2 % band reaches 0.09 m. A posterior of
    S between 0.077 and 0.086 m (Tschamut, seed 1) lies in the band but eight
    times above the bound: it does not want a value outside the box. One that
    reaches the bound still is flagged."""
    from calib.model.priors import CRSP_ROLLING_BOX

    rng = np.random.default_rng(1)
    post = np.tile([0.35, 0.93, 0.08, 37.0], (2000, 1))
    post[:, 2] = rng.uniform(0.077, 0.086, 2000)
    b = bound_mass(post, CRSP_ROLLING_BOX)
    assert b["roughness_m"]["lower"] == 1.0 and not b["roughness_m"]["flagged"]
    post[:, 2] = rng.uniform(0.01, 0.05, 2000)
    b = bound_mass(post, CRSP_ROLLING_BOX)
    assert b["roughness_m"]["flagged"] and b["roughness_m"]["lower_flagged"]


def test_rows_drawn_from_the_predictive_are_covered_at_about_the_nominal_rate(tmp_path):
    """Rows that are draws of R + e from the simulated distribution itself: about
    50 % and 90 % are covered, nothing is flagged."""
    rng = np.random.default_rng(1)
    sim = 100.0 + 20.0 * rng.standard_normal((2, 4000))  # two sizes
    sizes = np.repeat([0.5, 1.0], 100)
    y = 100.0 + 20.0 * rng.standard_normal(200) + 3.0 * rng.standard_normal(200)
    obs = _obs(tmp_path, sizes, y)
    cov = predictive_coverage(obs, sim)
    assert abs(cov["levels"]["0.5"]["fraction"] - 0.5) < 0.1
    assert abs(cov["levels"]["0.9"]["fraction"] - 0.9) < 0.06
    assert not cov["levels"]["0.5"]["flagged"] and not cov["levels"]["0.9"]["flagged"]


def test_a_model_that_stops_too_early_is_flagged(tmp_path):
    """18 rows of which 7 lie beyond the simulated 90 % band (the symptom
    seen on Tschamut): coverage of the 90 % band is flagged, and the record
    says the model may not fit."""
    rng = np.random.default_rng(2)
    sim = 80.0 + 5.0 * rng.standard_normal((1, 4000))
    y = np.concatenate([80.0 + 5.0 * rng.standard_normal(11), np.full(7, 130.0)])
    obs = _obs(tmp_path, np.full(18, 0.4), y, sd=1.0)
    piled = CRSP_BOX.from_unit(rng.random((1000, 3)))
    piled[:, 1] = CRSP_BOX.hi[1]
    rec = adequacy_record(piled, CRSP_BOX, obs, sim, "test")
    assert rec["coverage"]["levels"]["0.9"]["n_covered"] <= 11
    assert rec["coverage"]["levels"]["0.9"]["flagged"]
    assert not rec["ok"] and "Kt" in rec["message"] and "90%" in rec["message"]


def test_mass_on_a_bound_is_not_answered_by_widening_the_box(tmp_path):
    """The prior boxes are set from published ranges before fitting; where mass piles
    on a bound, the message points to what can settle it (a measurement that separates
    the parameters, a source, the missing physics), not to a wider box. Without mass
    on a bound the remedy is the physics or the data."""
    rng = np.random.default_rng(3)
    sim = 80.0 + 5.0 * rng.standard_normal((1, 4000))
    obs = _obs(tmp_path, np.full(18, 0.4), 80.0 + 5.0 * rng.standard_normal(18), sd=1.0)
    piled = CRSP_BOX.from_unit(rng.random((1000, 3)))
    piled[:, 1] = CRSP_BOX.hi[1]
    rec = adequacy_record(piled, CRSP_BOX, obs, sim, "test")
    assert not rec["ok"] and "Kt" in rec["message"]
    assert "widen the prior" not in rec["message"].lower()
    assert "calib/model/priors.py" in rec["message"] and "--velocities" in rec["message"]
    early = adequacy_record(None, CRSP_BOX, obs, sim + 60.0, "test")
    assert not early["ok"] and "90%" in early["message"]
    assert "missing physics" in early["message"] and "priors.py" not in early["message"]


def test_interval_rows_are_covered_when_they_overlap_the_band(tmp_path):
    path = tmp_path / "obs.csv"
    path.write_text("block_size_m,runout_min_m,runout_max_m\n1.0,90,95\n1.0,200,210\n")
    obs = load_observations(str(path))
    sim = np.linspace(80.0, 120.0, 401)[None]
    rows = predictive_coverage(obs, sim)["rows"]
    assert rows[0]["in_90"] and rows[0]["in_50"] and not rows[1]["in_90"]


def test_blocks_that_stall_at_their_release_are_flagged_with_where(tmp_path):
    """Three (size, release) entries: at the first, 80 % of the simulated blocks stop
    within 1 m of the release while its observed rows travelled 80-100 m; at the
    second as many stall but so did its rows (not a misfit); at the third none
    stall. Only the first is flagged, and the message names its release and the
    slope below it."""
    from calib.inference.adequacy import stalled_releases

    rng = np.random.default_rng(2)
    moving = 90.0 + 10.0 * rng.standard_normal(500)
    stall = np.where(rng.random(500) < 0.8, 0.2, moving)
    sim = np.stack([stall, stall, moving])
    obs = _obs(tmp_path, [0.3] * 9, [80, 90, 100, 0.3, 0.5, 0.2, 85, 95, 88])
    index = np.repeat([0, 1, 2], 3)
    rel, slope = np.array([38.7, 39.0, 41.0]), np.array([25.7, 25.7, 43.8])
    st = stalled_releases(obs, sim, index, rel, slope)
    assert [e["flagged"] for e in st["entries"]] == [True, False, False]
    first = st["entries"][0]
    assert abs(first["simulated_stalled"] - 0.8) < 0.05 and first["observed_stalled"] == 0.0
    assert first["rows"] == [1, 2, 3]
    rec = adequacy_record(None, CRSP_BOX, obs, sim, "test", index, rel, slope)
    assert not rec["ok"] and rec["stalls"]["flagged"] == [first]
    assert "released at x = 38.7 m (slope below it 26 deg)" in rec["message"]
    # without the stalling entry nothing is said about stalls
    ok = adequacy_record(None, CRSP_BOX, obs, np.stack([moving, stall, moving]), "test",
                         index, rel, slope)
    assert not ok["stalls"]["flagged"] and "stall" not in (ok["message"] or "")


def test_a_better_design_point_than_the_estimate_is_flagged(tmp_path):
    """Check 4: a design point whose simulated log-likelihood beats one of the
    fit's points by more than 1 nat per row and more than the likelihood-ratio
    bar (chi-square 99.9 % / 2: 8.1 nats for 3 parameters) is named in the
    message with the point it beats; within either bar it is reported, not
    flagged (Postignano: 2 rows, 2.1 nats); a design with no finished block
    anywhere (-inf) flags nothing."""
    from calib.inference.adequacy import better_design_point

    rng = np.random.default_rng(3)
    sim = (90.0 + 10.0 * rng.standard_normal(500))[None]
    obs = _obs(tmp_path, [0.3] * 4, [80, 90, 100, 95])
    theta = np.array([[0.2, 0.8, 0.5], [0.3, 0.9, 0.05], [0.4, 0.7, 2.0]])
    ll = np.array([-60.0, -20.0, -80.0])
    b = better_design_point(CRSP_BOX.names, theta, ll, {"estimate": -21.0,
                                                        "posterior mode": -40.0}, 4)
    assert b["flagged"] and b["theta"] == {"Kn": 0.3, "Kt": 0.9, "roughness_m": 0.05}
    assert abs(b["threshold_nats"] - 8.13) < 0.01
    assert b["points"]["posterior mode"]["gain_per_row_nats"] == 5.0
    assert not b["points"]["estimate"]["flagged"]
    rec = adequacy_record(None, CRSP_BOX, obs, sim, "test", better=b)
    assert not rec["ok"] and "fits the rows better than the posterior mode (-40) by 20 nats, " \
        "5.0 per row" in rec["message"] and "roughness_m 0.05" in rec["message"]
    assert "the estimate" not in rec["message"]
    for fitted, n_rows in (({"estimate": -27.0}, 4), ({"estimate": -22.1}, 2)):
        close = better_design_point(CRSP_BOX.names, theta, ll, fitted, n_rows)
        assert not close["flagged"], close
        assert "better" not in (adequacy_record(None, CRSP_BOX, obs, sim, "test",
                                                better=close)["message"] or "")
    none = better_design_point(CRSP_BOX.names, theta, np.full(3, -np.inf), {"estimate": -40.0},
                               4)
    assert not none["flagged"] and none["loglik"] is None
