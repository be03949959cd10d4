"""``scripts/terrain_variation_study.py`` (docs/studies.md, "The ground within
the raster's error"): the split into grounds changes nothing when the field is
zero, each part is its own ground with the block indices it has unsplit, and the
field has the gentle and steep standard deviations where the slope says."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from cli_run import load_script

import solvers.crsp as crsp
from solvers.profile import make_profile
from solvers.status import INVALID

FIELD = dict(spacing_m=5.0, sd_gentle_m=0.15, sd_steep_m=0.6, slope_break_deg=10.0, seed=4)


def _slope():
    """40 m at 35 deg, then 40 m at 5 deg, vertices 1 m apart (knots on vertices)."""
    x = np.arange(0.0, 81.0)
    z = np.where(x <= 40, -np.tan(np.radians(35)) * x,
                 -np.tan(np.radians(35)) * 40 - np.tan(np.radians(5)) * (x - 40))
    mats = {"m": dict(Kn=0.4, Kt=0.9, roughness_m=0.1, rolling_friction_deg=20.0,
                      phi_deg=30.0)}
    return make_profile(x, z, ["m"] * 80, mats, source="test")


def _tasks(prof, n_tasks=2):
    p = crsp.params_from_profile(prof, Kn=0.4, Kt=0.9, roughness_m=0.1,
                                 rolling_friction_deg=20.0)
    p = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(jnp.asarray(a), (n_tasks,)
                                                          + jnp.shape(a)), p)
    p = p._replace(release_x_m=jnp.asarray([2.0, 10.0]), release_vx_m_s=jnp.asarray([1.0, 2.0]))
    b = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(jnp.asarray(a), (n_tasks,)
                                                          + jnp.shape(a)), crsp.make_block(0.2))
    return p, b


def _leaves(r):
    return [np.asarray(v) for v in jax.tree_util.tree_leaves(r)]


def test_grounds_split_the_blocks_and_a_zero_field_changes_nothing():
    tv = load_script("terrain_variation_study")
    prof = _slope()
    p, b = _tasks(prof)
    key, st = jax.random.PRNGKey(3), jnp.asarray([30.0, 60.0])
    base = crsp.simulate_tasks(p, b, key, prof, st, n_per_task=16)
    zero = tv.vary_terrain(crsp.simulate_tasks, 2, **{**FIELD, "sd_gentle_m": 0.0,
                                                       "sd_steep_m": 0.0})
    for a, c in zip(_leaves(base), _leaves(zero(p, b, key, prof, st, n_per_task=16))):
        np.testing.assert_array_equal(a, c)
    varied = tv.vary_terrain(crsp.simulate_tasks, 2, **FIELD)(p, b, key, prof, st,
                                                               n_per_task=16)
    # part 1 is blocks 8-15 of the unsplit run, on its own ground
    ground1 = tv.perturbed_profile(prof, 1, **FIELD)
    part1 = crsp.simulate_tasks(p, b, key, ground1, st, n_per_task=8, offset=8)
    for a, c in zip(_leaves(varied), _leaves(part1)):
        np.testing.assert_array_equal(a[:, 8:], c)
    assert not np.array_equal(np.asarray(varied.runout_m), np.asarray(base.runout_m))
    assert not np.any(np.asarray(varied.status) == INVALID)  # never below its own ground


def test_the_field_is_steep_or_gentle_by_the_slope_and_keyed_by_its_part():
    tv = load_script("terrain_variation_study")
    prof = _slope()
    x, z = np.asarray(prof.x_m), np.asarray(prof.z_m)
    knots = np.arange(0.0, 81.0, 5.0)
    e = np.stack([tv.knot_field(x, z, g, **FIELD) for g in range(400)])
    at = np.searchsorted(x, knots)
    sd = e[:, at].std(axis=0)
    # knots 0-35 lie on 35 deg ground; 45-80 on 5 deg ground; 40 straddles the break
    np.testing.assert_allclose(sd[knots <= 35], 0.6, rtol=0.15)
    np.testing.assert_allclose(sd[knots >= 45], 0.15, rtol=0.15)
    # linear between knots; the same part gives the same field, another part another
    np.testing.assert_allclose(e[:, 2], 0.6 * e[:, 0] + 0.4 * e[:, 5], atol=1e-12)
    np.testing.assert_array_equal(tv.knot_field(x, z, 7, **FIELD), e[7])
    assert not np.allclose(e[7], e[8])
