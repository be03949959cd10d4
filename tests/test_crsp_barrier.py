"""CRSP protection barrier (``solvers.crsp._barrier``): its invariants on the
Postignano and Tschamut profiles, and closed-form crossings on straight ground.

Every run of a site uses the same profile, block count and number of stations,
so one compiled program serves all of them; the barrier's parameters are traced.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from calib.hazard._stats import reduce_chunk
from calib.model.unfinished import mask_unfinished
from solvers import crsp, ground_z, load_profile, make_profile
from solvers.crsp._contact import speed2_after
from solvers.profile import refine
from solvers.status import (
    INVALID,
    STATUS_NAMES,
    STOPPED,
    STOPPED_BY_BARRIER,
    finished,
    status_counts,
)

G = 9.81
N = 300
INF = math.inf

# a barrier where most blocks arrive, some flying over it, some rolling into it
# (Tschamut: a quarter of the blocks roll at 70 m), with a capacity inside the
# range of the energies brought there, so that every rule of the barrier acts
SITES = {
    "postignano": dict(path="data/postignano_profile.csv", radius_m=0.5, barrier_x_m=100.0,
                       height_m=2.0, capacity_kJ=200.0, downslope_m=(120.0, 140.0),
                       params=dict(Kn=0.41, Kt=0.87, roughness_m=0.5)),
    "tschamut": dict(path="data/tschamut2014/profile.csv", radius_m=0.19, barrier_x_m=70.0,
                     height_m=1.0, capacity_kJ=2.0, downslope_m=(90.0, 100.0),
                     params=dict(release_x_m=41.0, release_height_m=1.3, release_vx_m_s=1.5,
                                 roughness_m=0.3)),
}
# the Tschamut cases compile programs of their own (about 24 s): -m slow
CASES = ["postignano", pytest.param("tschamut", marks=pytest.mark.slow)]


def _stations(site):
    """The barrier's abscissa, just past it, and two stations downslope."""
    xb = site["barrier_x_m"]
    return np.array([xb, xb + 1e-6, *site["downslope_m"]])


def _params(prof, name: str, **barrier):
    """The site's parameters with a barrier (``barrier_x_m``, ``height_m``,
    ``capacity_kJ``), or none."""
    names = dict(barrier_x_m="barrier_x_m", height_m="barrier_height_m",
                 capacity_kJ="barrier_capacity_kJ")
    return crsp.params_from_profile(prof, **{names[k]: v for k, v in barrier.items()},
                                    **SITES[name]["params"])


@functools.cache
def _run(name: str, refine_m=None, **barrier):
    """N blocks of the site (key 0) with a barrier (none by default)."""
    site = SITES[name]
    prof = load_profile(site["path"])
    if refine_m is not None:
        prof = refine(prof, refine_m)
    return crsp.run_blocks(_params(prof, name, **barrier), crsp.make_block(site["radius_m"]),
                           jax.random.key(0), N, prof, stations_x_m=_stations(site))


def _barrier(name: str, **kw):
    site = SITES[name]
    args = dict(barrier_x_m=site["barrier_x_m"], height_m=site["height_m"],
                capacity_kJ=site["capacity_kJ"])
    args.update(kw)
    return _run(name, **args)


def _identical(a, b, rows=slice(None)):
    np.testing.assert_array_equal(a.runout_m[rows], b.runout_m[rows])
    np.testing.assert_array_equal(a.status[rows], b.status[rows])
    np.testing.assert_array_equal(a.n_events[rows], b.n_events[rows])
    np.testing.assert_array_equal(a.stations.passed[rows], b.stations.passed[rows])
    np.testing.assert_array_equal(a.stations.energy_kJ[rows], b.stations.energy_kJ[rows])


@pytest.mark.parametrize("name", CASES)
def test_a_barrier_that_catches_nothing_changes_nothing(name):
    """Height 0, a barrier at +inf, beyond the profile's end or behind the
    release: every runout, status, event count and station record is
    bit-identical to the run without a barrier (the barrier acts only through
    blocks that hit its net)."""
    site = SITES[name]
    base = _run(name)
    assert base.barrier is None  # no barrier: no record
    absent = _run(name, barrier_x_m=INF)
    _identical(base, absent)
    assert not absent.barrier.reached.any() and np.isnan(absent.barrier.energy_kJ).all()
    zero = _barrier(name, height_m=0.0)
    _identical(base, zero)
    assert zero.barrier.reached.mean() > 0.9  # it was crossed, and recorded
    x_end = float(load_profile(site["path"]).x_m[-1])
    _identical(base, _run(name, barrier_x_m=x_end + 10.0))
    behind = float(np.min(base.release_x_m)) - 1.0
    behind_run = _run(name, barrier_x_m=behind)
    _identical(base, behind_run)
    assert not behind_run.barrier.reached.any()


