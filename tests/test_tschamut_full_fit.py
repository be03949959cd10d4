"""The main job on all 62 Tschamut runs, as a practitioner runs it on their own
data (``python -m calib.fit data/tschamut2014/observations.csv --model crsp
--seed S``), for three seeds: every check it makes must pass.

What passing means: the posterior's sampler diagnostics at the thresholds of
``calib.inference.bayes`` (rank-normalised R-hat < ``RHAT_MAX``, bulk and tail
ESS >= ``ESS_MIN``), at least 4 chains and every one kept by the chain
screening, the log-likelihood GP's realisation check, and no parameter with
more than ``calib.inference.adequacy.BOUND_FLAG`` of its posterior within
``BOUND_BAND`` of a prior bound (``bayes.ok`` and the adequacy record of
``calibration.json``). Each fit took 5-15 minutes on 2 cores, by the machine: ``-m slow``.
"""

from __future__ import annotations

import json

import pytest

from calib.inference.adequacy import BOUND_BAND, BOUND_FLAG

DATA = "data/tschamut2014/observations.csv"

# What the three fits measured, on two machines. Each fit is deterministic on one machine
# and installation, but XLA compiles for the host's processor, so the last digits of a
# simulation, and from them a fit's path, differ between machines: the seed that passes
# moves, while on every machine measured at least one seed piles Kt on its bound, the end
# of a ridge the runouts leave open (docs/studies.md, "Where Kt's bound comes from" and
# "The three seeds on a faster machine"). The requirement is all three seeds, so the test
# asks for all three and reports each.
_MEASURED = (
    "measured 2026-12-08 (2 cores, 169,717 CRSP blocks/s of 1 m in `python -m solvers.bench "
    "--no-dem`, jax 0.10.2, numpyro 0.22.0): every sampler diagnostic and the GP realisation "
    "check pass for all three seeds (R-hat <= 1.002, bulk ESS >= 1,831, 4 of 4 chains kept, no "
    "divergences), in 316, 357 and 362 s; Kt's mass within 2 % of its upper bound 0.98 is "
    "27 % (seed 1, flagged), 9 % (seed 2) and 11 % (seed 3, flagged). On 2026-12-06 on a "
    "machine half as fast (85,514 blocks/s): 29 % and 12 % (flagged), 9 % (seed 3), in 805, "
    "600 and 878 s")


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=_MEASURED)
def test_the_main_job_passes_every_check_on_all_tschamut_runs_for_three_seeds(tmp_path):
    from calib.fit import main

    failed = {}
    for seed in (1, 2, 3):
        out = tmp_path / f"seed-{seed}"
        assert main([DATA, "--model", "crsp", "--seed", str(seed), "--out", str(out),
                     "--no-progress"]) == 0
        problems = _problems(json.loads((out / "calibration.json").read_text())["crsp"])
        if problems:
            failed[seed] = problems
    assert not failed, failed


def _problems(crsp: dict) -> list[str]:
    """What keeps one fit from passing every check (empty when it passes)."""
    bayes, adequacy = crsp["bayes"], crsp["adequacy"]
    screen = bayes.get("chain_screen") or {}
    kept = screen.get("kept", [])
    piled = {n: max(b["lower"], b["upper"]) for n, b in adequacy["bounds"].items()}
    summary = {n: {k: round(float(v), 3) for k, v in s.items() if k in
                   ("rhat", "ess_bulk", "ess_tail")} for n, s in bayes["summary"].items()}
    out = []
    if len(kept) < 4 or not all(kept):
        out.append(f"chains kept {sum(kept)} of {len(kept)}")
    out += [f"{n}: {m:.1%} within {BOUND_BAND:.0%} of a bound" for n, m in piled.items()
            if m > BOUND_FLAG]
    if not bayes["ok"]:
        out.append(f"posterior problems {bayes['problems']}; diagnostics {summary}")
    return out
