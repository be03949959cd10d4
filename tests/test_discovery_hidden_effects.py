"""Proof of the discrepancy workflow on data with a hidden effect (slow).

For each effect (and the null), 5 synthetic data sets (CRSP, 60 rows over six
sizes 0.2-2.0 m, sd 5 m, strength 1 = "moderate", seeds 1001-1005, which no
development run used) go through the default workflow. Required: the
effect is named in at least 4 of 5 seeds; on null data ``none`` in at least
4 of 5; whenever an effect is named, gap_after < gap_before.

Run: ``pytest -m slow -s tests/test_discovery_hidden_effects.py`` (17 minutes
on 2 cores on 2026-11-24); it prints the confusion matrix.

How the two shortfalls depend on the number of rows and on strength is
measured by ``python -m calib.power`` (other unseen seeds, 3001-3005;
docs/studies.md, "How much data does discover need?"): with 180 rows
fragmentation is named in 5 of 5, the vegetation belt in 0 of 5. On seeds
5001-5005 at 60 rows fragmentation was named in 1 of 5, and in 2 of 5 with 4 times the blocks
(``--n-blocks 512``, simulation sd 2.0 -> 0.5 nats): the shortfall is the data's
standard error, not the simulation noise. The belt needs another kind of
observation: with 30 passage speeds at 110 m added to the same 60 runout rows
(``calib.discover --velocities``) it was named in 4 of 5 unseen seeds
(8001-8005), against 2 of 5 on those seeds without the speeds
(docs/studies.md, "Passage speeds"). With 180 runout rows plus those 30 speeds
(unseen seeds 9001-9005, docs/studies.md, "One data design that names every
effect") every effect was named in at least 4 of 5 runs and the null gave
``none`` 5 of 5. This test keeps its first design, 60 runout rows and no speeds.
"""

import json
import os

import jax
import numpy as np
import pytest

from calib.discovery.candidates import crsp_candidates
from calib.discovery.discrepancy import discover
from calib.discovery.synthetic import synthesize_effect
from calib.inference.budget import DISCOVERY_PRESETS as PRESETS
from calib.model.effects import EFFECT_NAMES
from solvers.profile import load_profile

pytestmark = pytest.mark.slow

PROFILE = load_profile("data/postignano_profile.csv")
SEEDS = (1001, 1002, 1003, 1004, 1005)
RESULTS: dict[str, list[dict]] = {}


def _run(effect: str) -> list[dict]:
    out = []
    for seed in SEEDS:
        obs, _ = synthesize_effect(PROFILE, effect, 1.0, 60, seed)
        d = discover(crsp_candidates(PROFILE), obs, PROFILE, jax.random.key(0), PRESETS["crsp"])
        row = {"seed": seed, "named": d.named_effect, "gap_before": d.gap_before,
               "gap_after": d.gap_after,
               "gains": {r["effect"]: (round(r["delta_vs_none"], 1), round(r["se_delta"], 1))
                         for r in d.table}}
        print(f"{effect} seed {seed}: named {row['named']}, gap {d.gap_before:.2f} -> "
              f"{d.gap_after:.2f} m, gains {row['gains']}", flush=True)
        out.append(row)
    RESULTS[effect] = out
    path = os.environ.get("DISCOVERY_RESULTS")
    if path:
        with open(path, "w") as f:
            json.dump(RESULTS, f, indent=1)
    return out


_SHORT = {
    # Measured with this test at the default budget (2026-11-21).
    # The requirement stays 4 of 5; the belt does not reach it at
    # moderate strength with 60 rows, and every miss was "none", not another effect.
    # Fragmentation was the second shortfall (3 of 5 on 2026-11-21); with one likelihood
    # shared by calib.fit and calib.discover it was named in
    # 4 of 5 (2026-11-24: 1001 gain 14.6 +- 6.8 nats, 1003-1005; 1002 named
    # size_dissipation), so it is held to the requirement again.
    # Again 2026-12-05 (2 cores beside other runs, 1,865 s for the five): named in 0 of 5,
    # none every time; the belt's gains -0.3 +- 0.6, +1.9 +- 2.6, +0.2 +- 1.1,
    # -0.1 +- 0.7, -0.1 +- 1.2 nats. A strict xfail: it fails while the belt stays
    # unnamed at this design, and says so when it no longer does.
    "vegetation_belt": "named in 0 of 5 seeds (2026-12-05: belt gains -0.3 to +1.9 nats, "
                       "none named each time): a baseline with a "
                       "lower Kt reproduces the belt's shorter, narrower runouts of large "
                       "blocks about as well as the belt does (development seed 101: "
                       "log-likelihood at the truth -230.8, baseline's best -230.3)",
}


@pytest.mark.parametrize("effect", [
    pytest.param(e, marks=pytest.mark.xfail(reason=_SHORT[e], strict=True)) if e in _SHORT
    else e for e in EFFECT_NAMES])
def test_hidden_effect_is_named_in_4_of_5_seeds(effect):
    rows = _run(effect)
    hits = sum(r["named"] == effect for r in rows)
    for r in rows:
        if r["named"] != "none":
            assert r["gap_after"] < r["gap_before"], r
    assert hits >= 4, f"{effect}: named in {hits} of 5 seeds: {[r['named'] for r in rows]}"


def test_print_confusion_matrix():
    if not RESULTS:
        pytest.skip("run together with the per-effect tests")
    names = list(EFFECT_NAMES)
    print("\ntrue \\ named: " + " ".join(f"{n[:10]:>10}" for n in names))
    for eff, rows in RESULTS.items():
        counts = [sum(r["named"] == n for r in rows) for n in names]
        print(f"{eff[:13]:13}  " + " ".join(f"{c:>10}" for c in counts))
    ratios = [r["gap_after"] / r["gap_before"] for rows in RESULTS.values() for r in rows
              if r["named"] != "none"]
    if ratios:
        print(f"gap_after / gap_before when an effect was named: median {np.median(ratios):.2f}, "
              f"range {min(ratios):.2f}-{max(ratios):.2f} over {len(ratios)} runs")