@pytest.mark.parametrize("name", CASES)
def test_an_unlimited_barrier_stops_every_block_that_reaches_it(name):
    """Unlimited height and capacity: a block reaches the barrier exactly when,
    without it, it passes a station there; each one stops at the barrier
    (STOPPED_BY_BARRIER, a finished block with runout barrier - release) and
    none passes a station beyond it. Its record is the station's passage."""
    xb = SITES[name]["barrier_x_m"]
    base = _run(name)
    res = _run(name, barrier_x_m=xb)
    rec = res.barrier
    np.testing.assert_array_equal(rec.reached, base.stations.passed[:, 0])
    assert rec.reached.mean() > 0.9
    assert np.all(res.status[rec.reached] == STOPPED_BY_BARRIER)
    assert np.all(res.stopped[rec.reached]) and np.all(finished(res.status))
    np.testing.assert_array_equal(res.stop_x_m[rec.reached], xb)
    np.testing.assert_allclose(res.runout_m[rec.reached],
                               xb - res.release_x_m[rec.reached], rtol=1e-12)
    assert not res.stations.passed[:, 1:].any()
    _identical(base, res, ~rec.reached)
    # the record follows the station conventions (solvers.stations)
    m = rec.reached
    np.testing.assert_allclose(rec.energy_kJ[m], base.stations.energy_kJ[m, 0], rtol=1e-9)
    np.testing.assert_allclose(rec.speed_m_s[m], base.stations.velocity_m_s[m, 0], rtol=1e-9)
    np.testing.assert_allclose(rec.height_m[m], base.stations.bounce_height_m[m, 0],
                               rtol=1e-9, atol=1e-9)
    assert np.all(np.abs(rec.angle_deg[m]) <= 90.0) and np.all(rec.energy_after_kJ[m] == 0.0)


@pytest.mark.parametrize("name", CASES)
def test_a_barrier_never_lets_more_blocks_past_the_stations_beyond_it(name):
    """Common random numbers (same key): blocks that do not reach the barrier
    or fly over it are untouched, bit for bit; stopped blocks pass nothing
    beyond it; so the fraction passing each station downslope does not grow
    (blocks that break through may take other paths: the paired difference is
    bounded by two of its standard errors)."""
    site = SITES[name]
    base = _run(name)
    res = _barrier(name)
    rec = res.barrier
    over = rec.reached & (rec.height_m >= site["height_m"])
    stopped = res.status == STOPPED_BY_BARRIER
    through = rec.reached & ~over & ~stopped
    assert over.any() and stopped.any() and through.any(), (over.sum(), stopped.sum(),
                                                            through.sum())
    _identical(base, res, ~rec.reached | over)
    assert not res.stations.passed[stopped][:, 1:].any()
    for j in (2, 3):
        d = res.stations.passed[:, j].astype(float) - base.stations.passed[:, j]
        se = d.std(ddof=1) / math.sqrt(N) if d.any() else 0.0
        assert d.mean() <= 2.0 * se, (site["downslope_m"][j - 2], d.mean(), se)


@pytest.mark.parametrize("name", CASES)
def test_the_energy_kept_is_never_more_than_the_energy_brought(name):
    """At the crossing: E_after = E over the barrier, 0 stopped, E - E_cap
    through it, never more than E; and just past the barrier (a station 1 um
    beyond it, on the block's own next event) the block carries E_after."""
    site = SITES[name]
    res = _barrier(name)
    rec = res.barrier
    m = rec.reached
    e, after = rec.energy_kJ[m], rec.energy_after_kJ[m]
    assert np.all(after <= e)
    in_net = rec.height_m[m] < site["height_m"]
    caught = in_net & (e <= site["capacity_kJ"])
    through = in_net & ~caught
    assert through.any() and caught.any()
    np.testing.assert_allclose(after[through], e[through] - site["capacity_kJ"], rtol=1e-12)
    assert np.all(after[caught] == 0.0) and np.all(after[~in_net] == e[~in_net])
    np.testing.assert_array_equal(res.status[m] == STOPPED_BY_BARRIER, caught)
    # a station at the barrier sees what the block brought, one just past it what it
    # kept plus the work of gravity over 1 um, m g 1e-6 |tan(angle)| at most
    np.testing.assert_allclose(res.stations.energy_kJ[m, 0], e, rtol=1e-9)
    past = res.stations.passed[m, 1]
    assert np.all(past[through | ~in_net]) and not np.any(past[caught])
    mass_kg = float(crsp.make_block(site["radius_m"]).mass_kg)
    work = mass_kg * G * 1e-6 * np.abs(np.tan(np.radians(rec.angle_deg[m]))) / 1000.0
    gap = np.abs(res.stations.energy_kJ[m, 1] - after)
    assert np.all((gap <= 1.01 * work + 1e-9 * after)[past]), np.max((gap - work)[past])


