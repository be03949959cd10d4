"""Slow paper-reproduction checks of the DEM (issue 3; run with ``pytest -m slow``).

Targets (paper Sect. 4, ../shared/seed): single blocks L = 0.2, 0.9, 1.8 m with
the Table 1 damping (alpha 0.90, 0.43, 0.30) stop in the observed 110-220 m
band with runout increasing with L; one alpha for all sizes loses that trend;
the 1.8 m block split into 4, 16, 64 fragments (alpha per fragment from the
Table 1 trend 0.40 L^-0.5) runs out less the finer it breaks, 16 fragments in
110-160 m and 64 fragments in 40-110 m.

All runs: kn = ks = 50 GPa/m x 0.01 (the documented stiffness scale), UDEC's
unbalanced-force damping, fixed keys. Monte Carlo tolerances come from the
standard error of the difference of means, never from the results.
Where a target is not met the test stays as written and is marked
``xfail(strict=True)`` with the measured numbers.
"""

from __future__ import annotations

import functools
import math

import jax
import numpy as np
import pytest

import solvers  # noqa: F401  (x64)
from solvers.dem import Options, make_block, make_params, stable_dt
from solvers.dem._integrate import simulate_batch
from solvers.profile import load_profile

pytestmark = pytest.mark.slow

PROFILE_CSV = "data/postignano_profile.csv"
SCALE = 0.01
N_SINGLE = 48          # single blocks per size
MAX_TIME_S = 400.0     # simulated-time bound; a run still moving then fails "at rest"
BAND_M = (110.0, 220.0)


@functools.cache
def _params():
    return make_params(load_profile(PROFILE_CSV), stiffness_scale=SCALE)


@functools.cache
def singles(size_m: float, alpha: float):
    """Runouts (m) of N_SINGLE single blocks, and the stopped flags."""
    params = _params()
    block = make_block(size_m, alpha=alpha)
    keys = jax.random.split(jax.random.key(11), N_SINGLE)
    opts = Options(max_steps=int(MAX_TIME_S / float(stable_dt(params, block))))
    res = simulate_batch(params, block, keys, opts)
    return np.asarray(res.runout_m)[:, 0], np.asarray(res.stopped)[:, 0]


@functools.cache
def fragments(n_fragments: int, seed: int = 0):
    """Per-fragment runouts (m) and stopped flags of one fragmented 1.8 m block."""
    params = _params()
    block = make_block(1.8, n_fragments=n_fragments)
    opts = Options(max_steps=int(MAX_TIME_S / float(stable_dt(params, block))))
    res = simulate_batch(params, block, jax.random.key(seed)[None], opts)
    return np.asarray(res.runout_m)[0], np.asarray(res.stopped)[0]


def _se_diff(a, b):
    return math.sqrt(np.var(a, ddof=1) / a.size + np.var(b, ddof=1) / b.size)


def test_size_trend_with_table1_alphas():
    """Runout increases with L (each step by more than 2 standard errors), every
    median lies in the observed 110-220 m band, all blocks at rest."""
    runs = [singles(L, a) for L, a in ((0.2, 0.90), (0.9, 0.43), (1.8, 0.30))]
    for r, stopped in runs:
        assert stopped.all()
    med = [float(np.median(r)) for r, _ in runs]
    for (a, _), (b, _) in zip(runs[:-1], runs[1:], strict=True):
        assert b.mean() - a.mean() > 2.0 * _se_diff(a, b), med
    assert all(BAND_M[0] <= m <= BAND_M[1] for m in med), med


def test_size_trend_lost_with_one_alpha():
    """With alpha 0.43 for every size the 0.2 m and 1.8 m blocks run out the
    same within 3 standard errors, while with the Table 1 alphas they differ by
    more than 3 (the paper's reason for alpha(L))."""
    small, _ = singles(0.2, 0.43)
    large, _ = singles(1.8, 0.43)
    assert abs(large.mean() - small.mean()) < 3.0 * _se_diff(small, large)
    t_small, _ = singles(0.2, 0.90)
    t_large, _ = singles(1.8, 0.30)
    assert t_large.mean() - t_small.mean() > 3.0 * _se_diff(t_small, t_large)


def test_runout_decreases_with_fragment_count():
    """Median fragment runout: 4 > 16 > 64 fragments (one block each)."""
    med = {n: float(np.median(fragments(n)[0])) for n in (4, 16, 64)}
    assert med[4] > med[16] > med[64], med


@pytest.mark.xfail(strict=True, reason="measured (key 0, scale 0.01, at rest): 16 fragments "
                   "stop at 108.5-128.8 m; the lower end is 1.5 m short of the paper's 110 m "
                   "and the upper part of 110-160 m is not reached (scripts/dem_reproduce.py, "
                   "2 other keys: 107-124 m)")
def test_sixteen_fragments_in_paper_range():
    """Paper Fig. 5: the 16 fragments stop between 110 and 160 m (all at rest)."""
    r, stopped = fragments(16)
    assert stopped.all(), f"{int(stopped.sum())}/16 at rest"
    assert r.min() >= 110.0 and r.max() <= 160.0, (float(r.min()), float(r.max()))


def test_sixty_four_fragments_in_paper_range():
    """Paper Fig. 6: the 64 fragments stop between 40 and 110 m (10th-90th
    percentile), most of them above the slope break at 110 m (all at rest)."""
    r, stopped = fragments(64)
    assert stopped.all(), f"{int(stopped.sum())}/64 at rest"
    p10, p90 = np.percentile(r, [10, 90])
    assert p10 >= 40.0 and p90 <= 110.0, (float(p10), float(p90))


@pytest.mark.xfail(strict=True, reason="measured (scale 0.01, at rest) by scripts/"
                   "dem_reproduce.py and the DEM bench (two other keys): 64 fragments stop at "
                   "p10-p90 101-110 m (min-max 100-111 m), a one-layer queue at the foot of "
                   "the talus, no wider than the 16-fragment deposit (p10-p90 108-118 m); the "
                   "paper's 64 fragments spread over 40-110 m")
def test_sixty_four_fragments_spread_wider_than_sixteen():
    """Paper Sect. 4.2: the smallest fragments 'spread over a larger area' (40-110 m)
    than the 16 fragments (110-160 m): p10-p90 width of 64 > that of 16, and the
    64-fragment p10 below 70 m (the upper half of the paper's 40-110 m range)."""
    r16, r64 = fragments(16)[0], fragments(64)[0]
    w16 = np.subtract(*np.percentile(r16, [90, 10]))
    w64 = np.subtract(*np.percentile(r64, [90, 10]))
    assert w64 > w16 and np.percentile(r64, 10) < 70.0, (float(w16), float(w64))
