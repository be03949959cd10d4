"""The discovery loop end to end on a synthetic site with a known hidden effect
(``scripts/hidden_effect_chain.py``): discover names the effect, the fit with it
scores better than the baseline on rows of the same site that no fit saw, and
its hazard exceedance moves towards the truth's: at the road, and, a stricter
verdict, at every station the truth or a fit passes.

The chains themselves are slow (``pytest -m slow tests/test_hidden_effect_chain.py``:
about 10-35 minutes per effect on 2 cores, 180 rows, the default budgets; the
vegetation belt with 30 passage speeds at 110 m as well, the design
docs/studies.md found it needs, fitted by discover and by both fits, and its road
below the belt, ``_road_past_the_belt_m``); each runs
once and the three verdicts below read it. The script's own bookkeeping is checked in the
default run.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from cli_run import load_script

from calib.discovery.synthetic import LIVE_P_EXCEED, compare_exceedance

chain = load_script("hidden_effect_chain")


def test_the_baseline_is_the_refit_command_without_its_effects():
    cmd = ("python -m calib.fit /tmp/x.csv --model crsp --rolling-resistance profile "
           "--effect size_dissipation --effect=fragmentation --release-tolerance-m 1")
    assert chain.without_effects(cmd) == [
        "-m", "calib.fit", "/tmp/x.csv", "--model", "crsp", "--rolling-resistance", "profile",
        "--release-tolerance-m", "1"]


def test_exceedance_comparison_counts_live_stations_and_the_band():
    x = np.array([100.0, 150.0, 200.0, 250.0])
    truth = np.array([[0.5, 0.1, 0.0, 0.0]] + [[0.0] * 4] * 3)  # 0.2 m only

    def table(mean, q05, q95):  # the exceedance.csv columns the comparison reads
        rows = [{"block_size_m": d, "x_m": xx, "p_exceed_mean": m if d == 0.2 else 0.0,
                 "p_exceed_q05": lo if d == 0.2 else 0.0, "p_exceed_q95": hi if d == 0.2 else 0.0}
                for d in chain.SIZES_M for xx, m, lo, hi in zip(x, mean, q05, q95)]
        return pd.DataFrame(rows)
    base = table([0.3, 0.2, 0.0, 0.0], [0.2, 0.15, 0, 0], [0.4, 0.3, 0, 0])
    eff = table([0.5, 0.1, 0.0, 0.0], [0.4, 0.05, 0, 0], [0.6, 0.2, 0, 0])
    out = compare_exceedance({"baseline": base, "effect": eff}, truth, chain.SIZES_M, x, 200.0)
    e = out["0.2"]
    assert e["n_stations"] == 2  # the two stations where anything passes
    assert e["baseline"]["mean_abs_error"] == pytest.approx(0.15)
    assert e["effect"]["mean_abs_error"] == pytest.approx(0.0)
    assert e["baseline"]["truth_in_band"] == 0.0 and e["effect"]["truth_in_band"] == 1.0
    assert e["road"]["x_m"] == 200.0 and e["road"]["truth"] == 0.0
    assert out["2.0"]["n_stations"] == 0 and out["2.0"]["baseline"]["mean_abs_error"] is None
    json.dumps(out, allow_nan=False)  # what chain.json holds


# the data design that names the belt (docs/studies.md, "One data design that names
# every effect"): runouts and sizes alone cannot tell it from a lower Kt
_SPEEDS = {"vegetation_belt": ["--velocity-stations-m", "110", "--n-velocity", "30"]}

# Fragmentation's 0.2 m blocks sit at Monte Carlo level: mean |P - P_truth| 0.010 with
# the effect against 0.009 (2026-11-27), 0.0093 against 0.0090 (2026-12-05, twice), and
# 0.0089 against 0.0092 (2026-12-06, another machine and installation; docs/studies.md,
# "The chains at the road"): small blocks seldom break, so the two fits differ there by
# noise, and the verdict at that size can go either way from one run to the next.
_SHORT = {
    # measured with this test's chain, 180 runouts and 30 speeds at 110 m (2026-12-05,
    # docs/studies.md, "The forest belt's chain, with its passage speeds"; again "The
    # fragmentation and belt chains with twelve realisation waves")
    "vegetation_belt": "0.2 m blocks: mean |P - P_truth| 0.007 with the belt against 0.002 "
                       "for the baseline over 29 stations (0.5-2.0 m: 0.002-0.009 against "
                       "0.032-0.079); again 2026-12-05 with 12 realisation waves: 0.0065 "
                       "against 0.0032 (0.5-2.0 m: 0.002-0.009 against 0.025-0.076); 0.2 m "
                       "blocks mostly stop above the belt (the fit's simulated median "
                       "110 m, the belt from 129 m), where the belt changes nothing",
}


EFFECTS = ("size_dissipation", "rolling_resistance", "fragmentation", "vegetation_belt")


def _road_past_the_belt_m() -> float:
    """The belt site's road: the first 10 m station below the truth belt's lower end.

    The site file's road (x 230 m, the chain's default) lies where no block of the
    belt's truth arrives (measured 2026-12-05: no size with more than LIVE_P_EXCEED
    there in the truth or either fit), so it cannot show the belt. Below the belt
    (129-174 m on Postignano) is where a road the belt protects would be; the rule
    reads the truth's geometry only, no fit.
    """
    from calib.model import effects
    from solvers.profile import load_profile
    defaults = chain.build_parser()  # the chain's own profile and strength
    profile = load_profile(defaults.get_default("profile"))
    start_m = effects.truth("vegetation_belt", defaults.get_default("strength"), profile)[-2]
    end_m = start_m + effects.belt_geometry_m(profile)[2]
    return float(10.0 * np.ceil(end_m / 10.0))


# the effects whose site puts its road elsewhere than the chain's default (computed
# when the chain runs, not when the default run imports this file)
_ROADS = {"vegetation_belt": _road_past_the_belt_m}


@pytest.fixture(scope="module")
def chains(tmp_path_factory):
    """effect -> the chain's ``chain.json``; each effect's chain runs once."""
    done = {}

    def run(effect):
        if effect not in done:
            out = tmp_path_factory.mktemp(f"chain-{effect}")
            road = (["--road-x-m", f"{_ROADS[effect]():g}"] if effect in _ROADS else [])
            assert chain.main(["--effect", effect, *_SPEEDS.get(effect, []), *road,
                               "--out", str(out)]) == 0
            done[effect] = json.loads((out / "chain.json").read_text())
        return done[effect]
    return run


@pytest.mark.slow
@pytest.mark.parametrize("effect", EFFECTS)
def test_discover_names_the_effect_and_its_fit_scores_better_on_unseen_rows(effect, chains):
    r = chains(effect)
    assert r["named_effects"][:1] == [effect], r["named_effects"]
    v = r["validation"]
    assert v["effect"]["mean_crps_m"] < v["baseline"]["mean_crps_m"], v


@pytest.mark.slow
@pytest.mark.parametrize("effect", EFFECTS)
def test_the_effect_moves_the_road_exceedance_to_the_truth(effect, chains):
    """At the road, every size the truth or a fit brings there lies at least as close
    to the truth with the effect as without, and at least one size gets there."""
    r = chains(effect)
    road = {d: e["road"] for d, e in r["exceedance"].items()}
    live = [d for d, x in road.items()
            if max(x["truth"], x["baseline"][0], x["effect"][0]) > LIVE_P_EXCEED]
    assert live, road
    for d in live:
        x = road[d]
        assert abs(x["effect"][0] - x["truth"]) <= abs(x["baseline"][0] - x["truth"]), (d, x)


@pytest.mark.slow
@pytest.mark.parametrize("effect", [
    pytest.param(e, marks=pytest.mark.xfail(reason=_SHORT[e], strict=True)) if e in _SHORT
    else e for e in EFFECTS])
def test_the_effect_brings_every_station_closer_to_the_truth(effect, chains):
    """The stricter verdict: at every size, the mean |P - P_truth| over the stations
    the truth or a fit passes is no larger with the effect than without."""
    r = chains(effect)
    closer = [e["effect"]["mean_abs_error"] <= e["baseline"]["mean_abs_error"]
              for e in r["exceedance"].values() if e["n_stations"]]
    assert closer and all(closer), r["exceedance"]
