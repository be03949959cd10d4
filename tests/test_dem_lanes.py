"""How DEM blocks share a compiled call: a block's result does not depend on
its place in the call (``solvers.dem._sums``), and the forward model
(``calib.model.forward.DemForward``) runs one block size per call and hands
the runouts back in entry order."""

from __future__ import annotations

import jax
import numpy as np

import calib  # noqa: F401  (x64)
from calib.model.dem_run import DEM_RUN
from calib.model.entries import Entries
from calib.model.forward import DemForward, dem_lanes, entry_blocks, lane_calls, stack_trees
from solvers.dem import make_block
from solvers.profile import load_profile

PROFILE = load_profile("data/postignano_profile.csv")
# 0.2 and 2 m blocks on the gentle lower slope, where they come to rest within seconds
ENTRIES = Entries.at_sizes([0.2, 2.0, 0.2], 150.0)
ALPHA = np.array([[0.9, 0.3, 0.5], [0.2, 0.6, 0.95]])  # (T, S): one alpha per entry


def _spied(fw: DemForward, widths: list | None = None) -> list[list[float]]:
    """Record the block sides of every compiled call ``fw`` makes (and its
    number of lanes in ``widths``)."""
    fn, sides = fw._compiled(), []

    def spy(blocks, keys):
        sides.append(sorted(set(np.asarray(blocks.size_m).tolist())))
        if widths is not None:
            widths.append(len(np.asarray(blocks.size_m)))
        return fn(blocks, keys)

    fw._fn = spy
    return sides


def test_each_compiled_call_runs_blocks_of_one_size():
    """A vmapped call runs until its slowest lane stops, and a small block takes
    many more (shorter) steps than a large one (``calib.model.forward.
    lane_calls``): 2 parameter sets x 3 entries x 2 blocks = 12 lanes in calls
    of 4 hold one size each (8 lanes of 0.2 m, then 4 of 2 m); filled in
    (parameter set, entry, block) order, every call would hold both."""
    fw = DemForward(PROFILE, ENTRIES, 2, jax.random.key(0), form="constant", lane_batch=4)
    sides = _spied(fw)
    r = fw.runouts_at_alpha(ALPHA)
    assert r.shape == (2, 3, 2) and np.all(np.isfinite(r)), r
    assert sides == [[0.2], [0.2], [2.0]], sides


def test_a_side_whose_lanes_do_not_fill_its_calls_gets_a_padded_call_of_its_own():
    """15 lanes (10 of 0.2 m, 5 of 2 m) in calls of at most 4: the 0.2 m lanes
    take three calls, the 2 m lanes two, the last of each padded (cut in running
    order, the third call would hold 2 lanes of 0.2 m and 2 of 2 m, and run all
    four for the small blocks' steps)."""
    widths = []
    fw = DemForward(PROFILE, ENTRIES, 5, jax.random.key(0), form="constant", lane_batch=4)
    sides = _spied(fw, widths)
    r = fw.runouts_at_alpha(ALPHA[:1])
    assert sides == [[0.2]] * 3 + [[2.0]] * 2, sides
    assert widths == [4] * 5, widths
    assert r.shape == (1, 3, 5) and np.all(np.isfinite(r)), r


def test_a_small_run_is_not_padded_to_the_call_width():
    """One parameter set of 3 entries x 2 blocks (4 lanes of 0.2 m, 2 of 2 m)
    with calls of at most 32: the calls are as wide as the largest side (4
    lanes), not 32 lanes of which 26 repeat one lane."""
    widths = []
    fw = DemForward(PROFILE, ENTRIES, 2, jax.random.key(0), form="constant")
    sides = _spied(fw, widths)
    r = fw.runouts_at_alpha(ALPHA[:1])
    assert sides == [[0.2], [2.0]] and widths == [4, 4], (sides, widths)
    assert r.shape == (1, 3, 2) and np.all(np.isfinite(r)), r


