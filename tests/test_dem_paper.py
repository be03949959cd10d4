"""Slow paper-reproduction checks of the DEM (run with ``pytest -m slow``).

Targets (paper Sect. 4, ../shared/seed): single blocks L = 0.2, 0.9, 1.8 m with
the Table 1 damping (alpha 0.90, 0.43, 0.30) stop in the observed 110-220 m
band with runout increasing with L; one alpha for all sizes loses that trend;
the 1.8 m block split into 4, 16, 64 fragments (alpha per fragment from the
Table 1 trend 0.40 L^-0.5) runs out less the finer it breaks, 16 fragments in
110-160 m and 64 fragments in 40-110 m.

All runs: kn = ks = 50 GPa/m x 0.01 (the documented stiffness scale; joint
strengths x sqrt(0.01)), UDEC's unbalanced-force damping, fixed
keys, the DEM's rest test (rest only where statically admissible; a
run still moving at MAX_TIME_S is not at rest and its "runout" is a position,
not a runout). Monte Carlo tolerances come from the standard error of the
difference of means, never from the results. Where a target is not met the
test stays as written and is marked ``xfail(strict=True)`` with the measured
numbers.
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
    """Median fragment runout: 4 > 16 fragments (one block each, all at rest)."""
    (r4, s4), (r16, s16) = fragments(4), fragments(16)
    assert s4.all() and s16.all(), (int(s4.sum()), int(s16.sum()))
    assert np.median(r4) > np.median(r16), (float(np.median(r4)), float(np.median(r16)))


def test_runout_decreases_from_16_to_64_fragments():
    """Median fragment runout: 16 > 64 fragments, both at rest (paper Sect. 4.2)."""
    (r16, s16), (r64, s64) = fragments(16), fragments(64)
    assert s16.all() and s64.all(), (int(s16.sum()), int(s64.sum()))
    assert np.median(r16) > np.median(r64), (float(np.median(r16)), float(np.median(r64)))


@pytest.mark.xfail(strict=True, reason="measured (key 0, scale 0.01, the least-overlap pair "
                   "contact with shear springs): the 16 fragments are at rest between 108.7 and "
                   "127.1 m (median 112.0, p10-p90 109.2-124.2 m; 108.1-126.3 m with friction "
                   "regularised in the slip speed, 107.9-123.8 m with the earlier corner "
                   "contact); the lowest is 1.3 m short of the paper's 110 m and the upper part "
                   "of 110-160 m is not reached (the runs are chaotic: another compilation of "
                   "an earlier run gave 108.3-144.5 m)")
def test_sixteen_fragments_in_paper_range():
    """Paper Fig. 5: the 16 fragments stop between 110 and 160 m (all at rest)."""
    r, stopped = fragments(16)
    assert stopped.all(), f"{int(stopped.sum())}/16 at rest"
    assert r.min() >= 110.0 and r.max() <= 160.0, (float(r.min()), float(r.max()))


@pytest.mark.xfail(strict=True, reason="measured (key 0, scale 0.01, the least-overlap pair "
                   "contact with shear springs): all 64 at rest, positions p10-p90 102.0-111.0 m "
                   "(min-max 100.9-112.9, median 106.4): p10 inside the paper's 40-110 m, p90 "
                   "1.0 m beyond it; a queue on the 40 deg talus held by the fragments at its "
                   "foot and by friction between fragments, not spread up the slope. With "
                   "friction regularised in the slip speed the queue never rested (0/64 at "
                   "400 s, p10-p90 101.5-110.3 m). With every damping off the rested queue "
                   "slides 1.2 m in 5 s (deposit check): at rest under the model's damping, "
                   "at the edge of what friction holds")
def test_sixty_four_fragments_in_paper_range():
    """Paper Fig. 6: the 64 fragments stop between 40 and 110 m (10th-90th
    percentile), most of them above the slope break at 110 m (all at rest)."""
    r, stopped = fragments(64)
    assert stopped.all(), f"{int(stopped.sum())}/64 at rest"
    p10, p90 = np.percentile(r, [10, 90])
    assert p10 >= 40.0 and p90 <= 110.0, (float(p10), float(p90))


@pytest.mark.xfail(strict=True, reason="measured (key 0, scale 0.01, the least-overlap pair "
                   "contact with shear springs): the 64 fragments rest at p10-p90 102.0-111.0 m "
                   "(width 8.9 m), a queue at the foot of the talus, narrower than the "
                   "16-fragment deposit (p10-p90 109.2-124.2 m, width 15.0 m; with friction "
                   "regularised in the slip speed 8.8 m against 13.1 m); the paper's 64 "
                   "fragments spread over 40-110 m")
def test_sixty_four_fragments_spread_wider_than_sixteen():
    """Paper Sect. 4.2: the smallest fragments 'spread over a larger area' (40-110 m)
    than the 16 fragments (110-160 m): p10-p90 width of 64 > that of 16, and the
    64-fragment p10 below 70 m (the upper half of the paper's 40-110 m range)."""
    r16, r64 = fragments(16)[0], fragments(64)[0]
    w16 = np.subtract(*np.percentile(r16, [90, 10]))
    w64 = np.subtract(*np.percentile(r64, [90, 10]))
    assert w64 > w16 and np.percentile(r64, 10) < 70.0, (float(w16), float(w64))


# ------------------------------------------------ joint strength under the stiffness scale

N_BREAK = 16
BREAK_TIME_S = 6.0     # release, first impacts on the talus and a little after


@functools.cache
def breakage(stiffness_scale: float, strength_pa: float) -> np.ndarray:
    """Fraction of joints broken per block (N_BREAK blocks, key(0) split) of the
    1.8 m block in 4 fragments with c = t = strength, in the first BREAK_TIME_S."""
    params = make_params(load_profile(PROFILE_CSV), stiffness_scale=stiffness_scale,
                         c_joint_pa=strength_pa, t_joint_pa=strength_pa)
    block = make_block(1.8, n_fragments=4)
    opts = Options(max_steps=int(BREAK_TIME_S / float(stable_dt(params, block))))
    keys = jax.random.split(jax.random.key(0), N_BREAK)
    return np.asarray(simulate_batch(params, block, keys, opts).joints_broken)


@pytest.mark.parametrize("strength_pa", [1e6, 1e7])
def test_breakage_invariant_under_stiffness_shortcut(strength_pa):
    """Joint breakage at kn x 0.01 equals that at the paper's kn within noise:
    |mean difference| <= 2 standard errors of the difference + one joint of one
    block (1 / (4 N)). Peak impact forces scale as sqrt(k), so the strengths are
    scaled by sqrt(stiffness_scale) (``Params.joint_strength_exponent``).
    With unscaled strengths, at 1 MPa: 0.375 at x0.01 against 1.0
    at x1 (16 blocks)."""
    full, short = breakage(1.0, strength_pa), breakage(SCALE, strength_pa)
    assert abs(full.mean() - short.mean()) <= 2.0 * _se_diff(full, short) + 1.0 / (4 * N_BREAK), \
        (float(full.mean()), float(short.mean()))
