"""The discovery loop end to end on a synthetic site with a known hidden effect
(``scripts/hidden_effect_chain.py``): discover names the effect, the fit with it
scores better than the baseline on rows of the same site that no fit saw, and
its hazard exceedance lies closer to the truth's.

The chains themselves are slow (``pytest -m slow tests/test_hidden_effect_chain.py``:
about 20 minutes per effect on 2 cores (size dissipation, 2026-12-03: 1212 s), 180 rows,
the default budgets; the vegetation belt with 30 passage speeds at 110 m as well, the
design docs/studies.md found it needs, fitted by discover and by both fits); the
script's own bookkeeping is checked in the default run.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from cli_run import load_script

from calib.discovery.synthetic import compare_exceedance

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

_SHORT = {
    # measured with this test's chain (2026-11-27, docs/studies.md, "The loop closed on
    # a known truth"; again 2026-12-05, "The other three chains, rerun with the
    # best-point waves"; "The fragmentation and belt chains with twelve realisation
    # waves"): everything else held; the requirement stays
    "fragmentation": "0.2 m blocks: mean |P - P_truth| 0.010 with the effect against "
                     "0.009 for the baseline over 33 stations (0.5-2.0 m: 0.013-0.016 "
                     "against 0.021-0.119); again 2026-12-05: 0.0093 against 0.0090 "
                     "(0.5-2.0 m: 0.013-0.017 against 0.021-0.119); again 2026-12-05 with 12 "
                     "realisation waves: 0.0093 against 0.0090; small blocks seldom "
                     "break, so the two fits differ there by Monte Carlo error",
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


@pytest.mark.slow
@pytest.mark.parametrize("effect", [
    pytest.param(e, marks=pytest.mark.xfail(reason=_SHORT[e], strict=True)) if e in _SHORT
    else e for e in ("size_dissipation", "rolling_resistance", "fragmentation",
                     "vegetation_belt")])
def test_the_named_effect_refits_scores_better_and_moves_the_hazard_to_the_truth(
        effect, tmp_path):
    assert chain.main(["--effect", effect, *_SPEEDS.get(effect, []),
                       "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "chain.json").read_text())
    assert r["named_effects"][:1] == [effect], r["named_effects"]
    v = r["validation"]
    assert v["effect"]["mean_crps_m"] < v["baseline"]["mean_crps_m"], v
    closer = [e["effect"]["mean_abs_error"] <= e["baseline"]["mean_abs_error"]
              for e in r["exceedance"].values() if e["n_stations"]]
    assert closer and all(closer), r["exceedance"]