@pytest.mark.parametrize("name", CASES)
def test_no_block_below_the_ground_and_collinear_vertices_change_nothing(name):
    """With a barrier, no block ends below the ground or INVALID, and inserting
    collinear vertices (every 2 m on Postignano, one of them at the barrier;
    every 0.7 m on Tschamut) leaves the blocks' runouts, statuses and barrier
    records the same, up to round-off at rare borderline decisions."""
    res = _barrier(name)
    prof = load_profile(SITES[name]["path"])
    gz = np.asarray(ground_z(prof, jnp.asarray(res.stop_x_m)))
    assert np.all(res.stop_z_m >= gz - 1e-3) and not np.any(res.status == INVALID)
    fine = _barrier(name, refine_m=2.0 if name == "postignano" else 0.7)
    same = np.abs(res.runout_m - fine.runout_m) < 1e-6
    assert same.mean() >= 0.99, same.mean()
    assert np.mean(res.status == fine.status) >= 0.99
    np.testing.assert_array_equal(res.barrier.reached, fine.barrier.reached)
    # round-off grows along a rolling path of many segments (as for the runouts)
    np.testing.assert_allclose(res.barrier.energy_kJ, fine.barrier.energy_kJ, rtol=1e-6,
                               equal_nan=True)


@pytest.mark.parametrize("name", CASES)
def test_as_the_capacity_goes_to_zero_the_barrier_vanishes(name):
    """E_cap -> 0: blocks in the net break through keeping almost all their
    energy (they lose E_cap = 1e-9 kJ of at least 0.08 kJ), and the runs
    approach the run without a barrier: a block's runout moves by less than a
    millimetre, rare borderline decisions aside."""
    base = _run(name)
    res = _barrier(name, capacity_kJ=1e-9)
    rec = res.barrier
    m = rec.reached
    assert not np.any(res.status == STOPPED_BY_BARRIER)
    lost = rec.energy_kJ[m] - rec.energy_after_kJ[m]
    assert np.all(lost <= 1e-9 + 1e-14 * rec.energy_kJ[m])  # E_cap, up to round-off
    close = np.abs(res.runout_m - base.runout_m) < 1e-3
    assert close.mean() >= 0.99, close.mean()
    np.testing.assert_allclose(np.mean(res.stations.passed[:, 2:], axis=0),
                               np.mean(base.stations.passed[:, 2:], axis=0), atol=0.01)
    # and a finite capacity does move them
    assert np.mean(np.abs(_barrier(name).runout_m - base.runout_m) < 1e-3) < 0.99


# one compiled program for every single-block run on a straight two-vertex profile
_simulate = jax.jit(crsp.simulate, static_argnames=("settings",))


def _flat(length_m=1000.0, **mat):
    base = dict(Kn=0.41, Kt=0.87, roughness_m=0.0, rolling_friction_deg=30.0, phi_deg=30.0)
    base.update(mat)
    return make_profile([0.0, length_m], [0.0, 0.0], ["z"], {"z": base})


