"""Contact laws: block-wall corners, fragment-fragment corners, bonded joints.

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
corner and at a joint point (reduced mass m/2 of two equal fragments, two
points per face). A single-corner impact has another true effective mass,
1 / (1/m + (r x n)^2 / I), from 0.4 m (lever arm along the wall) to m (corner
straight down), so its restitution differs from the target: measured 0.61
for target 0.5 with the corner straight down (tests/test_dem.py). The dashpot
force is not clipped at zero (see ``contact_damping_ratio``); the Coulomb
limit uses max(F_n, 0).

Each contact function also reports, per fragment, whether it touches
something and whether one of its contacts is near the Coulomb limit (the rest
test in ``_integrate``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from solvers.dem._geometry import Joints, cross2, rotate
from solvers.dem._sums import ordered_sum

__all__ = ["WallContact", "joint_forces", "pair_forces", "pair_list_forces",
           "penetration_force", "wall_forces"]

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


def pair_forces(pos, cs, sn, vel, omega, r_corner, nbr, bonded, active, h, kn_c,
                tan_phi, eps, width, smooth: bool, cn=0.0, margin=0.05, info: bool = False):
    """Corner-to-face contacts between fragments (squares of half side h).

    Each fragment i tests its 4 corners against the K fragments ``nbr[i]``.
    j's face that faces i's centre gives the normal n; a corner of i within
    that face's extent and behind it by delta > 0 gets F_n = kn l_c delta.
    Friction is regularised Coulomb, F_t = -tan(phi) F_n tanh(v_t / eps)
    (no shear-spring history for these transient contacts: a documented
    simplification). The reaction -F acts on j at the same point, so linear
    momentum is conserved exactly. With a dashpot, F_n = kn l_c delta -
    cn v_n (v_n: relative normal velocity, < 0 when approaching).

    Args:
        pos (N,2), cs/sn (N,) cos/sin of rotation, vel (N,2), omega (N,),
        r_corner (N,4,2) world lever arms of the corners, nbr (N,K) int,
        bonded (N,N) bool (intact joint: no corner contact), active (N,) bool,
        cn: dashpot coefficient, N s/m per m; margin: Coulomb-cone margin.
        info: also return the per-fragment contact flags.

    Returns:
        force (N,2) and torque (N,) on every fragment; with ``info`` also
        touching (N,) and near_limit (N,) bool (any contact of the fragment
        with |F_t| > (1 - margin) tan(phi) max(F_n, 0)).
    """
    n_frag, k_nb = nbr.shape
    p = pos[:, None, None, :] + r_corner[:, None, :, :]            # (N,1,4,2)
    cj, sj = cs[nbr][:, :, None], sn[nbr][:, :, None]                # (N,K,1)
    d = p - pos[nbr][:, :, None, :]                                  # (N,K,4,2)
    q = rotate(d, cj, -sj)                                           # into j's frame
    # The face of j that is pushed through is the one facing i's centre
    # (chosen per pair, not per corner): a per-corner "nearest face" rule fails
    # for aligned face-to-face overlaps, whose corners sit on j's corners.
    c_rel = rotate(pos[:, None, :] - pos[nbr], cj[..., 0], -sj[..., 0])      # (N,K,2)
    use_x = (jnp.abs(c_rel[..., 0]) >= jnp.abs(c_rel[..., 1]))[..., None]    # (N,K,1)
    ax, az = jnp.abs(q[..., 0]), jnp.abs(q[..., 1])
    delta = jnp.where(use_x, h - ax, h - az)
    within = jnp.where(use_x, az, ax) <= h
    sgn = jnp.where(use_x, jnp.sign(c_rel[..., 0:1]), jnp.sign(c_rel[..., 1:2]))
    n_loc = jnp.stack([jnp.where(use_x, sgn, 0.0), jnp.where(use_x, 0.0, sgn)], axis=-1)
    n_w = rotate(n_loc, cj, sj)
    ok = (~bonded[jnp.arange(n_frag)[:, None], nbr] & active[:, None] & active[nbr]
          & (nbr != jnp.arange(n_frag)[:, None]))[:, :, None]
    ok = ok & within & (delta > (-20.0 * width if smooth else 0.0))
    # relative velocity of the corner w.r.t. the material point of j
    v_i = vel[:, None, None, :] + omega[:, None, None, None] * jnp.stack(
        [-r_corner[..., 1], r_corner[..., 0]], axis=-1)[:, None]
    v_j = vel[nbr][:, :, None, :] + omega[nbr][:, :, None, None] * jnp.stack(
        [-d[..., 1], d[..., 0]], axis=-1)
    vn = jnp.sum((v_i - v_j) * n_w, axis=-1)
    fn = jnp.where(ok, penetration_force(delta, kn_c, width, smooth) - cn * vn, 0.0)
    t_w = jnp.stack([-n_w[..., 1], n_w[..., 0]], axis=-1)
    vt = jnp.sum((v_i - v_j) * t_w, axis=-1)
    ft = -tan_phi * jnp.maximum(fn, 0.0) * jnp.tanh(vt / eps)
    f = fn[..., None] * n_w + ft[..., None] * t_w                     # on i, (N,K,4,2)
    f_i = ordered_sum(f, (1, 2))
    t_i = ordered_sum(cross2(r_corner[:, None], f), (1, 2))
    f_j = jax.ops.segment_sum(-ordered_sum(f, 2).reshape(-1, 2), nbr.reshape(-1),
                              num_segments=n_frag)
    t_j = jax.ops.segment_sum(ordered_sum(cross2(d, -f), 2).reshape(-1), nbr.reshape(-1),
                              num_segments=n_frag)
    if not info:
        return f_i + f_j, t_i + t_j
    near = ok & (jnp.abs(ft) > (1.0 - margin) * tan_phi * jnp.maximum(fn, 0.0))
    flags = jnp.stack([jnp.any(ok, axis=(2,)), jnp.any(near, axis=(2,))], -1)     # (N,K,2)
    mine = jnp.any(flags, axis=1)
    theirs = jax.ops.segment_max(flags.reshape(-1, 2).astype(jnp.int32), nbr.reshape(-1),
                                 num_segments=n_frag) > 0
    both = mine | theirs
    return f_i + f_j, t_i + t_j, both[:, 0], both[:, 1]


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


def _corners_into(xa, za, ca, sa, vxa, vza, wa, xb, zb, cb, sb, vxb, vzb, wb, ok, h,
                  kn_c, tan_phi, eps, width, smooth: bool, all_corners: bool = False,
                  cn=0.0, margin=0.05):
    """Corners of square a pushed into square b (one direction of a pair list).

    Inputs are (P,) component arrays of the two squares of each pair. b's face
    that faces a's centre gives the normal n (as in ``pair_forces``). Only the
    two corners of a's edge that faces b (the edge whose outward normal is
    closest to -n) are tested: the other two lie at or behind a's centre
    along n and reach into b only through overlaps deeper than ~0.45 h
    (measured over random poses; tests/test_dem.py checks equality below
    0.4 h), far beyond the penetrations of these stiffnesses (~0.1 h at
    15 m/s with stiffness_scale 0.01). ``all_corners`` tests all four.
    Arrays carry the corner axis first, (C, P), so loops run over pairs.

    Returns:
        fx, fz (P,) total force on a, ta (P,) torque on a, tb (P,) torque on b
        (the force on b is -(fx, fz)); touching (P,) and near_limit (P,) as
        0/1 floats (any corner in contact / with |F_t| > (1 - margin)
        tan(phi) max(F_n, 0)).
    """
    dcx, dcz = xa - xb, za - zb
    crx = cb * dcx + sb * dcz                   # a's centre in b's frame
    crz = -sb * dcx + cb * dcz
    use_x = jnp.abs(crx) >= jnp.abs(crz)
    sgn = jnp.where(use_x, jnp.sign(crx), jnp.sign(crz))
    nlx = jnp.where(use_x, sgn, 0.0)            # b's face normal, b's frame
    nlz = jnp.where(use_x, 0.0, sgn)
    nx = cb * nlx - sb * nlz                    # world
    nz = sb * nlx + cb * nlz
    if all_corners:
        ux = jnp.asarray([-1.0, 1.0, 1.0, -1.0])[:, None] * h + 0.0 * xa   # (4,P)
        uz = jnp.asarray([-1.0, -1.0, 1.0, 1.0])[:, None] * h + 0.0 * xa
    else:
        nax = ca * nx + sa * nz                 # n in a's frame
        naz = -sa * nx + ca * nz
        a_x = jnp.abs(nax) >= jnp.abs(naz)      # a's edge facing b is an x-face
        side = -jnp.where(a_x, jnp.sign(nax), jnp.sign(naz)) * h
        other = jnp.stack([-h + 0.0 * side, h + 0.0 * side])            # (2,P)
        ux = jnp.where(a_x, side, other)
        uz = jnp.where(a_x, other, side)
    # corner axis first, (C,P): the loops then run over pairs, contiguous
    rx = ca * ux - sa * uz                      # lever arms of a's corners
    rz = sa * ux + ca * uz
    dx, dz = dcx + rx, dcz + rz                 # corners relative to b's centre
    qx = cb * dx + sb * dz                      # in b's frame
    qz = -sb * dx + cb * dz
    ax, az = jnp.abs(qx), jnp.abs(qz)
    delta = h - jnp.where(use_x, ax, az)
    within = jnp.where(use_x, az, ax) <= h
    touch = ok & within & (delta > (-20.0 * width if smooth else 0.0))
    # relative velocity of a's corner w.r.t. the material point of b
    vrx = (vxa - vxb) - wa * rz + wb * dz
    vrz = (vza - vzb) + wa * rx - wb * dx
    vn = vrx * nx + vrz * nz                    # < 0 when approaching
    fn = jnp.where(touch, penetration_force(delta, kn_c, width, smooth) - cn * vn, 0.0)
    vt = -vrx * nz + vrz * nx
    f_lim = tan_phi * jnp.maximum(fn, 0.0)
    ft = -f_lim * jnp.tanh(vt / eps)
    fx = fn * nx - ft * nz
    fz = fn * nz + ft * nx
    near = touch & (jnp.abs(ft) > (1.0 - margin) * f_lim)
    # materialise the per-corner results once: without the barrier XLA's CPU
    # fusion recomputes the whole per-corner chain inside each of the four
    # reductions below (measured ~3x slower)
    out = lax.optimization_barrier(jnp.stack([fx, fz, rx * fz - rz * fx, dz * fx - dx * fz,
                                              touch.astype(fx.dtype), near.astype(fx.dtype)]))
    # elastic energy of the normal springs (J/m; linear law only), for diagnostics:
    # unused by the step, so XLA drops it there
    energy = jnp.sum(jnp.where(touch, 0.5 * kn_c * jnp.maximum(delta, 0.0) ** 2, 0.0), axis=0)
    return (*(ordered_sum(out[k], 0) for k in range(4)),
            *(jnp.max(out[k], axis=0) for k in (4, 5)), energy)


def pair_list_forces(pos, cs, sn, vel, omega, pi, pj, ok, h, kn_c, tan_phi, eps, width,
                     smooth: bool, all_corners: bool = False, cn=0.0, margin=0.05,
                     info: bool = False):
    """Fragment-fragment contacts over a list of unordered pairs (i < j).

    For each pair both directions are tested (corners of i against the face
    of j that faces i's centre, and corners of j against i), with the law of
    ``pair_forces``. Every pair force enters i and j with opposite signs, so
    linear momentum is conserved exactly whatever the list holds. Compared
    with the K-nearest list of ``pair_forces`` a pair is never seen from one
    side only, and the forces are gathered back with one scatter.

    Args:
        pos (N,2), cs/sn (N,), vel (N,2), omega (N,); pi, pj (P,) int pair
        indices; ok (P,) bool (pair active: both fragments present, no intact
        joint between them); cn: dashpot coefficient, N s/m per m; margin:
        Coulomb-cone margin; info: also return the contact flags.

    Returns:
        force (N,2) and torque (N,) on every fragment; with ``info`` also
        touching (N,) and near_limit (N,) bool, as in ``pair_forces``.
    """
    n_frag = pos.shape[0]
    xi, zi, xj, zj = pos[pi, 0], pos[pi, 1], pos[pj, 0], pos[pj, 1]
    ci, si, cj, sj = cs[pi], sn[pi], cs[pj], sn[pj]
    vxi, vzi, vxj, vzj = vel[pi, 0], vel[pi, 1], vel[pj, 0], vel[pj, 1]
    wi, wj = omega[pi], omega[pj]
    args = (h, kn_c, tan_phi, eps, width, smooth, all_corners, cn, margin)
    fx0, fz0, ti0, tj0, to0, nl0, _ = _corners_into(xi, zi, ci, si, vxi, vzi, wi,
                                                    xj, zj, cj, sj, vxj, vzj, wj, ok, *args)
    fx1, fz1, tj1, ti1, to1, nl1, _ = _corners_into(xj, zj, cj, sj, vxj, vzj, wj,
                                                    xi, zi, ci, si, vxi, vzi, wi, ok, *args)
    fx, fz = fx0 - fx1, fz0 - fz1                       # on i; -(fx, fz) on j
    idx = jnp.concatenate([pi, pj])
    rows = jnp.concatenate([jnp.stack([fx, fz, ti0 + ti1], -1),
                            jnp.stack([-fx, -fz, tj0 + tj1], -1)])
    acc = jax.ops.segment_sum(rows, idx, num_segments=n_frag)
    if not info:
        return acc[:, :2], acc[:, 2]
    flags = jnp.stack([jnp.maximum(to0, to1), jnp.maximum(nl0, nl1)], -1)
    flags = jax.ops.segment_max(jnp.concatenate([flags, flags]), idx, num_segments=n_frag)
    return acc[:, :2], acc[:, 2], flags[:, 0] > 0.5, flags[:, 1] > 0.5


def pair_list_energy(pos, cs, sn, pi, pj, ok, h, kn_c) -> jax.Array:
    """Elastic energy of the fragment-fragment normal springs, J/m (scalar):
    sum of kn l_c delta^2 / 2 over the corners of the pairs (pi, pj) where ``ok``
    (both directions, as ``pair_list_forces`` tests them; linear law)."""
    zero = jnp.zeros_like(pos[pi, 0])
    args = (ok, h, kn_c, 0.0, 1.0, 1.0, False)
    xi, zi, xj, zj = pos[pi, 0], pos[pi, 1], pos[pj, 0], pos[pj, 1]
    ci, si, cj, sj = cs[pi], sn[pi], cs[pj], sn[pj]
    e0 = _corners_into(xi, zi, ci, si, zero, zero, zero, xj, zj, cj, sj, zero, zero, zero,
                       *args)[-1]
    e1 = _corners_into(xj, zj, cj, sj, zero, zero, zero, xi, zi, ci, si, zero, zero, zero,
                       *args)[-1]
    return jnp.sum(e0 + e1)
