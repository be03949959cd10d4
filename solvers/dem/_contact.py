"""Contact laws: block-wall corners, fragment-fragment faces, bonded joints.

All forces are per metre of thickness (N/m); a contact of length l_c = s/2
(see ``_params``) turns the joint stiffness kn (Pa/m) into a spring kn l_c.

Constitutive law (paper eqs. 1-2, UDEC joint model):
    normal:  F_n = kn l_c delta            (delta = penetration >= 0; the
             incremental form dF_n = -kn l_c du_n summed from first touch)
    shear:   F_s <- F_s - ks l_c du_s,      du_s = v_t dt (incremental spring)
    limits:  |F_s| <= c l_c + F_n tan(phi) (Mohr-Coulomb), F_n >= -t l_c.
The wall has c = t = 0. Smooth variant (``smooth=True``): F_n = kn l_c w
softplus(delta / w) and |F_s| clipped by F_max tanh(F_s / F_max), so that the
force is C-infinity in positions and parameters. Sources: Itasca UDEC theory
(joint constitutive model, contact length), Cundall & Hart (1992).

Contact dashpots (the "viscous" damping mode; our addition, not the paper's
model): a linear dashpot in parallel with the normal spring of every wall and
fragment-fragment contact, F_n = kn l_c delta + c_n d(delta)/dt (Cundall &
Strack 1979), and with both springs of every intact joint. The coefficient is
c = 2 zeta sqrt(m_eff kn l_c) with zeta from the target restitution
(``_params.contact_damping_ratio``). Our choice of m_eff per contact point:
m/2 at a wall corner (two corners carry a face, so a flat face-down impact of
a fragment of mass m has exactly the target e), m/4 at a fragment-fragment
contact point and at a joint point (reduced mass m/2 of two equal fragments, two
points per face). A single-corner impact has another true effective mass,
1 / (1/m + (r x n)^2 / I), from 0.4 m (lever arm along the wall) to m (corner
straight down), so its restitution differs from the target: measured 0.61
for target 0.5 with the corner straight down (tests/test_dem.py). The dashpot
force is not clipped at zero (see ``contact_damping_ratio``); the Coulomb
limit uses max(F_n, 0).

Each contact function also reports, per fragment, whether it touches
something, whether one of its contacts is near the Coulomb limit and (wall and
fragment contacts) whether one slid in the step (the rest test in
``_integrate``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from solvers.dem._geometry import Joints, cross2, rotate
from solvers.dem._sums import ordered_sum

__all__ = ["PairContacts", "WallContact", "joint_forces", "pair_forces", "pair_list_forces",
           "pair_shear_stiffness", "penetration_force", "wall_forces"]

_TINY = 1e-30


def penetration_force(delta, k_c, width, smooth: bool):
    """Normal force for penetration ``delta`` (m): k_c max(delta, 0), or its
    softplus smoothing k_c w log(1 + exp(delta / w))."""
    if smooth:
        return k_c * width * jnp.logaddexp(0.0, delta / width)
    return k_c * jnp.maximum(delta, 0.0)


def _clip_shear(fs_trial, f_max, smooth: bool):
    if smooth:
        safe = jnp.where(f_max > _TINY, f_max, 1.0)
        return jnp.where(f_max > _TINY, safe * jnp.tanh(fs_trial / safe), 0.0)
    return jnp.clip(fs_trial, -f_max, f_max)


class WallContact(NamedTuple):
    """Corner-to-wall contact state of one step, each (...) like the corners.

    force (..., 2) N/m on the corner; fs new shear force N/m; delta penetration
    m; fn normal force N/m (spring + dashpot); touching bool; slipped bool (the
    trial shear exceeded the Coulomb limit by more than ``slip_tol`` and was
    clipped: the contact slid);
    near_limit bool (|F_s| > (1 - margin) tan(phi) max(F_n, 0)).
    """

    force: jax.Array
    fs: jax.Array
    delta: jax.Array
    fn: jax.Array
    touching: jax.Array
    slipped: jax.Array
    near_limit: jax.Array


def wall_forces(p, vp, fs_old, seg, kn_c, ks_c, dt, width, smooth: bool, cn=0.0,
                margin=0.05, slip_tol=0.0) -> WallContact:
    """Corner-to-wall contact forces.

    Normal: F_n = kn l_c delta - c_n v_n (v_n = corner velocity along the
    upward normal; c_n = 0 without dashpots). Shear: incremental spring
    F_s <- F_s - ks l_c v_t dt, clipped to tan(phi) max(F_n, 0) (eq. 2, c = 0).

    Args:
        p: (..., 2) corner positions, m. vp: (..., 2) corner velocities, m/s.
        fs_old: (...) shear force carried from the last step, N/m, along the
            segment tangent.
        seg: (xa, za, tx, tz, tan_phi) of the segment below each corner.
        kn_c, ks_c: contact springs kn l_c, ks l_c, N/m per m.
        dt: time step, s. width: softplus width, m.
        cn: normal dashpot coefficient, N s/m per m (broadcasts with the corners).
        margin: Coulomb-cone margin of the ``near_limit`` flag.
        slip_tol: excess of the trial shear over the limit, N/m, below which the
            contact is not flagged ``slipped`` (ks l_c x slip rate x dt).

    Returns:
        ``WallContact``.
    """
    xa, za, tx, tz, tan_phi = seg
    nx, nz = -tz, tx  # upward unit normal
    delta = -(nx * (p[..., 0] - xa) + nz * (p[..., 1] - za))
    touching = (penetration_force(delta, kn_c, width, smooth) > 0.0) if smooth else (delta > 0.0)
    vn = vp[..., 0] * nx + vp[..., 1] * nz
    fn = penetration_force(delta, kn_c, width, smooth) - jnp.where(touching, cn * vn, 0.0)
    vt = vp[..., 0] * tx + vp[..., 1] * tz
    fs_trial = jnp.where(touching, fs_old - ks_c * vt * dt, 0.0)
    f_max = jnp.maximum(fn, 0.0) * tan_phi
    fs = _clip_shear(fs_trial, f_max, smooth)
    force = jnp.stack([fn * nx + fs * tx, fn * nz + fs * tz], axis=-1)
    slipped = touching & (jnp.abs(fs_trial) - f_max > slip_tol)
    near_limit = touching & (jnp.abs(fs) > (1.0 - margin) * f_max)
    return WallContact(force, fs, delta, fn, touching, slipped, near_limit)



def joint_forces(pos, cs, sn, joints: Joints, intact, h, kn_c, ks_c, c_c, t_c, tan_phi,
                 vel=None, omega=None, cj=0.0):
    """Bonded joints: linear springs at the two end points of each shared face.

    With Delta = x_b(point) - x_a(point) (world) and the joint normal n rotating
    with fragment a: F_on_a = kn l_c (Delta.n) n + ks l_c (Delta.t) t, F_on_b =
    -F_on_a (for an elastic bond the incremental form of eq. 1 sums to this).
    A joint breaks for good (c = t = 0 afterwards) when at either point the
    compressive normal force F_c = -kn l_c Delta.n falls below -t l_c or the
    shear exceeds c l_c + max(F_c, 0) tan(phi) (eq. 2). With a dashpot
    (``vel``, ``omega`` given and cj > 0) an intact joint point also carries
    F_on_a += cj dDelta/dt (normal and shear alike); the strength test uses
    the spring forces only, as under local damping, whose forces are not joint
    stresses either (our choice).

    Returns:
        force (N,2), torque (N,), new intact flags (J,).
    """
    n_frag = pos.shape[0]
    a, b = joints.a, joints.b
    ra = rotate(jnp.asarray(joints.qa) * h, cs[a][:, None], sn[a][:, None])   # (J,2,2)
    rb = rotate(jnp.asarray(joints.qb) * h, cs[b][:, None], sn[b][:, None])
    delta = (pos[b][:, None] + rb) - (pos[a][:, None] + ra)
    n_w = rotate(jnp.asarray(joints.normal), cs[a], sn[a])[:, None, :]        # (J,1,2)
    t_w = jnp.stack([-n_w[..., 1], n_w[..., 0]], axis=-1)
    un = jnp.sum(delta * n_w, axis=-1)
    us = jnp.sum(delta * t_w, axis=-1)
    f_comp = -kn_c * un
    f_shear = ks_c * us
    fail = (f_comp < -t_c) | (jnp.abs(f_shear) > c_c + jnp.maximum(f_comp, 0.0) * tan_phi)
    intact_new = intact & ~jnp.any(fail, axis=-1)
    w = intact_new[:, None, None].astype(pos.dtype)
    f_spring = kn_c * un[..., None] * n_w + f_shear[..., None] * t_w         # (J,2,2)
    if vel is not None:
        def point_vel(k, r):
            return vel[k][:, None] + omega[k][:, None, None] * jnp.stack([-r[..., 1], r[..., 0]],
                                                                         -1)
        f_spring = f_spring + cj * (point_vel(b, rb) - point_vel(a, ra))
    f_a = w * f_spring
    force = (jax.ops.segment_sum(f_a.sum(1), a, num_segments=n_frag)
             - jax.ops.segment_sum(f_a.sum(1), b, num_segments=n_frag))
    torque = (jax.ops.segment_sum(cross2(ra, f_a).sum(1), a, num_segments=n_frag)
              + jax.ops.segment_sum(cross2(rb, -f_a).sum(1), b, num_segments=n_frag))
    return force, torque, intact_new



def _pair_contact(xa, za, ca, sa, vxa, vza, wa, xb, zb, cb, sb, vxb, vzb, wb, ok, fs_a, h,
                  kn_c, ks_c, tan_phi, dt, width, smooth: bool, cn=0.0, margin=0.05,
                  slip_tol=0.0):
    """Contact of two squares a and b of half side h, for P pairs at once.

    Reference face (separating-axis rule): of the four face axes u (a's two,
    b's two) the one of largest |d.u|, d the vector between the centres, is
    the axis of least overlap (the overlap on every axis is h + E - |d.u|,
    with E = h (|cos(theta)| + |sin(theta)|) the same on all four for two
    equal squares at relative rotation theta). Its square is the reference
    square R, its face towards the other square I the reference face (outward
    normal n, tangent t). I's incident edge is its face whose outward normal
    is most anti-parallel to n; the edge is clipped to the reference face's
    extent |tau| <= h along t, and each clipped end point p below the face by
    delta = h - (p - x_R).n > 0 carries F_n = kn l_c delta - c_n v_n along n
    (v: velocity of I's material point at p relative to R's); R takes the
    reaction at the same point.

    Friction: UDEC's incremental shear spring (eq. 2 of the module docstring),
    one per pair: F_s <- F_s - k_s v_t dt, clipped to |F_s| <= tan(phi)
    sum max(F_n, 0), with v_t the relative tangential speed at the points
    weighted by their normal forces (equal weights when no point carries a
    compressive force), and F_s shared among the points with the same
    weights. The spring holds a static load (a fragment resting on another on
    a slope below phi stays put) and slides at the Coulomb limit. Our choices:
    one spring per pair, not per point (the points' identity changes when the
    reference face changes; the pair's force does not), of fixed stiffness
    k_s = 2 ks l_c (a face contact's two points), carried between steps as
    the world-frame force on a and projected on the current tangent (a
    rotation of the contact only shortens it), and reset to zero when the
    pair stops touching (its energy is then lost, as at a wall corner).

    Sources: the least-overlap axis is the separating-axis test of oriented
    boxes (Gottschalk, Lin & Manocha 1996, OBBTree); the reference face,
    incident edge and clipping are the contact manifold of box-box collision
    in rigid-body engines (Catto, Box2D, GDC 2007 talk "Contact Manifolds";
    recalled, not checked against the text). Our choices: penalty springs at
    the clipped points (the UDEC law of the module docstring) in place of the
    engines' impulses, and no bias between nearly equal axes. Why this rule:
    the penetration of the least-overlap axis is continuous in the poses (the
    minimum of continuous overlaps), and at a switch between a's and b's axes
    the two contact sets are mirror images, so the spring energy does not
    jump when the reference face changes; clipping moves a contact point
    continuously to the face's end where a corner test would drop it.

    Inputs are (P,) component arrays of the two squares of each pair (centre,
    cos/sin of rotation, velocity, spin); ``ok`` (P,) bool marks live pairs;
    ``fs_a`` (P,2) the shear spring's force on a from the last step (world
    frame, N/m); ks_c the shear spring of one point, N/m per m; dt the step,
    s; ``slip_tol`` as in ``wall_forces``.

    Returns:
        fx, fz (P,) force on a (b takes -(fx, fz)), ta, tb (P,) torques on a
        and b, touching (P,), near_limit (P,) and slipped (P,) bool, fs_a (P,2)
        the new shear force on a, energy (P,) normal spring energy kn l_c
        max(delta, 0)^2 / 2 summed over the points, J/m (linear law; for
        diagnostics, dropped by XLA in the step).
    """
    dx, dz = xa - xb, za - zb
    proj = jnp.stack([jnp.abs(cb * dx + sb * dz), jnp.abs(-sb * dx + cb * dz),
                      jnp.abs(ca * dx + sa * dz), jnp.abs(-sa * dx + ca * dz)])
    k = jnp.argmax(proj, axis=0)                # ties: b before a, x before z
    ref_b, use_x = k < 2, (k % 2) == 0

    def pick(b_val, a_val):                     # (reference, incident)
        return jnp.where(ref_b, b_val, a_val), jnp.where(ref_b, a_val, b_val)

    (xr, xi), (zr, zi) = pick(xb, xa), pick(zb, za)
    (cr, ci), (sr, si) = pick(cb, ca), pick(sb, sa)
    (vxr, vxi), (vzr, vzi), (wr, wi) = pick(vxb, vxa), pick(vzb, vza), pick(wb, wa)
    ux, uz = jnp.where(use_x, cr, -sr), jnp.where(use_x, sr, cr)
    ex, ez = xi - xr, zi - zr
    sgn = jnp.where(ex * ux + ez * uz >= 0.0, 1.0, -1.0)
    nx, nz = sgn * ux, sgn * uz                 # reference face's outward normal
    tx, tz = -nz, nx
    # I's incident edge: its face whose outward normal is most anti-parallel to n
    nix, niz = ci * nx + si * nz, -si * nx + ci * nz
    i_x = jnp.abs(nix) >= jnp.abs(niz)
    side = -jnp.where(i_x, jnp.sign(nix), jnp.sign(niz)) * h
    other = jnp.stack([-h + 0.0 * side, h + 0.0 * side])                # (2,P)
    lx, lz = jnp.where(i_x, side, other), jnp.where(i_x, other, side)
    vx_, vz_ = ex + ci * lx - si * lz, ez + si * lx + ci * lz           # from R's centre
    tau, nu = vx_ * tx + vz_ * tz, vx_ * nx + vz_ * nz                  # (2,P)
    # the edge runs within 45 deg of t, so |tau[1] - tau[0]| >= sqrt(2) h
    tau_c = jnp.clip(tau, -h, h)
    nu_c = nu[0] + (tau_c - tau[0]) / (tau[1] - tau[0]) * (nu[1] - nu[0])
    delta = h - nu_c
    reach = (jnp.max(tau, axis=0) >= -h) & (jnp.min(tau, axis=0) <= h)
    touch = ok & reach & (delta > (-20.0 * width if smooth else 0.0))
    px, pz = tau_c * tx + nu_c * nx, tau_c * tz + nu_c * nz             # from R's centre
    rix, riz = px - ex, pz - ez                                         # from I's centre
    vrx = (vxi - wi * riz) - (vxr - wr * pz)
    vrz = (vzi + wi * rix) - (vzr + wr * px)
    vn, vt = vrx * nx + vrz * nz, vrx * tx + vrz * tz                   # vn < 0: closing
    fn = jnp.where(touch, penetration_force(delta, kn_c, width, smooth) - cn * vn, 0.0)
    # one shear spring per pair, shared among the points by their normal forces
    press = jnp.where(touch, jnp.maximum(fn, 0.0), 0.0)                 # (2,P)
    total = jnp.sum(press, axis=0)
    n_touch = jnp.sum(touch, axis=0)
    w = jnp.where(total > 0.0, press / jnp.where(total > 0.0, total, 1.0),
                  touch / jnp.maximum(n_touch, 1))
    any_touch = n_touch > 0
    on_i = jnp.where(ref_b, 1.0, -1.0)          # I is a when b is the reference
    fs_old = on_i * (fs_a[:, 0] * tx + fs_a[:, 1] * tz)
    fs_trial = jnp.where(any_touch, fs_old - pair_shear_stiffness(ks_c) * jnp.sum(w * vt, axis=0)
                         * dt, 0.0)
    f_lim = tan_phi * total
    fs = _clip_shear(fs_trial, f_lim, smooth)
    slipped = any_touch & (jnp.abs(fs_trial) - f_lim > slip_tol)
    near = any_touch & (jnp.abs(fs) > (1.0 - margin) * f_lim)
    ft = w * fs                                                         # (2,P) on I
    fx, fz = fn * nx + ft * tx, fn * nz + ft * tz                       # on I
    # materialise the per-point results once (XLA's CPU fusion otherwise
    # recomputes the chain inside each reduction below)
    out = lax.optimization_barrier(jnp.stack([fx, fz, rix * fz - riz * fx, pz * fx - px * fz]))
    fix, fiz, ti, tr = (ordered_sum(out[j], 0) for j in range(4))
    energy = jnp.sum(jnp.where(touch, 0.5 * kn_c * jnp.maximum(delta, 0.0) ** 2, 0.0), axis=0)
    fs_a_new = jnp.stack([on_i * fs * tx, on_i * fs * tz], -1)
    return (on_i * fix, on_i * fiz, jnp.where(ref_b, ti, tr), jnp.where(ref_b, tr, ti),
            any_touch, near, slipped, fs_a_new, energy)


def _pair_args(pos, cs, sn, vel, omega, pi, pj):
    return (pos[pi, 0], pos[pi, 1], cs[pi], sn[pi], vel[pi, 0], vel[pi, 1], omega[pi],
            pos[pj, 0], pos[pj, 1], cs[pj], sn[pj], vel[pj, 0], vel[pj, 1], omega[pj])


def _gather(n_frag, pi, pj, fx, fz, ti, tj, flags, weight=1.0):
    """Scatter pair forces to fragments: (fx, fz) and ti on i, -(fx, fz) and tj
    on j; ``flags`` (F,P) bool per pair become (F,N): any pair of the fragment."""
    idx = jnp.concatenate([pi, pj])
    rows = weight * jnp.stack([jnp.concatenate([fx, -fx]), jnp.concatenate([fz, -fz]),
                               jnp.concatenate([ti, tj])], -1)
    acc = jax.ops.segment_sum(rows, idx, num_segments=n_frag)
    f = jnp.concatenate([flags, flags], axis=1).T.astype(jnp.int32)
    per_frag = jax.ops.segment_max(f, idx, num_segments=n_frag) > 0
    return acc[:, :2], acc[:, 2], per_frag.T


class PairContacts(NamedTuple):
    """Fragment-fragment contacts of one step.

    force (N,2) N/m and torque (N,) N m/m on every fragment; fs (N,N,2) the
    pairs' shear springs, N/m (entry [i, j], i < j: world-frame force on i;
    zero for pairs not touching); touching, near_limit, slipped (N,) bool:
    any pair contact of the fragment touches / has |F_s| > (1 - margin)
    tan(phi) sum max(F_n, 0) / slid this step (as ``WallContact``).
    """

    force: jax.Array
    torque: jax.Array
    fs: jax.Array
    touching: jax.Array
    near_limit: jax.Array
    slipped: jax.Array


def pair_shear_stiffness(ks_c):
    """The shear spring of one fragment pair, 2 ks l_c (a face contact's two
    points; our choice, see ``_pair_contact``), N/m per m."""
    return 2.0 * ks_c


def _slots(pi, pj):
    """Each listed pair's entry [lo, hi] (lo < hi) of the springs' table, and
    the sign that turns the force stored there (on lo) into the force on pi."""
    return (jnp.minimum(pi, pj), jnp.maximum(pi, pj),
            jnp.where(pi < pj, 1.0, -1.0)[:, None])


def _springs_table(n_frag, slots, fs_i, live):
    """The (i < j) table of the listed pairs' new shear forces (zero elsewhere)."""
    lo, hi, sign = slots
    val = jnp.where(live[:, None], sign * fs_i, 0.0)
    return jnp.zeros((n_frag, n_frag, 2), fs_i.dtype).at[lo, hi].set(val)


def pair_list_forces(pos, cs, sn, vel, omega, pi, pj, ok, fs_pair, h, kn_c, ks_c, tan_phi, dt,
                     width, smooth: bool, cn=0.0, margin=0.05, slip_tol=0.0) -> PairContacts:
    """Fragment-fragment contacts over a list of unordered pairs (i < j), each
    by the reference-face rule of ``_pair_contact``. Every pair force enters i
    and j with opposite signs, so linear momentum is conserved exactly
    whatever the list holds.

    Args:
        pos (N,2), cs/sn (N,), vel (N,2), omega (N,); pi, pj (P,) int pair
        indices; ok (P,) bool (pair active: both fragments present, no intact
        joint between them); fs_pair (N,N,2) the shear springs of the last
        step (``PairContacts.fs``); kn_c, ks_c: springs of one point, N/m per
        m; dt: step, s; cn: dashpot coefficient, N s/m per m (P,) or scalar;
        margin: Coulomb-cone margin; slip_tol: as in ``wall_forces``.

    Returns:
        ``PairContacts``.
    """
    n_frag = pos.shape[0]
    slots = _slots(pi, pj)
    fx, fz, ti, tj, touch, near, slip, fs_i, _ = _pair_contact(
        *_pair_args(pos, cs, sn, vel, omega, pi, pj), ok, slots[2] * fs_pair[slots[:2]], h,
        kn_c, ks_c, tan_phi, dt, width, smooth, cn, margin, slip_tol)
    force, torque, flags = _gather(n_frag, pi, pj, fx, fz, ti, tj,
                                   jnp.stack([touch, near, slip]))
    return PairContacts(force, torque, _springs_table(n_frag, slots, fs_i, touch), *flags)


def pair_forces(pos, cs, sn, vel, omega, nbr, bonded, active, fs_pair, h, kn_c, ks_c, tan_phi,
                dt, width, smooth: bool, cn=0.0, margin=0.05, slip_tol=0.0) -> PairContacts:
    """The contacts of ``pair_list_forces`` over K-nearest lists: fragment i
    meets the K fragments ``nbr[i]`` (the earlier pair search, kept for
    benchmarks). A pair listed from both sides enters each time with weight
    1/2, so every pair counts once (both entries read and write the same
    shear spring).

    Args:
        as ``pair_list_forces``, with nbr (N,K) int, bonded (N,N) bool (intact
        joint: no contact), active (N,) bool and cn (N,K) or scalar.
    """
    n_frag, k_nb = nbr.shape
    pi = jnp.repeat(jnp.arange(n_frag), k_nb)
    pj = nbr.reshape(-1)
    mutual = jnp.any(nbr[pj] == pi[:, None], axis=-1)
    ok = ~bonded[pi, pj] & active[pi] & active[pj] & (pi != pj)
    slots = _slots(pi, pj)
    fx, fz, ti, tj, touch, near, slip, fs_i, _ = _pair_contact(
        *_pair_args(pos, cs, sn, vel, omega, pi, pj), ok, slots[2] * fs_pair[slots[:2]], h,
        kn_c, ks_c, tan_phi, dt, width, smooth, jnp.broadcast_to(cn, nbr.shape).reshape(-1),
        margin, slip_tol)
    weight = jnp.where(mutual, 0.5, 1.0)
    force, torque, flags = _gather(n_frag, pi, pj, fx, fz, ti, tj,
                                   jnp.stack([touch, near, slip]),
                                   jnp.concatenate([weight, weight])[:, None])
    return PairContacts(force, torque, _springs_table(n_frag, slots, fs_i, touch), *flags)


def pair_list_energy(pos, cs, sn, pi, pj, ok, h, kn_c) -> jax.Array:
    """Elastic energy of the fragment-fragment normal springs, J/m (scalar):
    kn l_c delta^2 / 2 summed over the contact points of the pairs (pi, pj)
    where ``ok``, as ``pair_list_forces`` finds them (linear law). The shear
    springs' energy is |F_s|^2 / (2 pair_shear_stiffness) per pair
    (``PairContacts.fs``)."""
    zero = jnp.zeros_like(pos[:, 0])
    args = _pair_args(pos, cs, sn, jnp.stack([zero, zero], -1), zero, pi, pj)
    fs0 = jnp.zeros((pi.shape[0], 2), pos.dtype)
    return jnp.sum(_pair_contact(*args, ok, fs0, h, kn_c, 1.0, 0.0, 0.0, 1.0, False)[-1])
