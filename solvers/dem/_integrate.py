"""State, pure step and the bounded rollout of one (possibly fragmented) block.

Integration is UDEC's central-difference scheme (Itasca UDEC theory, "motion
of rigid blocks"; Cundall & Hart 1992): velocities live at half steps,

    v(t + dt/2) = v(t - dt/2) + (F(t) + F_d(t)) / m dt,
    x(t + dt)   = x(t) + v(t + dt/2) dt,

and the same for the rotation with the torque and I = m s^2 / 6. It is
second order for position-dependent forces. The local damping (paper eq. 3,
alpha = pi D) acts per degree of freedom (x, z, rotation):

    F_d,i = -alpha |F_i| sign(v_i),

where F_i is the whole unbalanced force including gravity (Cundall's classic
form, used by Itasca's codes: ``damp_gravity = 1``) or the contact force only
(``damp_gravity = 0``). In the classic form a block in free flight with
alpha = 0.9 falls at 0.1 g and rises against 1.9 g. The "viscous" mode turns
local damping off and puts dashpots at the contacts instead (``_contact``).

Rest (our rule, see ``Params``): a fragment is held while it is slow, none of
its wall or fragment contacts slips (faster than ``rest_slip_m_s``), and its contacts lie
inside the Coulomb cone with a margin or it has moved less than
``rest_disp_m`` since the hold began; it is at rest after ``stop_hold_s`` of
being held. Status codes are
``solvers.status``'s: a block whose fragments are all at rest is ``STOPPED``
(``LEFT_PROFILE`` if one passed the profile end), still running after
``max_steps`` is ``BUDGET``, and a non-finite position or a fragment centre
below the ground line (tunnelled through the wall) is ``INVALID``.

Loop: ``lax.while_loop`` over chunks of ``Options.chunk`` steps (a
``fori_loop``), ending when every fragment has stopped or left the profile, or
after ``Options.max_steps``. We use a bounded while loop rather than a scan of
max_steps because blocks stop at very different times (a scan would pay for
max_steps every time); the price is no reverse-mode AD, which NOTES.md shows is
useless past ~0.5 s of contact anyway (finite differences with common random
numbers are the calibration route). Under ``vmap`` the loop runs until the
slowest lane ends; finished lanes are frozen by the ``status`` mask, and the
sums over corners and contacts are fixed chains of additions (``_sums``),
which round alike in every lane, so a block's result does not depend on its
batch or on its place in it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from solvers.dem._contact import (
    joint_forces,
    pair_forces,
    pair_list_forces,
    pair_shear_stiffness,
    wall_forces,
)
from solvers.dem._geometry import (
    SegmentTable,
    corner_offsets,
    cross2,
    fragment_layout,
    joints_of,
    rotate,
    segment_lookup,
    segment_table,
)
from solvers.dem._params import (
    Block,
    Options,
    Params,
    contact_damping_ratio,
    stable_dt,
)
from solvers.dem._sums import ordered_sum
from solvers.profile import ground_z
from solvers.stations import StationRecord, empty_record, record_passage
from solvers.status import BUDGET, INVALID, LEFT_PROFILE, RUNNING, STOPPED
from solvers.truncated_normal import nonnegative_normal

__all__ = ["Consts", "Pose", "Result", "State", "init", "result", "rollout", "simulate",
           "simulate_batch", "step", "trajectory"]


class Pose(NamedTuple):
    """Explicit initial conditions of the N fragments (bypasses the random release).

    pos (N,2) m, theta (N,) rad, vel (N,2) m/s, omega (N,) rad/s.
    """

    pos: jax.Array
    theta: jax.Array
    vel: jax.Array
    omega: jax.Array


class Consts(NamedTuple):
    """Per-block constants computed once by ``init``."""

    dt: jax.Array
    mass: jax.Array          # kg/m, per fragment
    inertia: jax.Array       # kg m2/m, per fragment
    half: jax.Array          # half side h, m
    alpha: jax.Array         # (N,)
    kn_c: jax.Array          # kn l_c, N/m per m
    ks_c: jax.Array
    c_c: jax.Array           # joint cohesion x l_c (scaled, see Params), N/m
    t_c: jax.Array           # joint tensile strength x l_c (scaled), N/m
    cn_wall: jax.Array       # (N,) wall-corner dashpot, N s/m per m (0: none)
    cn_pair: jax.Array       # (N,) fragment's share of a pair/joint dashpot
    width: jax.Array         # softplus width, m
    seg: SegmentTable
    x_end: jax.Array
    x_release: jax.Array
    ground_at_stations: jax.Array  # (S,)


class State(NamedTuple):
    """Dynamic state of one block's fragments (N fragments, J joints, S stations).

    pos (N,2) float64 m at t; theta (N,) rad; vel (N,2) and omega (N,) at
    t - dt/2; fs (N,4) wall shear force per corner (N/m); fs_pair (N,N,2)
    fragment-fragment shear springs (``_contact.PairContacts.fs``, N/m);
    intact (J,) joints;
    slow_s (N,) time held by the rest test (s; the name predates the test);
    anchor (N,3) pose (x, z, theta) at the start of the hold; exited (N,) left
    the profile end; rec StationRecord with (N,S) fields; n_steps, status
    scalars.
    """

    pos: jax.Array
    theta: jax.Array
    vel: jax.Array
    omega: jax.Array
    fs: jax.Array
    fs_pair: jax.Array
    intact: jax.Array
    slow_s: jax.Array
    anchor: jax.Array
    exited: jax.Array
    rec: StationRecord
    n_steps: jax.Array
    status: jax.Array


class Result(NamedTuple):
    """Outcome for one block; per-fragment fields have shape (N,).

    stop_x_m, stop_z_m: final centre position, m. runout_m: stop_x_m minus the
    release abscissa (horizontal travel), m. stopped: came to rest (flagged
    False if it left the profile or ran out of steps). exited: passed the
    profile end. status: block status (see ``STATUS_NAMES``). n_steps, time_s,
    dt_s: steps run, simulated time, time step. joints_broken: fraction of
    joints broken. stations: StationRecord with (N,S) fields.
    """

    stop_x_m: jax.Array
    stop_z_m: jax.Array
    runout_m: jax.Array
    stopped: jax.Array
    exited: jax.Array
    status: jax.Array
    n_steps: jax.Array
    time_s: jax.Array
    dt_s: jax.Array
    joints_broken: jax.Array
    stations: StationRecord


def consts(params: Params, block: Block) -> Consts:
    """Per-block constants. Dashpots (``_contact``): c = 2 zeta sqrt(m_eff kn l_c)
    with m_eff = m/2 at a wall corner and m/4 at a fragment-fragment contact point or
    joint point; zeta from ``params.restitution`` (or each fragment's alpha)."""
    n = block.n_side
    s = block.size_m / n
    mass = params.rho * s * s
    l_c = 0.5 * s
    kn_c = params.kn * params.stiffness_scale * l_c
    ks_c = params.ks * params.stiffness_scale * l_c
    width = params.smooth_width * mass * params.gravity / (2.0 * kn_c)
    strength = params.stiffness_scale ** params.joint_strength_exponent * l_c
    e_alpha = jnp.sqrt((1.0 - block.alpha) / (1.0 + block.alpha))
    e = jnp.where(params.restitution < 0.0, e_alpha, params.restitution)
    zeta = contact_damping_ratio(jnp.clip(e, 1e-6, 1.0))
    return Consts(
        dt=stable_dt(params, block), mass=mass, inertia=mass * s * s / 6.0, half=0.5 * s,
        alpha=block.alpha * params.local_damping, kn_c=kn_c, ks_c=ks_c,
        c_c=params.c_joint_pa * strength, t_c=params.t_joint_pa * strength,
        cn_wall=2.0 * zeta * jnp.sqrt(0.5 * mass * kn_c),
        cn_pair=2.0 * zeta * jnp.sqrt(0.25 * mass * kn_c), width=width,
        seg=segment_table(params.profile), x_end=params.profile.x_m[-1],
        x_release=block.release_x_m,
        ground_at_stations=ground_z(params.profile, block.stations_x_m))


def _release(params: Params, block: Block, key: jax.Array, errors: bool = False) -> Pose:
    """Random release at the cliff edge: orientation U(0, pi/2), downslope offset
    U(0, jitter), horizontal speed U(0, speed) or the block's own
    (``Block.release_speed_m_s``), its lowest possible point ``release_gap_m``
    or the block's own height (``Block.release_height_m``) above the ground at
    the release point; fragments laid out rigidly.

    A block's own height and speed are uncertain inputs, as in CRSP's release
    (``solvers.crsp.init``): with their sds (``Block.release_height_sd_m``,
    ``release_speed_sd_m_s``) positive each is a draw of a normal about the
    given value truncated to >= 0 (``solvers.truncated_normal``), from two
    uniforms of ``fold_in(key, 1)``, a stream of its own, so every other draw
    of the release, and every release with both sds 0, is as without them. A
    negative height is then a release from the error's tail above the ground;
    with sd 0 it is clipped: on the ground. The draws are compiled only with
    ``errors`` (``Options.release_errors``); without it a positive sd gives a
    NaN height, which the step reports as ``INVALID``."""
    n = block.n_side
    k_theta, k_x, k_v = jax.random.split(key, 3)
    theta0 = jax.random.uniform(k_theta, (), minval=0.0, maxval=0.5 * math.pi)
    jitter = params.release_jitter_m * jax.random.uniform(k_x, ())
    h, sd_h = block.release_height_m, block.release_height_sd_m
    v, sd_v = block.release_speed_m_s, block.release_speed_sd_m_s
    if errors:
        u_h, u_v = jax.random.uniform(jax.random.fold_in(key, 1), (2,), dtype=jnp.float64)
        h_given, v_given = nonnegative_normal(u_h, h, sd_h), nonnegative_normal(u_v, v, sd_v)
    else:
        h_given, v_given = jnp.maximum(h, 0.0), jnp.maximum(v, 0.0)
    v0 = jnp.where(jnp.isnan(v), params.release_speed_m_s * jax.random.uniform(k_v, ()),
                   v_given)
    gap = jnp.where(jnp.isnan(h), params.release_gap_m, h_given)
    if not errors:  # errors this program cannot draw: a NaN release, reported INVALID
        gap = jnp.where((sd_h > 0.0) | (sd_v > 0.0), jnp.nan, gap)
    big_r = block.size_m / math.sqrt(2.0)
    x0 = block.release_x_m + big_r + jitter
    z0 = ground_z(params.profile, block.release_x_m) + big_r + gap
    off = jnp.asarray(fragment_layout(n)) * (block.size_m / n)
    pos = jnp.stack([x0, z0]) + rotate(off, jnp.cos(theta0), jnp.sin(theta0))
    zeros = jnp.zeros((n * n,))
    return Pose(pos, zeros + theta0, jnp.stack([zeros + v0, zeros], axis=-1), zeros)


class ContactInfo(NamedTuple):
    """Per-fragment contact flags of one step (N,) bool, for the rest test.

    touching: in contact with the wall or a free fragment (intact joints do not
    count); near_limit: one of those contacts has |F_s| > (1 - margin)
    tan(phi) max(F_n, 0); slipped: one of its wall or fragment contacts slid
    this step.
    """

    touching: jax.Array
    near_limit: jax.Array
    slipped: jax.Array


def _forces(st: State, params: Params, c: Consts, nbr, options: Options, n_side: int):
    """Contact forces (N,2), torques (N,), new wall shear, new fragment shear
    springs, new joint flags, ContactInfo."""
    cs, sn = jnp.cos(st.theta), jnp.sin(st.theta)
    r = rotate(corner_offsets(c.half)[None], cs[:, None], sn[:, None])      # (N,4,2)
    p = st.pos[:, None, :] + r
    vp = st.vel[:, None, :] + st.omega[:, None, None] * jnp.stack([-r[..., 1], r[..., 0]], -1)
    if options.segment_search == "all":
        seg = _lookup_all(c.seg, p, params)
    else:
        seg = segment_lookup(c.seg, p[..., 0])
    margin = params.rest_cone_margin
    wall = wall_forces(p, vp, st.fs, seg, c.kn_c, c.ks_c, c.dt, c.width, options.smooth,
                       cn=c.cn_wall[:, None], margin=margin,
                       slip_tol=c.ks_c * params.rest_slip_m_s * c.dt)
    fw, fs = wall.force, wall.fs
    force = ordered_sum(fw, 1)
    torque = ordered_sum(cross2(r, fw), 1)
    touching = jnp.any(wall.touching, axis=1)
    near = jnp.any(wall.near_limit, axis=1)
    slipped = jnp.any(wall.slipped, axis=1)
    intact = st.intact
    if n_side > 1:
        joints = joints_of(n_side)
        tan_j = jnp.tan(jnp.deg2rad(params.phi_joint_deg))
        with_joints = options.pair_search == "knn" or len(nbr) < 4 or nbr[3]
        if with_joints:
            cj = 0.5 * (c.cn_pair[joints.a] + c.cn_pair[joints.b])[:, None, None]
            fj, tj, intact = joint_forces(st.pos, cs, sn, joints, st.intact, c.half, c.kn_c,
                                          c.ks_c, c.c_c, c.t_c, tan_j, st.vel, st.omega, cj)
        else:  # every joint already broken (chunk-level switch in ``simulate``)
            fj, tj = jnp.zeros_like(force), jnp.zeros_like(torque)
        slip_tol = pair_shear_stiffness(c.ks_c) * params.rest_slip_m_s * c.dt
        if options.pair_search == "knn":
            n_frag = n_side * n_side
            bonded = (jnp.zeros((n_frag, n_frag), bool).at[joints.a, joints.b].set(intact)
                      .at[joints.b, joints.a].set(intact))
            cn = 0.5 * (c.cn_pair[:, None] + c.cn_pair[nbr])
            pc = pair_forces(st.pos, cs, sn, st.vel, st.omega, nbr, bonded, ~st.exited,
                             st.fs_pair, c.half, c.kn_c, c.ks_c, tan_j, c.dt, c.width,
                             options.smooth, cn=cn, margin=margin, slip_tol=slip_tol)
        elif nbr[0].shape[0] == 0:  # no pair near enough to touch in this chunk
            pc = None
        else:
            pi, pj, jid = nbr[:3]
            free = jnp.concatenate([~intact, jnp.ones((1,), bool)])[jid]
            ok = free & ~st.exited[pi] & ~st.exited[pj]
            pc = pair_list_forces(st.pos, cs, sn, st.vel, st.omega, pi, pj, ok, st.fs_pair,
                                  c.half, c.kn_c, c.ks_c, tan_j, c.dt, c.width, options.smooth,
                                  cn=0.5 * (c.cn_pair[pi] + c.cn_pair[pj]), margin=margin,
                                  slip_tol=slip_tol)
        force = force + fj
        torque = torque + tj
        if pc is None:
            fs_pair = jnp.zeros_like(st.fs_pair)
        else:
            force, torque, fs_pair = force + pc.force, torque + pc.torque, pc.fs
            touching, near = touching | pc.touching, near | pc.near_limit
            slipped = slipped | pc.slipped
    else:
        fs_pair = st.fs_pair
    return force, torque, fs, fs_pair, intact, ContactInfo(touching, near, slipped)


def _lookup_all(table: SegmentTable, p, params: Params):
    """Brute-force variant: every corner tests every segment (for benchmarks)."""
    x_b = jnp.concatenate([table.x_inner, params.profile.x_m[-1:]])
    px, pz = p[..., 0][..., None], p[..., 1][..., None]
    inside = (px >= jnp.concatenate([params.profile.x_m[:1] - 1e9, table.x_inner])) \
        & (px < jnp.concatenate([x_b[:-1], x_b[-1:] + 1e9]))
    dist = -table.tz * (px - table.xa) + table.tx * (pz - table.za)
    best = jnp.argmax(jnp.where(inside, -jnp.abs(dist), -jnp.inf), axis=-1)
    onehot = best[..., None] == jnp.arange(table.xa.shape[0])
    return tuple(jnp.sum(jnp.where(onehot, f, 0.0), axis=-1)
                 for f in (table.xa, table.za, table.tx, table.tz, table.tan_phi))


def neighbours(st: State, k: int, options: Options = Options()):
    """Candidate contacts, rebuilt once per chunk of steps.

    "list" (default): the P = k N / 2 closest unordered pairs (i < j) of
    fragment centres, with each pair's joint index (J if none), as
    (pi, pj, jid). "knn": the (N, k) indices of the k nearest fragments of
    each fragment (the earlier scheme, kept for benchmarks).
    """
    d = st.pos[:, None, :] - st.pos[None, :, :]
    d2 = jnp.sum(d * d, axis=-1)
    n = st.pos.shape[0]
    if options.pair_search == "knn":
        d2 = jnp.where(jnp.eye(n, dtype=bool) | st.exited[None, :], jnp.inf, d2)
        return lax.top_k(-d2, k)[1]
    iu, ju = np.triu_indices(n, 1)
    n_pairs = min(len(iu), (k * n) // 2)
    d2p = jnp.where(st.exited[iu] | st.exited[ju], jnp.inf, d2[iu, ju])
    neg, sel = lax.top_k(-d2p, n_pairs)
    joints = joints_of(math.isqrt(n))
    jid_table = np.full((n, n), len(joints.a), np.int32)
    jid_table[joints.a, joints.b] = np.arange(len(joints.a))
    jid_table[joints.b, joints.a] = np.arange(len(joints.a))
    pi, pj = jnp.asarray(iu)[sel], jnp.asarray(ju)[sel]
    return pi, pj, jnp.asarray(jid_table[iu, ju])[sel], -neg


def _pair_tiers(n_pairs: int) -> list[int]:
    """Static pair-list lengths a chunk may use (0, P/8, P/2, P)."""
    return sorted({0, n_pairs // 8, n_pairs // 2, n_pairs})


def _chunk(s: State, params, c: Consts, options: Options, block: Block, k_nb: int) -> State:
    """Run ``options.chunk`` steps with one candidate-pair list.

    With ``options.adaptive`` (list search only) the chunk picks, by
    ``lax.switch``, the shortest static prefix of the distance-sorted pair
    list that holds every pair whose centres are closer than the contact
    range s sqrt(2) plus a skin (twice the distance two fragments can close
    in a chunk at twice the fastest current speed, plus 2 cm), and leaves out
    the joint forces once every joint is broken. Pairs beyond that range
    cannot touch within the chunk, so the forces are those of the full list.
    """
    n = block.n_side

    def run(nbr):
        return lax.fori_loop(0, options.chunk,
                             lambda _, x: step_with_stations(x, params, c, nbr, options, block),
                             s)

    if n == 1:
        return run(None)
    nbr = neighbours(s, k_nb, options)
    if options.pair_search == "knn":
        return run(nbr)
    pi, pj, jid, d2 = nbr
    if not options.adaptive:
        return run((pi, pj, jid, True))
    radius = c.half * math.sqrt(2.0)
    vmax = jnp.max(jnp.where(s.exited, 0.0, jnp.sqrt(jnp.sum(s.vel ** 2, -1))
                             + jnp.abs(s.omega) * radius))
    skin = 2.0 * (2.0 * vmax) * options.chunk * c.dt + 0.02
    n_near = jnp.sum(d2 < (2.0 * radius + skin) ** 2)
    tiers = _pair_tiers(pi.shape[0])
    tier = jnp.searchsorted(jnp.asarray(tiers), n_near, side="left")
    any_joint = jnp.any(s.intact)
    branches = [(lambda p, j: (lambda _: run((pi[:p], pj[:p], jid[:p], j))))(p, j)
                for j in (False, True) for p in tiers]
    return lax.switch(tier + len(tiers) * any_joint.astype(jnp.int32), branches, None)


def init(params: Params, block: Block, key: jax.Array, options: Options = Options(),
         pose: Pose | None = None) -> tuple[Consts, State]:
    """Initial constants and state. ``pose`` overrides the random release.

    The first half-step velocity is v(-dt/2) = v(0) - a(0) dt/2 with a(0) the
    undamped acceleration, which keeps the scheme second order from t = 0.
    """
    n = block.n_side
    c = consts(params, block)
    pose = _release(params, block, key, options.release_errors) if pose is None else pose
    n_frag, n_joint = n * n, len(joints_of(n).a)
    st = State(pos=jnp.asarray(pose.pos, jnp.float64), theta=jnp.asarray(pose.theta),
               vel=jnp.asarray(pose.vel), omega=jnp.asarray(pose.omega),
               fs=jnp.zeros((n_frag, 4)), fs_pair=jnp.zeros((n_frag, n_frag, 2)),
               intact=jnp.ones((n_joint,), bool),
               slow_s=jnp.zeros((n_frag,)),
               anchor=jnp.concatenate([jnp.asarray(pose.pos, jnp.float64),
                                       jnp.asarray(pose.theta)[:, None]], axis=-1),
               exited=jnp.zeros((n_frag,), bool),
               rec=jax.tree.map(lambda a: jnp.broadcast_to(a, (n_frag,) + a.shape),
                                empty_record(block.stations_x_m.shape[0])),
               n_steps=jnp.asarray(0, jnp.int32), status=jnp.asarray(RUNNING, jnp.int32))
    nbr = neighbours(st, min(options.n_neighbors, n_frag - 1), options) if n > 1 else None
    if nbr is not None and options.pair_search != "knn":
        nbr = (*nbr[:3], True)
    force, torque, _, _, _, _ = _forces(st, params, c, nbr, options, n)
    acc = force / c.mass + jnp.array([0.0, -1.0]) * params.gravity
    st = st._replace(vel=st.vel - 0.5 * c.dt * acc,
                     omega=st.omega - 0.5 * c.dt * torque / c.inertia)
    return c, st


def step(st: State, params: Params, c: Consts, nbr, options: Options, n_side: int) -> State:
    """One central-difference step (pure). Frozen once ``status`` != RUNNING.

    Also advances the rest test (``Params``: held = slow and no wall slip and
    (contacts inside the Coulomb cone with margin, or moved < rest_disp_m
    since the hold began)) and sets the status (``solvers.status`` codes).
    """
    force, torque, fs, fs_pair, intact, info = _forces(st, params, c, nbr, options, n_side)
    g = jnp.array([0.0, -1.0]) * (c.mass * params.gravity)
    f_unbal = force + g
    f_base = force + params.damp_gravity * g
    if options.smooth:
        def sgn(v):
            return jnp.tanh(v / params.sign_eps_m_s)
    else:
        sgn = jnp.sign
    alpha = c.alpha
    f_damp = -alpha[:, None] * jnp.abs(f_base) * sgn(st.vel)
    t_damp = -alpha * jnp.abs(torque) * sgn(st.omega)
    vel = st.vel + (f_unbal + f_damp) * (c.dt / c.mass)
    omega = st.omega + (torque + t_damp) * (c.dt / c.inertia)
    pos = st.pos + vel * c.dt
    theta = st.theta + omega * c.dt

    running = st.status == RUNNING
    move = running & ~st.exited
    pos = jnp.where(move[:, None], pos, st.pos)
    theta = jnp.where(move, theta, st.theta)
    vel = jnp.where(move[:, None], vel, st.vel)
    omega = jnp.where(move, omega, st.omega)
    fs = jnp.where(move[:, None], fs, st.fs)
    fs_pair = jnp.where(running, fs_pair, st.fs_pair)
    intact = jnp.where(running, intact, st.intact)

    rec = st.rec  # stations are recorded by step_with_stations
    exited = st.exited | (pos[:, 0] > c.x_end)
    radius = c.half * math.sqrt(2.0)
    # rest test (our rule; see Params and the module docstring)
    speed2 = jnp.sum(vel * vel, axis=-1) + (omega * radius) ** 2
    slow = speed2 < params.stop_speed_m_s ** 2
    stuck = info.touching & ~info.near_limit
    moved = (jnp.sqrt(jnp.sum((pos - st.anchor[:, :2]) ** 2, axis=-1))
             + radius * jnp.abs(theta - st.anchor[:, 2]))
    held = slow & ~info.slipped & (stuck | (moved < params.rest_disp_m))
    slow_s = jnp.where(held, st.slow_s + c.dt, 0.0)
    anchor = jnp.where(held[:, None], st.anchor,
                       jnp.concatenate([pos, theta[:, None]], axis=-1))
    slow_s = jnp.where(move, slow_s, st.slow_s)
    anchor = jnp.where(move[:, None], anchor, st.anchor)
    finished = jnp.all((slow_s >= params.stop_hold_s) | exited)
    # invalid: a non-finite value, or a fragment centre below the ground line
    xa, za, tx, tz, _ = segment_lookup(c.seg, pos[:, 0])
    below = (tx * (pos[:, 1] - za) - tz * (pos[:, 0] - xa)) < 0.0
    bad = ~jnp.all(jnp.isfinite(pos)) | ~jnp.all(jnp.isfinite(vel)) | jnp.any(below & ~exited)
    n_steps = st.n_steps + running.astype(jnp.int32)
    new_status = jnp.where(bad, INVALID,
                           jnp.where(finished, jnp.where(jnp.any(exited), LEFT_PROFILE, STOPPED),
                                     jnp.where(n_steps >= options.max_steps, BUDGET,
                                               RUNNING)))
    status = jnp.where(running, new_status, st.status).astype(jnp.int32)
    return State(pos, theta, vel, omega, fs, fs_pair, intact, slow_s, anchor, exited, rec, n_steps,
                 status)


def _lowest_z(st: State, c: Consts) -> jax.Array:
    """(N,) height of each fragment's lowest corner, m."""
    cs, sn = jnp.cos(st.theta), jnp.sin(st.theta)
    corners = st.pos[:, None, :] + rotate(corner_offsets(c.half)[None], cs[:, None],
                                          sn[:, None])
    return jnp.min(corners[..., 1], axis=1)


def _stations(old: State, new: State, c: Consts, block: Block) -> StationRecord:
    """Record first downslope passages of the stations during the step old -> new.

    Speed and energy use v(t + dt/2), the velocity over the step in which the
    centre crossed. The clearance is interpolated linearly to the crossing,
    x(t) + f (x(t+dt) - x(t)) = x_s, between the lowest-corner heights at t
    and t + dt (it was taken at t + dt, one step late).
    """
    xs = block.stations_x_m
    x0, x1 = old.pos[:, 0:1], new.pos[:, 0:1]
    crossed = (x0 < xs) & (x1 >= xs)
    dx = x1 - x0
    f = jnp.where(crossed, (xs - x0) / jnp.where(crossed, dx, 1.0), 1.0)
    e_kj = 0.5e-3 * (c.mass * jnp.sum(new.vel ** 2, -1) + c.inertia * new.omega ** 2)
    speed = jnp.sqrt(jnp.sum(new.vel ** 2, -1))
    low0, low1 = _lowest_z(old, c)[:, None], _lowest_z(new, c)[:, None]
    height = low0 + f * (low1 - low0) - c.ground_at_stations
    return record_passage(old.rec, crossed, jnp.broadcast_to(e_kj[:, None], crossed.shape),
                          jnp.broadcast_to(speed[:, None], crossed.shape), height)


def step_with_stations(st, params, c, nbr, options, block):
    n = block.n_side
    new = step(st, params, c, nbr, options, n)
    if block.stations_x_m.shape[0] > 0:
        new = new._replace(rec=_stations(st, new, c, block))
    return new


def result(st: State, c: Consts) -> Result:
    """``Result`` of a final state (per-fragment fields (N,))."""
    stopped = ~st.exited & ((st.status == STOPPED) | (st.status == LEFT_PROFILE))
    broken = jnp.mean((~st.intact).astype(jnp.float64)) if st.intact.shape[0] else \
        jnp.asarray(0.0)
    return Result(stop_x_m=st.pos[:, 0], stop_z_m=st.pos[:, 1],
                  runout_m=st.pos[:, 0] - c.x_release, stopped=stopped, exited=st.exited,
                  status=st.status, n_steps=st.n_steps, time_s=st.n_steps * c.dt, dt_s=c.dt,
                  joints_broken=broken, stations=st.rec)


def simulate(params: Params, block: Block, key: jax.Array, options: Options = Options(),
             pose: Pose | None = None) -> Result:
    """Roll one block (or one fragmented block) out until rest (pure; vmap it).

    Args:
        params: physics and numerics (``Params``).
        block: size, per-fragment alpha, release point, stations (``Block``).
        key: PRNG key of the random release (orientation, offset, speed).
        options: static options (``Options``), hashable.
        pose: explicit initial conditions instead of the random release.

    Returns:
        ``Result`` with per-fragment stop positions, runouts and flags.
    """
    c, st = rollout(params, block, key, options, pose)
    return result(st, c)


def rollout(params: Params, block: Block, key: jax.Array, options: Options = Options(),
            pose: Pose | None = None) -> tuple[Consts, State]:
    """``simulate`` returning the constants and the final ``State`` (pure; vmap it).

    The final state carries what a ``Result`` drops (velocities, wall shear
    springs, broken joints), e.g. for ``deposit_check``.
    """
    n = block.n_side
    c, st = init(params, block, key, options, pose)
    k_nb = min(options.n_neighbors, n * n - 1)
    st = lax.while_loop(lambda s: s.status == RUNNING,
                        lambda s: _chunk(s, params, c, options, block, k_nb), st)
    return c, st


def simulate_batch(params: Params, block: Block, keys: jax.Array,
                   options: Options = Options()) -> Result:
    """``jit(vmap(simulate))`` over a batch of keys (one block per key)."""
    return simulate_batch_jit(params, block, keys, options)


def _simulate_batch_impl(params, block, keys, options):
    if keys.shape[0] == 1:  # one lane: no vmap, so the adaptive lax.switch stays a switch
        return jax.tree.map(lambda a: a[None], simulate(params, block, keys[0], options))
    # under vmap a switch runs every branch: use the plain full pair list
    options = options._replace(adaptive=False)
    return jax.vmap(lambda k: simulate(params, block, k, options))(keys)


# the jitted batch itself (AOT: simulate_batch_jit.lower(...).compile())
simulate_batch_jit = jax.jit(_simulate_batch_impl, static_argnames=("options",))


def trajectory(params: Params, block: Block, key: jax.Array, n_saves: int, every: int,
               options: Options = Options(), pose: Pose | None = None):
    """Fixed-length rollout saving the state every ``every`` steps (lax.scan).

    For tests and figures. Returns (Consts, stacked States of leading size n_saves).
    """
    n = block.n_side
    c, st = init(params, block, key, options, pose)
    k_nb = min(options.n_neighbors, n * n - 1)

    def outer(s, _):
        nbr = neighbours(s, k_nb, options) if n > 1 else None
        if nbr is not None and options.pair_search != "knn":
            nbr = (*nbr[:3], True)
        s = lax.fori_loop(0, every,
                          lambda _, x: step_with_stations(x, params, c, nbr, options, block), s)
        return s, s

    _, hist = lax.scan(outer, st, None, length=n_saves)
    return c, hist
