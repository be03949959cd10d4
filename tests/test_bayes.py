"""The NUTS diagnostics of ``calib.inference.bayes`` (rank-normalised R-hat, bulk and tail
ESS, computed by ArviZ) on synthetic chains whose answer is known."""

from __future__ import annotations

import numpy as np

from calib.inference.bayes import ESS_MIN, RHAT_MAX, chain_diagnostics


def test_well_mixed_chains_pass_and_a_stuck_chain_fails():
    # 4 chains x 1000 independent N(0, 1) draws of 2 parameters: R-hat is 1 up to
    # its sampling error (about 1/(2 * 4000) ~ 1e-4 per parameter, far inside 1.01)
    rng = np.random.default_rng(0)
    good = rng.standard_normal((4, 1000, 2))
    rhat, bulk, tail = chain_diagnostics(good)
    assert rhat.shape == bulk.shape == tail.shape == (2,)
    assert np.all(np.abs(rhat - 1.0) < 0.005) and np.all(rhat < RHAT_MAX)
    # independent draws: ESS about the 4000 draws (its relative sd is a few %)
    assert np.all((bulk > 3000) & (bulk < 5000)) and np.all(tail > 2000)
    # one chain stuck in another mode (shifted by 3 sd, its own small spread)
    stuck = good.copy()
    stuck[0, :, 0] = 3.0 + 0.1 * stuck[0, :, 0]
    rhat, bulk, tail = chain_diagnostics(stuck)
    assert rhat[0] > 1.3 and rhat[1] < RHAT_MAX
    assert tail[0] < ESS_MIN < tail[1]


def test_a_chain_with_a_different_scale_fails_the_rank_statistic():
    # equal means, one chain 3x wider: the folded (tail) part of the rank-normalised
    # R-hat sees it; classic split R-hat on the draws themselves stays near 1
    rng = np.random.default_rng(1)
    x = rng.standard_normal((4, 1000, 1))
    x[0] *= 3.0
    rhat, _, _ = chain_diagnostics(x)
    assert rhat[0] > RHAT_MAX
    half = np.concatenate([x[:, :500, 0], x[:, 500:, 0]])  # split chains, untransformed
    n = half.shape[1]
    w = half.var(axis=1, ddof=1).mean()
    b = n * half.mean(axis=1).var(ddof=1)
    assert np.sqrt(((n - 1) / n * w + b / n) / w) < RHAT_MAX
