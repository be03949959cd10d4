"""The optional CRSP effects (solvers/crsp/_effects.py): off by default, and each
changes the runouts the way its physics says, inside the solver."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import solvers.crsp as crsp
from solvers.crsp._effects import breaks, in_belt, size_scaled
from solvers.profile import load_profile

PROFILE = load_profile("data/postignano_profile.csv")
BASE = dict(Kn=0.40, Kt=0.96, roughness_m=0.4)
# 128 blocks, no stations, the default pool: the compiled program of the other
# 256-slot runs on this profile (tests/test_crsp.py, tests/test_crsp_invariants.py)
N = 128


def _runouts(diameter_m, **kw):
    p = crsp.params_from_profile(PROFILE, **{**BASE, **kw})
    r = crsp.simulate_pooled(p, crsp.make_block(diameter_m / 2), jax.random.key(3), PROFILE,
                             jnp.zeros((0,)), n_blocks=N)
    assert np.all(np.asarray(r.status) != crsp.BUDGET)
    return np.asarray(r.runout_m)


def test_effects_are_off_by_default_and_neutral_values_change_nothing():
    plain = _runouts(1.0)
    neutral = _runouts(1.0, restitution_size_exponent=0.0, frag_energy_kJ=np.inf,
                       rolling_resistance=0.0, belt_start_m=120.0, belt_end_m=180.0,
                       belt_loss=0.0)
    np.testing.assert_array_equal(plain, neutral)
    # a size exponent changes nothing for a block of the reference diameter (1 m)
    np.testing.assert_array_equal(plain, _runouts(1.0, restitution_size_exponent=0.3))


def test_size_dependent_restitution_spreads_the_size_trend():
    g = 0.3
    small0, small1 = _runouts(0.2), _runouts(0.2, restitution_size_exponent=g)
    big0, big1 = _runouts(2.0), _runouts(2.0, restitution_size_exponent=g)
    assert np.median(small1) <= np.median(small0)
    assert np.median(big1) > np.median(big0) + 20.0
    assert float(size_scaled(0.9, 1.0, 0.5)) == pytest.approx(min(0.9 * 2**0.5, 0.99))


def test_fragmentation_shortens_large_blocks_only():
    small0, small1 = _runouts(0.2), _runouts(0.2, frag_energy_kJ=300.0)
    big0, big1 = _runouts(2.0), _runouts(2.0, frag_energy_kJ=300.0)
    np.testing.assert_array_equal(small0, small1)  # 0.2 m blocks never carry 300 kJ
    assert np.median(big1) < np.median(big0) - 30.0
    # the break criterion: (1/2) m v_n^2 in kJ, once
    assert bool(breaks(1000.0, 30.0, 400.0, False))  # 450 kJ > 400
    assert not bool(breaks(1000.0, 30.0, 500.0, False))
    assert not bool(breaks(1000.0, 30.0, 400.0, True))


def test_rolling_resistance_lets_small_blocks_stop_on_the_talus():
    r = _runouts(0.2, rolling_resistance=0.4)  # tan(30) + 0.4 > tan(40): rest possible
    assert np.mean(r < 100.0) > 0.2
    assert np.mean(_runouts(0.2) < 100.0) == 0.0


def test_vegetation_belt_stops_blocks_in_or_before_it():
    big0 = _runouts(2.0)
    big1 = _runouts(2.0, belt_start_m=130.0, belt_end_m=175.0, belt_loss=0.4)
    assert np.mean(big0 > 175.0) > 0.5
    assert np.mean(big1 > 175.0) < 0.5 * np.mean(big0 > 175.0)
    assert bool(in_belt(150.0, 130.0, 175.0)) and not bool(in_belt(176.0, 130.0, 175.0))


def test_effect_parameters_vary_per_task_in_one_compiled_pool():
    """Effects are ordinary traced parameters: tasks with different values share one
    program and each matches its own single run."""
    base = crsp.params_from_profile(PROFILE, **BASE)
    values = jnp.array([0.0, 0.4])
    p = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (2,) + a.shape), base)
    p = p._replace(rolling_resistance=values)
    blocks = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), crsp.make_block(0.1))
    res = crsp.simulate_tasks(p, blocks, jax.random.key(3), PROFILE, jnp.zeros((0,)),
                              n_per_task=N)
    np.testing.assert_allclose(np.asarray(res.runout_m[0]), _runouts(0.2), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(res.runout_m[1]),
                               _runouts(0.2, rolling_resistance=0.4), rtol=1e-9)
