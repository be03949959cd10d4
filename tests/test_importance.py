"""Pareto-smoothed importance weights (``calib.inference.importance``): k-hat on sets
whose tail is known."""

from __future__ import annotations

import numpy as np
import pytest

from calib.inference.importance import KHAT_MAX, MIN_POINTS, ess, psis_weights


def test_near_uniform_weights_have_a_small_khat_and_stay_put():
    rng = np.random.default_rng(0)
    lr = 0.1 * rng.standard_normal(1000)  # log-normal weights, sd 0.1: light tail
    w, khat = psis_weights(lr)
    assert khat < 0.5
    assert w.sum() == pytest.approx(1.0) and np.all(w > 0)
    raw = np.exp(lr) / np.exp(lr).sum()
    assert np.max(np.abs(w / raw - 1)) < 0.05  # smoothing barely moves them
    assert ess(w) > 950


def test_heavy_tailed_weights_are_flagged_and_smoothed():
    # Pareto ratios with tail index 1/0.9: true k = 0.9 (infinite variance);
    # k-hat's sd at 1000 points and 94 tail points is about 0.1
    rng = np.random.default_rng(1)
    lr = np.log1p(rng.pareto(1 / 0.9, 1000))
    w, khat = psis_weights(lr + 123.0)  # any additive constant
    assert khat > KHAT_MAX
    raw = np.exp(lr - lr.max())
    raw /= raw.sum()
    assert w.max() <= raw.max() + 1e-12 and w.sum() == pytest.approx(1.0)


def test_degenerate_and_small_sets():
    rng = np.random.default_rng(2)
    # the tail spans more than the float range: one point carries everything
    w, khat = psis_weights(1000.0 * rng.standard_normal(500))
    assert khat == np.inf and w.max() > 0.9 and w.sum() == pytest.approx(1.0)
    # too few points for a tail fit: raw weights, k-hat not estimated
    lr = rng.standard_normal(MIN_POINTS - 1)
    w, khat = psis_weights(lr)
    assert np.isnan(khat)
    np.testing.assert_allclose(w, np.exp(lr) / np.exp(lr).sum())
    # a point of zero likelihood gets weight 0
    lr = rng.standard_normal(100)
    lr[3] = -np.inf
    w, khat = psis_weights(lr)
    assert w[3] == 0.0 and np.isfinite(khat) and w.sum() == pytest.approx(1.0)


def test_the_khat_bar_falls_with_fewer_points():
    """min(0.7, 1 - 1/log10 S) (Vehtari et al. 2024): 0.631 at S = 512, 0.7 from
    S = 2155 on, nothing trusted at S <= 10."""
    from calib.inference.importance import khat_threshold

    assert khat_threshold(512) == pytest.approx(1 - 1 / np.log10(512))
    assert khat_threshold(512) == pytest.approx(0.631, abs=5e-4)
    assert khat_threshold(10_000) == KHAT_MAX
    assert khat_threshold(10) == 0.0
    bars = [khat_threshold(n) for n in (32, 256, 512, 1024, 4096)]
    assert bars == sorted(bars)
