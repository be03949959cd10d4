"""The main job on all 62 Tschamut runs, as a practitioner runs it on their own
data (``python -m calib.fit data/tschamut2014/observations.csv --model crsp
--seed S``), for three seeds: every check it makes must pass.

What passing means: the posterior's sampler diagnostics at the thresholds of
``calib.inference.bayes`` (rank-normalised R-hat < ``RHAT_MAX``, bulk and tail
ESS >= ``ESS_MIN``), at least 4 chains and every one kept by the chain
screening, the log-likelihood GP's realisation check, and no parameter with
more than ``calib.inference.adequacy.BOUND_FLAG`` of its posterior within
``BOUND_BAND`` of a prior bound (``bayes.ok`` and the adequacy record of
``calibration.json``). Each fit took 5.5-6.5 minutes on 2 cores: ``-m slow``.
"""

from __future__ import annotations

import json

import pytest

from calib.inference.adequacy import BOUND_FLAG

DATA = "data/tschamut2014/observations.csv"

# What each seed's fit measured (2026-12-05, 2 cores, one fit at a time, the same call as
# ``python -m calib.fit DATA --model crsp --seed S``). docs/studies.md, "The three seeds
# again, on the current code", reads the same failures: the best region at the edge of
# the Kt box (where the simulator's own posterior lies too), and a log-likelihood GP
# whose uncertainty spans the box.
_MEASURED = {
    1: "measured 2026-12-05 (330 s): R-hat <= 1.002, bulk ESS >= 1,431, 4 of 4 chains "
       "kept, at most 0.2 % of Kn near a bound; the GP realisation check fails: the "
       "posterior medians of 32 GP realisations span Kn 0.29-0.59 and phi_r 6.4-38.4 deg "
       "against 90 % intervals 0.461-0.559 and 29.5-35.8 deg",
    2: "measured 2026-12-05 (359 s): R-hat <= 1.001, bulk ESS >= 4,421, 4 of 4 chains "
       "kept; 89 % of Kt within 2 % of its upper bound 0.98 (90 % interval 0.971-0.979); "
       "the GP realisation check fails (Kn 0.18-0.60 against 0.376-0.456)",
    3: "measured 2026-12-05 (374 s): R-hat <= 1.002, bulk ESS >= 2,821, 4 of 4 chains "
       "kept after a best-point wave; 77 % of Kt within 2 % of its upper bound 0.98 "
       "(90 % interval 0.966-0.979); the GP realisation check fails (Kn 0.29-0.59 "
       "against 0.361-0.488, phi_r 6.2-39.8 deg against 32.7-37.1)",
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
