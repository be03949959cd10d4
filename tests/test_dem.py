"""Tests of the rigid-block DEM: analytic cases, invariants, batching, CLI."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cli_run import run_cli

import solvers  # noqa: F401  (x64)
from solvers.dem import (
    AlphaLawError,
    Options,
    Pose,
    check_run_numerics,
    make_block,
    make_params,
    parse_alpha_law,
    simulate,
    stable_dt,
    trajectory,
)
from solvers.dem._integrate import simulate_batch
from solvers.profile import ground_z, load_profile, make_profile
from solvers.status import BUDGET

G = 9.81
PROFILE_CSV = "data/postignano_profile.csv"
PROFILE_ABS = os.path.abspath(PROFILE_CSV)  # for commands run in another folder


def _mat(phi):
    return {"rock": {"Kn": 0.4, "Kt": 0.8, "roughness_m": 0.0, "rolling_friction_deg": 30.0,
                     "phi_deg": phi}}


def incline(beta_deg, phi_deg=30.0, length=400.0):
    """Straight slope z = -x tan(beta) from x = -length/2 to length/2."""
    x = np.array([-length / 2, length / 2])
    return make_profile(x, -x * math.tan(math.radians(beta_deg)), ["rock"], _mat(phi_deg))


def pose1(x, z, theta=0.0, vx=0.0, vz=0.0, omega=0.0):
    return Pose(jnp.array([[x, z]]), jnp.array([theta]), jnp.array([[vx, vz]]),
                jnp.array([omega]))


def run_traj(params, block, pose, n_saves, every, options=Options()):
    f = jax.jit(lambda p: trajectory(params, block, jax.random.key(0), n_saves, every,
                                     options, p))
    return f(pose)


# ---------------------------------------------------------------- analytic cases

@pytest.mark.parametrize("mode,factor", [("contact", 1.0), ("unbalanced", 0.5)])
def test_free_fall(mode, factor):
    """contact-only damping leaves gravity undamped: z = z0 - g t^2 / 2 exactly
    (leapfrog is exact for constant force); the classic form with alpha 0.5
    falls at (1 - alpha) g while v < 0 (Cundall's local damping)."""
    params = make_params(incline(0.0), damping=mode, dt_s=1e-3)
    block = make_block(1.0, alpha=0.5)
    c, h = run_traj(params, block, pose1(0.0, 100.0), 10, 100)
    t = np.arange(1, 11) * 0.1
    z = np.asarray(h.pos[:, 0, 1])
    expected = 100.0 - 0.5 * factor * G * t ** 2
    if mode == "contact":
        np.testing.assert_allclose(z, expected, rtol=0, atol=1e-9)
    else:  # start-up: v(-dt/2) = +g dt/2 is damped with the opposite sign in the
        # first step, a velocity offset below 2 alpha g dt, i.e. |dz| < 2 alpha g dt t
        assert np.all(np.abs(z - expected) <= 2 * 0.5 * G * 1e-3 * t)
        assert abs(z[-1] - expected[-1]) < 0.01 * 0.5 * factor * G  # (1-alpha) g, not g
    np.testing.assert_allclose(np.asarray(h.pos[:, 0, 0]), 0.0, atol=1e-12)


def _slide(beta, phi, alpha, mode="unbalanced", t_end=1.0):
    prof = incline(beta, phi)
    params = make_params(prof, damping=mode, stiffness_scale=0.01)
    block = make_block(0.5, alpha=alpha)
    b = math.radians(beta)
    # start resting flat on the slope at the static penetration of two corners
    kn_c = params.kn * params.stiffness_scale * 0.25
    m = params.rho * 0.25
    pen = m * G * math.cos(b) / (2 * kn_c)
    d = 0.25 - pen
    pose = pose1(d * math.sin(b), d * math.cos(b), theta=-b)
    dt = float(stable_dt(params, block))
    every = int(round(0.05 / dt))
    n = int(round(t_end / (every * dt)))
    c, h = run_traj(params, block, pose, n, every)
    t = np.arange(1, n + 1) * every * dt
    s = (np.asarray(h.pos[:, 0, 0]) - float(pose.pos[0, 0])) / math.cos(b)
    return t, s


@pytest.mark.xfail(reason="undamped penalty springs: friction excites rocking and hopping "
                   "(contact lost most steps), the mean friction is lower and the block slides "
                   "~18% farther in 1 s than the rigid-contact formula", strict=True)
def test_sliding_acceleration_above_phi_undamped():
    """Undamped block on a 40 deg incline, phi 30: s = g (sin b - cos b tan phi) t^2 / 2."""
    t, s = _slide(40.0, 30.0, alpha=0.0)
    b, phi = math.radians(40), math.radians(30)
    a = G * (math.sin(b) - math.cos(b) * math.tan(phi))
    np.testing.assert_allclose(s[-1], 0.5 * a * t[-1] ** 2, rtol=0.02)


def test_sliding_acceleration_damped_unbalanced():
    """Classic local damping scales a steady slide by (1 - alpha) (both x and z
    components of the net force point along the motion)."""
    t, s = _slide(40.0, 30.0, alpha=0.3)
    b, phi = math.radians(40), math.radians(30)
    a = 0.7 * G * (math.sin(b) - math.cos(b) * math.tan(phi))
    np.testing.assert_allclose(s[-1], 0.5 * a * t[-1] ** 2, rtol=0.03)


def test_rest_below_phi():
    """A block on a 20 deg incline with phi 30 stays put (elastic creep < 1 mm)."""
    t, s = _slide(20.0, 30.0, alpha=0.0, t_end=2.0)
    assert np.max(np.abs(s)) < 1e-3


@pytest.mark.parametrize("alpha", [0.3, 0.43, 0.9])
def test_normal_impact_restitution(alpha):
    """Flat face-down impact without gravity at a fine step (dt_frac 0.005):
    e = sqrt((1 - alpha) / (1 + alpha)) (NOTES.md, one-dof local damping)."""
    params = make_params(incline(0.0), gravity=0.0, dt_frac=0.005, stiffness_scale=0.01)
    block = make_block(0.5, alpha=alpha)
    dt = float(stable_dt(params, block))
    # contact lasts about pi sqrt(m / k); simulate 0.1 m approach + 3 contact times
    k = params.kn * params.stiffness_scale * 0.5
    t_c = math.pi * math.sqrt(params.rho * 0.25 / k)
    n = int((0.02 / 5.0 + 3 * t_c) / dt)
    c, h = run_traj(params, block, pose1(0.0, 0.27, vz=-5.0), n // 10, 10)
    vz_out = float(h.vel[-1, 0, 1])
    e = vz_out / 5.0
    assert float(h.pos[-1, 0, 1]) > 0.25  # separated
    assert e == pytest.approx(math.sqrt((1 - alpha) / (1 + alpha)), rel=0.03)


def _flat_impact(params, alpha=0.0, size_m=0.5, theta=0.0, v=5.0):
    """Face-down (theta 0) or corner-down (theta pi/4) impact on a flat wall
    without gravity; returns the outgoing / incoming normal speed."""
    block = make_block(size_m, alpha=alpha)
    dt = float(stable_dt(params, block))
    k = params.kn * params.stiffness_scale * size_m
    t_c = math.pi * math.sqrt(params.rho * size_m ** 2 / k)
    reach = 0.5 * size_m * (math.cos(theta) + math.sin(theta))
    n = int((0.02 / v + 3 * t_c) / dt)
    c, h = run_traj(params, block, pose1(0.0, reach + 0.02, theta=theta, vz=-v), n // 10, 10)
    assert float(h.pos[-1, 0, 1]) > reach  # separated
    return float(h.vel[-1, 0, 1]) / v


@pytest.mark.parametrize("e", [0.23, 0.5, 0.73])
def test_viscous_normal_impact_restitution(e):
    """Viscous mode, flat face-down impact without gravity at dt_frac 0.02:
    outgoing / incoming speed = the target e (linear spring-dashpot, zeta =
    -ln e / sqrt(pi^2 + ln^2 e), c = 2 zeta sqrt(m_eff k)) within 3 %. At the
    default dt_frac 0.1 the measured e is 0.207 / 0.483 / 0.731 (the dashpot
    sees the half-step velocity): documented, not tested."""
    params = make_params(incline(0.0), damping="viscous", restitution=e, gravity=0.0,
                         dt_frac=0.02, stiffness_scale=0.01)
    assert _flat_impact(params, alpha=0.9) == pytest.approx(e, rel=0.03)  # alpha ignored


def test_viscous_corner_impact_restitution_differs():
    """A corner-down impact has effective mass m, not the m/2 the dashpot is
    set for, so it is under-damped: e ~ 0.61 for target 0.5 (documented in
    solvers/dem/_contact.py). Guards the documentation."""
    params = make_params(incline(0.0), damping="viscous", restitution=0.5, gravity=0.0,
                         dt_frac=0.02, stiffness_scale=0.01)
    assert _flat_impact(params, theta=math.pi / 4) == pytest.approx(0.61, abs=0.02)


def test_viscous_restitution_from_alpha_and_free_fall():
    """Without a restitution the viscous mode takes e = sqrt((1 - alpha) /
    (1 + alpha)) per fragment, and local damping is off: free fall at g."""
    params = make_params(incline(0.0), damping="viscous", gravity=0.0, dt_frac=0.02,
                         stiffness_scale=0.01)
    alpha = 0.43
    assert _flat_impact(params, alpha=alpha) == pytest.approx(
        math.sqrt((1 - alpha) / (1 + alpha)), rel=0.03)
    fall = make_params(incline(0.0), damping="viscous", dt_s=1e-3)
    c, h = run_traj(fall, make_block(1.0, alpha=0.9), pose1(0.0, 100.0), 10, 100)
    t = np.arange(1, 11) * 0.1
    np.testing.assert_allclose(np.asarray(h.pos[:, 0, 1]), 100.0 - 0.5 * G * t ** 2, atol=1e-9)


def test_make_params_damping_validation():
    prof = incline(0.0)
    for bad in (0.0, -0.2, 1.5, float("nan")):
        with pytest.raises(ValueError, match="restitution"):
            make_params(prof, damping="viscous", restitution=bad)
    with pytest.raises(ValueError, match="restitution"):
        make_params(prof, damping="unbalanced", restitution=0.5)
    with pytest.raises(ValueError, match="damping"):
        make_params(prof, damping="rayleigh")
    from solvers.dem import contact_damping_ratio
    assert float(contact_damping_ratio(1.0)) == 0.0
    zeta = float(contact_damping_ratio(0.5))
    assert math.exp(-zeta * math.pi / math.sqrt(1 - zeta ** 2)) == pytest.approx(0.5, rel=1e-12)


def test_second_order_convergence_in_dt():
    """Smooth contact, no damping: error of z(T) through an impact falls ~4x per
    halving of dt (central difference, diffrax test_ode_order style)."""
    prof = incline(0.0, phi_deg=0.0)  # frictionless: forces depend on positions only
    block = make_block(0.2, alpha=0.0)
    t_end = 0.04
    pose = pose1(0.0, 0.115, theta=0.1, vz=-0.5, vx=0.2)

    def z_at(n):
        params = make_params(prof, dt_s=t_end / n, stiffness_scale=1e-3, smooth_width=0.5)
        c, h = run_traj(params, block, pose, 1, n, Options(smooth=True))
        return np.asarray(jnp.concatenate([h.pos[-1, 0], h.theta[-1]]))

    ref = z_at(12800)
    errs = [np.max(np.abs(z_at(n) - ref)) for n in (200, 400, 800)]
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(orders > 1.7), (errs, orders)


def test_station_clearance_at_crossing():
    """A block thrown horizontally in undamped free fall crosses a station at
    t* = (x_s - x0) / vx: recorded clearance = z0 - g t*^2 / 2 - h - ground,
    speed = |v| (half-step velocity, within g dt), to far below one step's fall."""
    prof = incline(0.0)
    params = make_params(prof, damping="contact", dt_s=1e-3)
    block = make_block(1.0, alpha=0.5, stations=(3.0507,))
    pose = pose1(0.0, 50.0, vx=2.0)
    c, h = run_traj(params, block, pose, 20, 100)
    t_star = 3.0507 / 2.0
    rec = h.rec
    assert bool(rec.passed[-1, 0, 0])
    z_star = 50.0 - 0.5 * G * t_star ** 2 - 0.5
    # one step late would be off by |vz| dt = 15 mm here
    assert abs(float(rec.bounce_height_m[-1, 0, 0]) - z_star) < 1e-4
    assert abs(float(rec.velocity_m_s[-1, 0, 0]) - math.hypot(2.0, G * t_star)) < 2 * G * 1e-3


# ---------------------------------------------------------------- invariants

def test_energy_never_created():
    """Mechanical energy (kinetic + potential, in flight) never exceeds its start
    value: block bouncing down a 35 deg slope, alpha 0 (friction only)."""
    params = make_params(incline(35.0, 30.0), stiffness_scale=0.01)
    block = make_block(0.5, alpha=0.0)
    pose = pose1(0.0, 3.0, theta=0.3, vx=2.0)
    c, h = run_traj(params, block, pose, 2000, 4)
    m, inertia = params.rho * 0.25, params.rho * 0.25 * 0.25 / 6
    ke = 0.5 * m * np.sum(np.asarray(h.vel[:, 0]) ** 2, -1) + 0.5 * inertia * np.asarray(
        h.omega[:, 0]) ** 2
    e = ke + m * G * np.asarray(h.pos[:, 0, 1])
    e0 = 0.5 * m * 4.0 + m * G * 3.0
    # flight only: no corner below the ground line
    z_g = -np.tan(np.radians(35)) * np.asarray(h.pos[:, 0, 0])
    clear = (np.asarray(h.pos[:, 0, 1]) - z_g) * np.cos(np.radians(35)) > 0.25 * math.sqrt(2)
    assert clear.sum() > 100 and (~clear).sum() > 5  # it did fly and touch
    # half-step velocity: |dKE| <= m |v| g dt / 2 in flight
    dt = float(c.dt)
    tol = m * np.sqrt(2 * e0 / m + 2 * G * 300) * G * dt
    assert np.all(e[clear] <= e0 + tol)
    assert e[-1] < e0  # friction dissipated something


def _energy_history(params, block, pose, t_end_s):
    """Energy (J/m) after every step of a fixed rollout, and the constants."""
    from solvers.dem import init, mechanical_energy
    n = int(t_end_s / float(stable_dt(params, block)))
    c, h = run_traj(params, block, pose, n, 1)
    _, s0 = init(params, block, jax.random.key(0), Options(), pose)
    seq = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), s0, h)
    cur, nxt = (jax.tree.map(lambda a: a[:-1], seq), jax.tree.map(lambda a: a[1:], seq))
    e = jax.jit(jax.vmap(lambda a, b: mechanical_energy(params, c, a, b, block.n_side)))(cur, nxt)
    return c, h, np.asarray(e.total_J)


def _switch_tolerance(c, h):
    """Energy error of one corner switching contact on within a step: the spring
    energy of one step's penetration at the fastest speed, kn l_c (v dt)^2 / 2
    (the central-difference energy is otherwise exact for linear springs)."""
    v = np.sqrt(np.sum(np.asarray(h.vel) ** 2, -1)) + np.abs(np.asarray(h.omega)) * float(
        c.half) * math.sqrt(2)
    return 0.5 * float(c.kn_c) * (float(v.max()) * float(c.dt)) ** 2


@pytest.mark.parametrize("mode,alpha", [("unbalanced", 0.3), ("unbalanced", 0.9),
                                        ("contact", 0.3), ("viscous", 0.0)])
def test_energy_never_increases_with_damping(mode, alpha):
    """Kinetic + potential + elastic energy of a block bouncing and sliding down
    a 35 deg slope (phi 30) never rises above its running minimum by more than
    one contact switch's error (``_switch_tolerance``), with local damping
    alpha > 0 or contact dashpots (e = 0.5)."""
    kw = {"restitution": 0.5} if mode == "viscous" else {}
    params = make_params(incline(35.0, 30.0), damping=mode, stiffness_scale=0.01, **kw)
    block = make_block(0.5, alpha=alpha)
    c, h, e = _energy_history(params, block, pose1(0.0, 3.0, theta=0.3, vx=2.0), 3.0)
    rise = e - np.minimum.accumulate(e)
    assert rise.max() <= _switch_tolerance(c, h), (rise.max(), _switch_tolerance(c, h))
    assert e[-1] < e[0] - 0.1 * abs(e[0])  # it did lose energy


def _breaking_block(vx):
    params = make_params(incline(35.0), stiffness_scale=0.01, t_joint_pa=0.05e6,
                         c_joint_pa=0.05e6)
    block = make_block(1.0, alpha=0.3, n_fragments=4)
    pos = jnp.array([[-0.25, 2.75], [0.25, 2.75], [-0.25, 3.25], [0.25, 3.25]])
    pose = Pose(pos, jnp.zeros(4), jnp.zeros((4, 2)).at[:, 0].set(vx), jnp.zeros(4))
    return _energy_history(params, block, pose, 1.5)


def test_energy_never_increases_when_bonds_break():
    """A 2 x 2 block (alpha 0.3, c = t = 0.05 MPa) dropped flat on a 35 deg
    slope breaks all its joints; every break removes the joint's stored energy
    and the total never rises above its running minimum beyond one contact
    switch's error."""
    c, h, e = _breaking_block(0.0)
    intact = np.asarray(h.intact).sum(1)
    assert intact[-1] == 0
    breaks = np.nonzero(np.diff(intact) < 0)[0] + 1
    assert all(e[b + 1] < e[b] for b in breaks)
    rise = e - np.minimum.accumulate(e)
    assert rise.max() <= _switch_tolerance(c, h), (rise.max(), _switch_tolerance(c, h))


def test_energy_never_increases_when_bonds_break_thrown():
    """The same block thrown at 2 m/s: after the joints break, two diagonal
    fragments overlap corner to corner, where a contact face chosen by the
    direction of the centres once measured the penetration against the wrong
    face (+354 J/m in one step)."""
    c, h, e = _breaking_block(2.0)
    rise = e - np.minimum.accumulate(e)
    assert rise.max() <= _switch_tolerance(c, h), (rise.max(), _switch_tolerance(c, h))


def test_momentum_conserved_fragment_collision():
    """Two free fragments (joints broken at once, no gravity, no damping) collide
    off-centre: total linear momentum is conserved to rounding."""
    params = make_params(incline(0.0), gravity=0.0, stiffness_scale=0.01)
    block = make_block(1.0, alpha=0.0, n_fragments=4)
    pos = jnp.array([[-1.0, 50.0], [0.0, 50.2], [20.0, 80.0], [40.0, 80.0]])
    vel = jnp.array([[3.0, 0.0], [-1.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    pose = Pose(pos, jnp.array([0.0, 0.3, 0.0, 0.0]), vel, jnp.zeros(4))
    c, h = run_traj(params, block, pose, 200, 20)
    m = float(c.mass)
    p = m * np.sum(np.asarray(h.vel), axis=1)
    np.testing.assert_allclose(p, np.broadcast_to(m * np.array([2.0, 0.0]), p.shape), rtol=0,
                               atol=1e-9 * m)
    assert not np.allclose(np.asarray(h.vel[-1, 0]), [3.0, 0.0])  # they did collide
    assert not np.any(np.asarray(h.intact[-1]))


# slow: a 16-fragment block run to rest on Postignano, 31 s in a default run (13 s of it
# compiling a program no other test uses); the default run keeps the guard that turns a
# fragment below the ground into INVALID
# (tests/test_dem_rest.py::test_tunnelled_fragment_is_invalid)
@pytest.mark.slow
def test_no_fragment_inside_ground():
    """16 fragments of a 1.8 m block end above the ground (within 10x the static
    penetration of the whole block on one fragment corner)."""
    prof = load_profile(PROFILE_CSV)
    params = make_params(prof, stiffness_scale=0.01)
    block = make_block(1.8, n_fragments=16)
    opts = Options(max_steps=int(40.0 / float(stable_dt(params, block))))
    res = jax.jit(lambda k: simulate(params, block, k, opts))(jax.random.key(3))
    tol = 10 * params.rho * 1.8 ** 2 * G / (params.kn * params.stiffness_scale * 0.225)
    clearance = np.asarray(res.stop_z_m) - np.asarray(ground_z(prof, res.stop_x_m))
    assert np.all(clearance > 0.45 * 0 + 0.0 - tol)  # centre above ground ...
    # ... and every corner too (corner depth <= tol): centre height >= -tol + 0 for a
    # fragment of half side 0.225 lying on any face means clearance >= 0.225 cos - tol
    assert np.all(clearance > 0.225 * math.cos(math.radians(40)) - 0.225 * 0.1 - tol)


@pytest.mark.slow  # an equivalence of pair prefixes, 10 s: run with -m slow
def test_adaptive_pair_prefix_same_result():
    """The chunk-level switch (short pair prefix, joints skipped once broken)
    gives the forces of the full pair list: same final state."""
    prof = load_profile(PROFILE_CSV)
    params = make_params(prof, stiffness_scale=0.01)
    block = make_block(1.8, n_fragments=4)
    n = int(6.0 / float(stable_dt(params, block)))
    out = [jax.jit(lambda k, o=o: simulate(params, block, k, o))(jax.random.key(5))
           for o in (Options(max_steps=n), Options(max_steps=n, adaptive=False))]
    np.testing.assert_allclose(np.asarray(out[0].stop_x_m), np.asarray(out[1].stop_x_m),
                               rtol=0, atol=1e-9)
    assert float(out[0].joints_broken) > 0  # joints did break on the way


# ---------------------------------------------------------------- batching, keys

def _small():
    prof = load_profile(PROFILE_CSV)
    params = make_params(prof, stiffness_scale=0.01)
    return params, make_block(0.9, alpha=0.43), Options(max_steps=20_000)


def test_vmap_equals_loop():
    params, block, opts = _small()
    keys = jax.random.split(jax.random.key(7), 3)
    batched = simulate_batch(params, block, keys, opts)
    one = jax.jit(lambda k: simulate(params, block, k, opts))
    for i in range(3):
        r = one(keys[i])
        # XLA may fuse the batched and single programs differently (rounding only)
        np.testing.assert_allclose(np.asarray(batched.stop_x_m[i]), np.asarray(r.stop_x_m),
                                   rtol=1e-8)


def test_same_key_same_result_and_keys_differ():
    params, block, opts = _small()
    f = jax.jit(lambda k: simulate(params, block, k, opts))
    a, b = f(jax.random.key(1)), f(jax.random.key(1))
    np.testing.assert_array_equal(np.asarray(a.stop_x_m), np.asarray(b.stop_x_m))
    c = f(jax.random.key(2))
    assert float(c.stop_x_m[0]) != float(a.stop_x_m[0])


def test_unstopped_block_is_flagged():
    params, block, _ = _small()
    r = simulate(params, block, jax.random.key(0), Options(max_steps=1000))
    assert int(r.status) == BUDGET and not bool(r.stopped[0])


def test_stable_dt_formula():
    params = make_params(load_profile(PROFILE_CSV))
    block = make_block(0.9, alpha=0.43)
    m = 2350 * 0.81
    expected = 0.1 * 2 * math.sqrt((m / 3) / (2 * 50e9 * 0.45))
    assert float(stable_dt(params, block)) == pytest.approx(expected, rel=1e-12)


# ---------------------------------------------------------------- alpha law

def test_alpha_law_table1_trend_and_safety():
    law = parse_alpha_law("0.40*L**-0.5")
    np.testing.assert_allclose([float(law(x)) for x in (0.2, 0.9, 1.8)], [0.90, 0.43, 0.30],
                               atol=0.01)
    assert float(parse_alpha_law("minimum(0.9, exp(-L))")(1.0)) == pytest.approx(math.exp(-1))
    for bad in ("__import__('os')", "L.real", "x*2", "[1][0]", "lambda: 1", ""):
        with pytest.raises(AlphaLawError):
            parse_alpha_law(bad)
    with pytest.raises(AlphaLawError):
        make_block(0.01, alpha_law="0.40*L**-0.5")  # alpha > 1 for a 1 cm block


def test_run_numerics_have_one_check_that_names_the_callers_value():
    """check_run_numerics: the stiffness scale in (0, 1], the simulated time finite
    and positive; None is not checked; the message names the value as the caller
    does (python -m solvers.dem and python -m calib.hazard pass their options,
    calib's DemRun its fields)."""
    check_run_numerics(0.01, 150.0)
    check_run_numerics(1.0, None)
    check_run_numerics()
    with pytest.raises(ValueError, match=r"^--stiffness-scale: expected a value in \(0, 1\], "
                                         r"got 0$"):
        check_run_numerics(0.0, 150.0, {"stiffness_scale": "--stiffness-scale"})
    for bad in (1.5, math.nan, math.inf):
        with pytest.raises(ValueError, match="^stiffness_scale: expected a value in"):
            check_run_numerics(bad)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="^max_time_s: expected a positive time"):
            check_run_numerics(max_time_s=bad)


# ---------------------------------------------------------------- CLI

BAD_ARGS = [
    ["--block-size-m", "0.9", "--out", "x.csv"],                         # no profile
    ["--profile", "nope.csv", "--block-size-m", "0.9", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "-1", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--fragments", "5", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--alpha", "1.5", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--alpha-law-expr", "__import__('os')",
     "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--alpha", "0.4", "--alpha-law-expr",
     "0.4*L", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--n-blocks", "0", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--stations-m", "500", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "abc", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--restitution", "0.5",
     "--out", "x.csv"],                                                 # not viscous
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--damping", "viscous",
     "--restitution", "0", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--damping", "rayleigh",
     "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--batch-size", "0", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--stiffness-scale", "0",
     "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--max-time-s", "nan", "--out", "x.csv"],
    ["--profile", PROFILE_CSV, "--block-size-m", "0.9", "--density-kg-m3", "0", "--out", "x.csv"],
]


@pytest.mark.parametrize("args", BAD_ARGS)
def test_cli_bad_arguments(args, tmp_path, monkeypatch, capsys):
    """One line on stderr, exit 2, no file (``main`` in this process; the exit
    status of a real process: ``test_cli_bad_arguments_in_a_real_process``)."""
    from solvers.dem.__main__ import main

    monkeypatch.chdir(tmp_path)  # the relative --out x.csv lands here, if anywhere
    rc, _, err = run_cli(main, [PROFILE_ABS if a == PROFILE_CSV else a for a in args], capsys)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0], err
    assert not (tmp_path / "x.csv").exists()


def test_cli_bad_arguments_in_a_real_process(tmp_path):
    p = subprocess.run([sys.executable, "-m", "solvers.dem", "--profile", PROFILE_CSV,
                        "--block-size-m", "-1", "--out", str(tmp_path / "x.csv")],
                       capture_output=True, text=True)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0], p.stderr
    assert not (tmp_path / "x.csv").exists()