def test_a_flight_meets_the_barrier_on_its_parabola_and_breaks_through():
    """Released 20 m above flat ground at (3, 4) m/s: at x_b = 4 m the parabola
    gives the height, speed and angle; with E_cap = 3/4 E the block breaks
    through at half its speed and spin and flies on from there (checked at a
    station before it lands)."""
    prof = _flat()
    h0, vx, vz, xb = 20.0, 3.0, 4.0, 4.0
    block = crsp.make_block(0.5)
    tb = xb / vx
    zb, vzb = h0 + vz * tb - 0.5 * G * tb**2, vz - G * tb
    e = 0.5 * float(block.mass_kg) * (vx**2 + vzb**2) / 1000.0
    params = crsp.params_from_profile(prof, release_x_m=0.0, release_height_m=h0,
                                      release_vx_m_s=vx, release_vz_m_s=vz, barrier_x_m=xb,
                                      barrier_height_m=30.0, barrier_capacity_kJ=0.75 * e)
    xs = 5.0
    res = _simulate(params, block, jax.random.key(0), profile=prof,
                    stations_x_m=jnp.array([xs]))
    rec = res.barrier
    assert bool(rec.reached)
    np.testing.assert_allclose(float(rec.height_m), zb, rtol=1e-12)
    np.testing.assert_allclose(float(rec.speed_m_s), math.hypot(vx, vzb), rtol=1e-12)
    np.testing.assert_allclose(float(rec.angle_deg), math.degrees(math.atan2(-vzb, vx)),
                               rtol=1e-12)
    np.testing.assert_allclose(float(rec.energy_kJ), e, rtol=1e-12)
    np.testing.assert_allclose(float(rec.energy_after_kJ), 0.25 * e, rtol=1e-12)
    ts = (xs - xb) / (0.5 * vx)
    np.testing.assert_allclose(float(res.stations.bounce_height_m[0]),
                               zb + 0.5 * vzb * ts - 0.5 * G * ts**2, rtol=1e-12)
    np.testing.assert_allclose(float(res.stations.velocity_m_s[0]),
                               math.hypot(0.5 * vx, 0.5 * vzb - G * ts), rtol=1e-12)
    # flying higher than the barrier: untouched
    over = _simulate(params._replace(barrier_height_m=jnp.float64(zb - 1e-6)), block,
                         jax.random.key(0), profile=prof, stations_x_m=jnp.array([xs]))
    free = _simulate(params._replace(barrier_x_m=jnp.float64(INF)), block,
                         jax.random.key(0), profile=prof, stations_x_m=jnp.array([xs]))
    assert float(over.runout_m) == float(free.runout_m)
    assert float(over.barrier.energy_after_kJ) == float(over.barrier.energy_kJ)


def test_a_rolling_block_meets_the_barrier_at_its_rolling_speed():
    """A block rolling down a smooth 20 deg slope (rolling friction 10 deg):
    at the barrier its clearance is 0, its speed the closed form
    ``u^2 = u0^2 + 2 A d`` and its energy 1/2 m (1 + k) u^2; a capacity above
    that stops it, one below lets it roll on with E - E_cap."""
    beta = -math.radians(20.0)
    prof = make_profile([0.0, 200.0], [0.0, 200.0 * math.tan(beta)], ["z"],
                        {"z": dict(Kn=0.41, Kt=0.87, roughness_m=0.0,
                                   rolling_friction_deg=10.0, phi_deg=30.0)})
    block = crsp.make_block(0.5)
    u0, xb, k = 2.0, 50.0, 0.4
    a = G * (-math.sin(beta) - math.tan(math.radians(10.0)) * math.cos(beta)) / (1 + k)
    u2 = float(speed2_after(u0**2, a, 0.0, xb / math.cos(beta)))
    e = 0.5 * float(block.mass_kg) * (1 + k) * u2 / 1000.0
    params = crsp.params_from_profile(prof, release_x_m=0.0, release_vx_m_s=u0 * math.cos(beta),
                                      release_vz_m_s=u0 * math.sin(beta), barrier_x_m=xb,
                                      barrier_height_m=1.0, barrier_capacity_kJ=2.0 * e)
    caught = _simulate(params, block, jax.random.key(0), profile=prof,
                       stations_x_m=jnp.array([xb + 10.0]))
    assert int(caught.status) == STOPPED_BY_BARRIER and float(caught.stop_x_m) == xb
    rec = caught.barrier
    assert float(rec.height_m) == 0.0
    np.testing.assert_allclose(float(rec.energy_kJ), e, rtol=1e-12)
    np.testing.assert_allclose(float(rec.speed_m_s), math.sqrt(u2), rtol=1e-12)
    np.testing.assert_allclose(float(rec.angle_deg), -math.degrees(beta), rtol=1e-12)
    np.testing.assert_allclose(float(caught.stop_z_m), xb * math.tan(beta), rtol=1e-12)
    # through: rolls on with E - E_cap, checked 10 m further
    xs = xb + 10.0
    through = _simulate(params._replace(barrier_capacity_kJ=jnp.float64(0.5 * e)), block,
                            jax.random.key(0), profile=prof, stations_x_m=jnp.array([xs]))
    np.testing.assert_allclose(float(through.barrier.energy_after_kJ), 0.5 * e, rtol=1e-12)
    u2s = float(speed2_after(0.5 * u2, a, 0.0, 10.0 / math.cos(beta)))
    np.testing.assert_allclose(float(through.stations.velocity_m_s[0]), math.sqrt(u2s),
                               rtol=1e-10)


