"""The main job on all 62 Tschamut runs, as a practitioner runs it on their own
data (``python -m calib.fit data/tschamut2014/observations.csv --model crsp
--seed S``), for three seeds: every check it makes must pass.

What passing means: the posterior's sampler diagnostics at the thresholds of
``calib.inference.bayes`` (rank-normalised R-hat < ``RHAT_MAX``, bulk and tail
ESS >= ``ESS_MIN``), at least 4 chains and every one kept by the chain
screening, the log-likelihood GP's realisation check, and no parameter with
more than ``calib.inference.adequacy.BOUND_FLAG`` of its posterior within
``BOUND_BAND`` of a prior bound (``bayes.ok`` and the adequacy record of
``calibration.json``). Each fit took 10-15 minutes on 2 cores: ``-m slow``.
"""

from __future__ import annotations

import json

import pytest

from calib.inference.adequacy import BOUND_FLAG

DATA = "data/tschamut2014/observations.csv"

# What each seed's fit measured (2026-12-06, 2 cores, one fit at a time, the same call as
# ``python -m calib.fit DATA --model crsp --seed S``, at the site file's rolling threshold
# 0.05 m/s, jax 0.10.2 and numpyro 0.22.0): every sampler diagnostic and the GP realisation
# check pass for all three, seed 1 after its careful run; seeds 1 and 2 pile mass on Kt's
# bound, the end of a ridge the runouts leave open. docs/studies.md, "Divergences repaired
# with a smaller step" and "Where Kt's bound comes from".
_MEASURED = {
    1: "measured 2026-12-06 (805 s): R-hat <= 1.002, bulk ESS >= 1,760, tail ESS >= 2,261, "
       "4 of 4 chains kept, the GP realisation check passed after 3 waves, a careful run after "
       "4 divergences; 29 % of Kt within 2 % of its upper bound 0.98 (90 % interval "
       "0.944-0.978)",
    2: "measured 2026-12-06 (600 s): R-hat <= 1.002, bulk ESS >= 2,574, tail ESS >= 2,092, "
       "4 of 4 chains kept, the GP realisation check passed after 2 waves; 12 % of Kt within "
       "2 % of its upper bound 0.98 (90 % interval 0.932-0.977)",
    3: None,  # measured 2026-12-06 (878 s): every check passed; Kt 9 % near its bound
}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    pytest.param(s, marks=() if _MEASURED[s] is None else
                 pytest.mark.xfail(strict=True, reason=_MEASURED[s])) for s in (1, 2, 3)])
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