def test_cli_writes_rows(tmp_path):
    out = tmp_path / "dem.csv"
    p = subprocess.run([sys.executable, "-m", "solvers.dem", "--profile", PROFILE_CSV,
                        "--block-size-m", "0.9", "--n-blocks", "2", "--alpha", "0.43",
                        "--fragments", "4", "--max-time-s", "5", "--density-kg-m3", "9400",
                        "--seed", "0", "--stations-m", "110", "--no-progress",
                        "--out", str(out)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    import re

    import pandas as pd

    from solvers.cli import RUN_COLUMNS
    df = pd.read_csv(out)
    assert len(df) == 8
    # the schema of python -m solvers.crsp (solvers.cli.RUN_COLUMNS), one row per fragment
    assert list(df.columns[:len(RUN_COLUMNS) + 1]) == [*RUN_COLUMNS, "n_steps"]
    assert list(df.block) == [0] * 4 + [1] * 4 and list(df.fragment) == [0, 1, 2, 3] * 2
    assert (df.block_size_m == 0.9).all()
    # --density-kg-m3 reaches the parameters: 4x the paper's 2350 is 2x the stable step
    # (dt ~ sqrt(m / k)) at the default stiffness scale, the calibration's
    params = make_params(load_profile(PROFILE_CSV), stiffness_scale=0.01)
    dt_paper = float(stable_dt(params, make_block(0.9, alpha=0.43, n_fragments=4)))
    dt = float(re.search(r"dt=([0-9.e+-]+) s", p.stdout).group(1))
    assert abs(dt / dt_paper - 2.0) < 2e-2, (dt, dt_paper)  # dt printed to 3 digits
    # python -m solvers.crsp's station names; the 2D energy says it is per metre of width
    assert list(df.columns[-4:]) == ["passed_110m", "energy_kJ_per_m_110m",
                                     "velocity_m_s_110m", "bounce_height_m_110m"]
    assert len(p.stdout.strip().splitlines()) == 1
    assert "DEM:" not in p.stderr  # --no-progress: no bar


def test_cli_fragment_status():
    """Each row's status is its fragment's: every fragment of an invalid block is
    invalid; a fragment that passed the profile's end left it, its siblings at
    rest stopped; a block out of budget leaves its fragments out of budget."""
    from solvers.dem.__main__ import _fragment_status
    from solvers.status import BUDGET, INVALID, LEFT_PROFILE, STOPPED

    block = np.array([INVALID, LEFT_PROFILE, BUDGET, STOPPED])
    exited = np.array([[True, False], [True, False], [True, False], [False, False]])
    stopped = np.array([[False, False], [False, True], [False, False], [True, True]])
    assert list(_fragment_status(block, exited, stopped)) == [
        INVALID, INVALID, LEFT_PROFILE, STOPPED, LEFT_PROFILE, BUDGET, STOPPED, STOPPED]


def test_cli_viscous_batches(tmp_path):
    """--damping viscous with a restitution, run in batches of one block: one
    row per block, statuses are the shared names."""
    import pandas as pd

    from solvers.status import STATUS_NAMES
    out = tmp_path / "dem.csv"
    p = subprocess.run([sys.executable, "-m", "solvers.dem", "--profile", PROFILE_CSV,
                        "--block-size-m", "0.9", "--n-blocks", "2", "--damping", "viscous",
                        "--restitution", "0.5", "--stiffness-scale", "0.01",
                        "--max-time-s", "3", "--batch-size", "1", "--seed", "0",
                        "--out", str(out)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "damping=viscous" in p.stdout
    assert "DEM:" in p.stderr and "2/2" in p.stderr  # the progress bar, in blocks
    df = pd.read_csv(out)
    assert len(df) == 2 and set(df["status"]) <= set(STATUS_NAMES.values())


# ---------------------------------------------------------------- strength scaling

def _block_at_rest_broken(n_fragments, exponent):
    from test_dem_rest import incline as incline_rest
    from test_dem_rest import resting_pose
    params = make_params(incline_rest(25.0), stiffness_scale=0.01,
                         joint_strength_exponent=exponent)
    block = make_block(1.8, alpha=0.3, n_fragments=n_fragments)
    opts = Options(max_steps=int(3.0 / float(stable_dt(params, block))))
    pose = resting_pose(params, 1.8, 25.0, n_fragments)
    res = jax.jit(lambda p: simulate(params, block, jax.random.key(0), opts, p))(pose)
    return float(res.joints_broken)


@pytest.mark.slow
@pytest.mark.parametrize("n_fragments", [16, 64])
def test_block_at_rest_keeps_its_joints_unscaled_strengths(n_fragments):
    """Control of the next test: with unscaled strengths (exponent 0) the same
    block at rest at kn x0.01 keeps every joint."""
    assert _block_at_rest_broken(n_fragments, 0.0) == 0.0


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured: at kn x0.01 the sqrt-scaled default strengths "
                   "(c 0.2 -> 0.02 MPa, t 0.1 -> 0.01 MPa) do not carry the block's own weight: "
                   "16 fragments lose 8 % of their joints and 64 fragments 100 % within 3 s "
                   "(0 % at x1, and 0 % at x0.01 with unscaled strengths). Static stresses do "
                   "not scale with k, impact forces do (Params.joint_strength_exponent)")
@pytest.mark.parametrize("n_fragments", [16, 64])
def test_block_at_rest_keeps_its_joints_under_stiffness_shortcut(n_fragments):
    """An intact 1.8 m block placed at rest on a 25 deg slope (phi 30, alpha
    0.3), default joint strengths (scaled by sqrt(0.01)), kn x0.01: no joint
    breaks in 3 s."""
    broken = _block_at_rest_broken(n_fragments, 0.5)
    assert broken == 0.0, broken


def test_release_at_a_given_height_and_speed():
    """A block with its own release height and speed (a tracked field run) starts
    with its lowest possible point (a corner, half a diagonal below the centre)
    that height above the ground at the release point and that horizontal
    speed; with both NaN (``make_block``'s default) the release rule's 1 cm
    and speed in [0, 1) m/s, as before, from the same key."""
    from solvers.dem._integrate import _release

    prof = load_profile("data/postignano_profile.csv")
    params = make_params(prof)
    key = jax.random.key(3)
    own = make_block(0.8, alpha=0.5, n_fragments=4, release_x_m=20.0,
                     release_speed_m_s=2.5, release_height_m=1.2)
    rule = make_block(0.8, alpha=0.5, n_fragments=4, release_x_m=20.0)
    ground = float(ground_z(prof, jnp.asarray(20.0)))
    half_diag = 0.8 / math.sqrt(2.0)
    p_own, p_rule = _release(params, own, key), _release(params, rule, key)
    centre = np.asarray(p_own.pos).mean(axis=0)
    assert centre[1] - half_diag - ground == pytest.approx(1.2, abs=1e-9)
    np.testing.assert_allclose(np.asarray(p_own.vel), [[2.5, 0.0]] * 4)
    centre = np.asarray(p_rule.pos).mean(axis=0)
    assert centre[1] - half_diag - ground == pytest.approx(params.release_gap_m, abs=1e-9)
    v = np.asarray(p_rule.vel)[:, 0]
    assert np.all(v == v[0]) and 0.0 <= v[0] < params.release_speed_m_s
    np.testing.assert_array_equal(p_own.theta, p_rule.theta)  # same key, same turn