@pytest.mark.slow  # 12 s
def test_barriers_vary_per_task_in_one_compiled_pool():
    """The barrier's parameters are per task like the others: tasks with
    different barriers in one ``simulate_tasks`` call (common random numbers)
    each give what their own run gives."""
    name = "postignano"
    site = SITES[name]
    prof = load_profile(site["path"])
    cases = [dict(barrier_x_m=INF), dict(barrier_x_m=100.0, height_m=2.0, capacity_kJ=200.0),
             dict(barrier_x_m=80.0)]
    sets = [_params(prof, name, **c) for c in cases]
    stack = lambda xs: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    blocks = stack([crsp.make_block(site["radius_m"])] * len(cases))
    both = crsp.simulate_tasks(stack(sets), blocks, jax.random.key(0), prof,
                               jnp.asarray(_stations(site)), n_per_task=N)
    assert np.all(np.asarray(both.status[2]) == STOPPED_BY_BARRIER)
    for t, c in enumerate(cases):
        one = _run(name, **c)
        np.testing.assert_allclose(both.runout_m[t], one.runout_m, rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(both.status[t], one.status)
        np.testing.assert_allclose(both.barrier.energy_kJ[t], one.barrier.energy_kJ,
                                   rtol=1e-9, equal_nan=True)


def test_every_status_consumer_counts_a_block_stopped_by_the_barrier_as_finished():
    """The status has a name, counts, is finished (its runout is a result), and
    the calibration's mask and the hazard tables' reduction keep it."""
    status = np.array([STOPPED, STOPPED_BY_BARRIER, INVALID])
    assert STATUS_NAMES[STOPPED_BY_BARRIER] == "stopped_by_barrier"
    assert status_counts(status)["stopped_by_barrier"] == 1
    np.testing.assert_array_equal(finished(status), [True, True, False])
    np.testing.assert_array_equal(mask_unfinished([1.0, 2.0, 3.0], status), [1.0, 2.0, np.nan])
    stats = reduce_chunk(jnp.array([[5.0, 5.0, 5.0]]), jnp.asarray(status)[None],
                         jnp.ones((1, 3, 1), bool), jnp.ones((1, 3, 1)), jnp.ones((1, 3, 1)),
                         jnp.ones((1, 3, 1)), jnp.ones(3, bool), jnp.array([4.0]))
    assert int(stats.n_unfinished[0]) == 1 and int(stats.exceed[0, 0]) == 2


@pytest.mark.parametrize("field,value", [("barrier_height_m", -1.0),
                                         ("barrier_capacity_kJ", float("nan")),
                                         ("barrier_x_m", float("nan"))])
def test_a_negative_or_nan_barrier_parameter_is_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        crsp.params_from_profile(_flat(), **{"barrier_x_m": 10.0, field: value})
    with pytest.raises(ValueError, match="without barrier_x_m"):
        crsp.params_from_profile(_flat(), barrier_height_m=3.0)


# slow: a count of compiled programs, 14 s
@pytest.mark.slow
def test_a_run_without_a_barrier_compiles_none_of_its_code():
    """No barrier (the default): the parameters carry None and the event step's
    compiled program has none of the barrier's work, which a barrier at +inf
    (same results) adds: fewer operations in XLA's cost analysis."""
    from solvers._rng import key_words
    from solvers.crsp._model import init, segment_table, step

    prof = load_profile(SITES["postignano"]["path"])
    block = crsp.make_block(0.5)
    keys = jax.random.split(jax.random.key(0), 8)

    def flops(params):
        def lanes(p, b, ks):
            table = segment_table(prof, p, b)
            s = jax.vmap(lambda k: init(p, b, k, prof))(ks)
            return jax.vmap(lambda s, w: step(s, p, b, w, prof, table, crsp.Settings()))(
                s, jax.vmap(key_words)(ks))
        cost = jax.jit(lanes).lower(params, block, keys).compile().cost_analysis()
        return (cost[0] if isinstance(cost, list) else cost)["flops"]

    none = crsp.params_from_profile(prof)
    assert none.barrier_x_m is None and none.barrier_height_m is None
    assert flops(none) < flops(crsp.params_from_profile(prof, barrier_x_m=INF))
