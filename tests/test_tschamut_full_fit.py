"""The main job on all 62 Tschamut runs, as a practitioner runs it on their own
data (``python -m calib.fit data/tschamut2014/observations.csv --model crsp
--seed S``), for three seeds: every check it makes must pass.

What passing means: the posterior's sampler diagnostics at the thresholds of
``calib.inference.bayes`` (rank-normalised R-hat < ``RHAT_MAX``, bulk and tail
ESS >= ``ESS_MIN``), at least 4 chains and every one kept by the chain
screening, the log-likelihood GP's realisation check, and no parameter with
more than ``calib.inference.adequacy.BOUND_FLAG`` of its posterior within
``BOUND_BAND`` of a prior bound (``bayes.ok`` and the adequacy record of
``calibration.json``). Each fit took 11.5-12.5 minutes on 2 cores: ``-m slow``.
"""

from __future__ import annotations

import json

import pytest

from calib.inference.adequacy import BOUND_FLAG

DATA = "data/tschamut2014/observations.csv"

# What each seed's fit measured (2026-12-05, 2 cores, one fit at a time, the same call as
# ``python -m calib.fit DATA --model crsp --seed S``, with 12 realisation waves).
# docs/studies.md, "Twelve realisation waves", reads the same failures: the best region
# at the edge of the Kt box (where the simulator's own posterior lies too), and a
# log-likelihood GP whose realisations put their peaks anywhere in the box.
_MEASURED = {
    1: "measured 2026-12-05 (692 s): R-hat <= 1.001, bulk ESS >= 3,961, 4 of 4 chains "
       "kept, 8.9 % of Kt within 2 % of its bound 0.98 (not flagged); the GP realisation "
       "check fails: the posterior medians of 32 GP realisations span Kn 0.23-0.59 and "
       "phi_r 5.7-38.3 deg against 90 % intervals 0.327-0.413 and 35.6-37.0 deg",
    2: "measured 2026-12-05 (797 s, the last NUTS run with twice the draws for its tail "
       "ESS of Kn, 385 before): R-hat <= 1.003, bulk ESS >= 1,875, tail ESS >= 717, 4 of 4 "
       "chains kept; 49 % of Kt within 2 % of its upper bound 0.98 (90 % interval "
       "0.937-0.979); the GP realisation check fails (Kn 0.29-0.59 against 0.331-0.494, "
       "phi_r 16.3-36.6 deg against 35.8-37.0)",
    3: "measured 2026-12-05 (753 s): R-hat <= 1.002, bulk ESS >= 1,875, 4 of 4 chains "
       "kept after a best-point wave; 39 % of Kt within 2 % of its upper bound 0.98 "
       "(90 % interval 0.942-0.979); the GP realisation check fails (Kn 0.35-0.59 "
       "against 0.353-0.431, phi_r 12.9-38.3 deg against 35.3-37.3)",
}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=_MEASURED[s])) for s in (1, 2, 3)])
def test_the_main_job_passes_every_check_on_all_tschamut_runs(seed, tmp_path):
    from calib.fit import main

    assert main([DATA, "--model", "crsp", "--seed", str(seed), "--out", str(tmp_path),
                 "--no-progress"]) == 0
    crsp = json.loads((tmp_path / "calibration.json").read_text())["crsp"]
    bayes, adequacy = crsp["bayes"], crsp["adequacy"]
    screen = bayes.get("chain_screen") or {}
    kept = screen.get("kept", [])
    piled = {n: max(b["lower"], b["upper"]) for n, b in adequacy["bounds"].items()}
    summary = {n: {k: round(float(v), 3) for k, v in s.items() if k in
                   ("rhat", "ess_bulk", "ess_tail")} for n, s in bayes["summary"].items()}
    measured = (f"problems: {bayes['problems']}; chains kept {sum(kept)} of {len(kept)}; "
                f"mass at a bound {piled}; diagnostics {summary}")
    assert len(kept) >= 4 and all(kept), measured
    assert max(piled.values()) <= BOUND_FLAG, measured
    assert bayes["ok"], measured