def test_lane_calls_cover_every_lane_once_in_calls_of_one_side():
    """``lane_calls``: every lane in exactly one call (padding repeats a lane of
    its own call), one side per call, alpha ascending within it, one width."""
    rng = np.random.default_rng(0)
    side = rng.choice([0.2, 0.5, 2.0], size=70)
    alpha = rng.uniform(0.1, 0.9, size=70)
    calls = lane_calls(side, alpha, 16)
    largest = max(np.sum(side == L) for L in (0.2, 0.5, 2.0))
    k = -(-largest // 16)
    assert {len(c) for c in calls} == {-(-largest // k)}  # the fewest calls, evenly filled
    for c in calls:
        assert len(set(side[c])) == 1
        real = list(dict.fromkeys(c.tolist()))  # first occurrences, in order
        assert np.all(np.diff(alpha[real]) >= 0)
        assert all(i == real[-1] for i in c[len(real):])
    firsts = np.concatenate([list(dict.fromkeys(c.tolist())) for c in calls])
    assert sorted(firsts.tolist()) == list(range(70))
    few = lane_calls(np.repeat([0.2, 2.0], [3, 5]), 0.5, 32)
    assert [c.tolist() for c in few] == [[0, 1, 2, 2, 2], [3, 4, 5, 6, 7]]
    assert lane_calls(np.array([]), np.array([]), 32) == []
    even = lane_calls(np.repeat([0.2, 2.0], [33, 10]), 0.5, 32)  # 2 + 1 calls of 17
    assert [len(c) for c in even] == [17, 17, 17], [len(c) for c in even]


def test_runouts_come_back_in_entry_order():
    """One lane per call (no lane shares a call, so the order cannot change a
    result): every entry's runouts equal those of a forward that runs that entry
    alone, with the same blocks (common random numbers)."""
    key = jax.random.key(0)
    r = DemForward(PROFILE, ENTRIES, 2, key, form="constant",
                   lane_batch=1).runouts_at_alpha(ALPHA)
    for s in range(ENTRIES.n):
        alone = DemForward(PROFILE, ENTRIES.take(np.array([s])), 2, key, form="constant",
                           lane_batch=1).runouts_at_alpha(ALPHA[:, s:s + 1])
        np.testing.assert_array_equal(r[:, s], alone[:, 0])
    assert len({float(v) for v in r.ravel()}) > 6  # the entries' runouts differ


def test_a_block_runs_alike_wherever_it_sits_in_a_call():
    """32 blocks (0.6, 1 and 2 m, alpha 0.3-0.8, their own keys) released at the
    crest, run in one call and again in the reverse order: every block stops
    at the same point to the bit. XLA's CPU backend vectorises the lanes and
    leaves the last ones to a scalar loop; a reduction of the four corner
    forces compiled as ``jnp.sum`` rounded differently in the two, and the
    blocks in lanes 0-3 and 28-31 stopped elsewhere when reversed."""
    rng = np.random.default_rng(1)
    sides, alphas = rng.choice([0.6, 1.0, 2.0], 32), rng.uniform(0.3, 0.8, 32)
    params = DEM_RUN.params(PROFILE, rho=2600.0)
    options = DEM_RUN.options(params, sides)
    blocks = [make_block(float(L), alpha=float(a), release_x_m=0.0, release_speed_m_s=1.0,
                         release_height_m=0.0) for L, a in zip(sides, alphas, strict=True)]
    keys = [jax.random.fold_in(jax.random.key(3), j) for j in range(32)]
    fwd = dem_lanes(params, stack_trees(blocks), jax.numpy.stack(keys), options)
    rev = dem_lanes(params, stack_trees(blocks[::-1]), jax.numpy.stack(keys[::-1]), options)
    x_fwd, x_rev = np.asarray(fwd.runout_m)[:, 0], np.asarray(rev.runout_m)[::-1, 0]
    assert np.all(np.isfinite(x_fwd)) and len(set(x_fwd.tolist())) > 16, x_fwd
    np.testing.assert_array_equal(x_fwd, x_rev)


def test_fragment_candidate_runs_one_size_per_call(monkeypatch):
    """``calib.discover``'s DEM fragmentation candidate (2 x 2 bonded fragments)
    runs each block side in calls of its own, all of one width, and its
    runouts (the furthest fragment of each block) are those of one call of
    every lane."""
    from calib.discovery import dem_candidates as dc
    from calib.model.unfinished import mask_unfinished

    entries = Entries.at_sizes([1.0, 2.0, 1.0], 150.0)
    fw = dc.DemEffectForward(PROFILE, entries, 2, jax.random.key(0), effect="fragmentation")
    calls, real = [], dc.dem_lanes

    def spy(params, blocks, keys, options):
        calls.append(np.asarray(blocks.size_m).tolist())
        return real(params, blocks, keys, options)

    monkeypatch.setattr(dc, "dem_lanes", spy)
    r = fw.runouts(np.array([[0.5, 4.0]]))  # alpha 0.5, joints of 10^4 Pa
    assert calls == [[1.0] * 4, [2.0] * 4], calls
    assert r.shape == (1, 3, 2) and np.all(np.isfinite(r)), r

    # the same lanes in one call, in entry order
    strength = 1e4
    params = DEM_RUN.params(PROFILE, c_joint_pa=strength, t_joint_pa=strength,
                            rho=entries.density_kg_m3)
    sides = entries.dem_side_m
    options = DEM_RUN.options(params, sides, n_fragments=dc.N_FRAGMENTS, adaptive=False)
    lanes = [b for b in entry_blocks(entries, 0.5, n_fragments=dc.N_FRAGMENTS)
             for _ in range(2)]
    keys = jax.numpy.stack([jax.random.fold_in(jax.random.key(0), j) for j in [0, 1] * 3])
    res = real(params, stack_trees(lanes), keys, options)
    one_call = mask_unfinished(np.max(np.asarray(res.runout_m), axis=-1), res.status)
    np.testing.assert_array_equal(r[0].ravel(), one_call)
