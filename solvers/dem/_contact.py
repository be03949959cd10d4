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
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from solvers.dem._geometry import Joints, cross2, rotate

__all__ = ["joint_forces", "pair_forces", "pair_list_forces", "penetration_force",
           "wall_forces"]

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


def wall_forces(p, vp, fs_old, seg, kn_c, ks_c, dt, width, smooth: bool):
    """Corner-to-wall contact forces.

    Args:
        p: (..., 2) corner positions, m. vp: (..., 2) corner velocities, m/s.
        fs_old: (...) shear force carried from the last step, N/m, along the
            segment tangent.
        seg: (xa, za, tx, tz, tan_phi) of the segment below each corner.
        kn_c, ks_c: contact springs kn l_c, ks l_c, N/m per m.
        dt: time step, s. width: softplus width, m.

    Returns:
        force (..., 2) on the corner, N/m; new shear force (...); penetration (...) m.
    """
    xa, za, tx, tz, tan_phi = seg
    nx, nz = -tz, tx  # upward unit normal
    delta = -(nx * (p[..., 0] - xa) + nz * (p[..., 1] - za))
    fn = penetration_force(delta, kn_c, width, smooth)
    vt = vp[..., 0] * tx + vp[..., 1] * tz
    touching = (fn > 0.0) if smooth else (delta > 0.0)
    fs_trial = jnp.where(touching, fs_old - ks_c * vt * dt, 0.0)
    fs = _clip_shear(fs_trial, fn * tan_phi, smooth)
    force = jnp.stack([fn * nx + fs * tx, fn * nz + fs * tz], axis=-1)
    return force, fs, delta


def pair_forces(pos, cs, sn, vel, omega, r_corner, nbr, bonded, active, h, kn_c,
                tan_phi, eps, width, smooth: bool):
    """Corner-to-face contacts between fragments (squares of half side h).

    Each fragment i tests its 4 corners against the K fragments ``nbr[i]``.
    j's face that faces i's centre gives the normal n; a corner of i within
    that face's extent and behind it by delta > 0 gets F_n = kn l_c delta.
    Friction is regularised Coulomb, F_t = -tan(phi) F_n tanh(v_t / eps)
    (no shear-spring history for these transient contacts: a documented
    simplification). The reaction -F acts on j at the same point, so linear
    momentum is conserved exactly.

    Args:
        pos (N,2), cs/sn (N,) cos/sin of rotation, vel (N,2), omega (N,),
        r_corner (N,4,2) world lever arms of the corners, nbr (N,K) int,
        bonded (N,N) bool (intact joint: no corner contact), active (N,) bool.

    Returns:
        force (N,2) and torque (N,) on every fragment.
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
    fn = jnp.where(ok, penetration_force(delta, kn_c, width, smooth), 0.0)
    # relative velocity of the corner w.r.t. the material point of j
    v_i = vel[:, None, None, :] + omega[:, None, None, None] * jnp.stack(
        [-r_corner[..., 1], r_corner[..., 0]], axis=-1)[:, None]
    v_j = vel[nbr][:, :, None, :] + omega[nbr][:, :, None, None] * jnp.stack(
        [-d[..., 1], d[..., 0]], axis=-1)
    t_w = jnp.stack([-n_w[..., 1], n_w[..., 0]], axis=-1)
    vt = jnp.sum((v_i - v_j) * t_w, axis=-1)
    ft = -tan_phi * fn * jnp.tanh(vt / eps)
    f = fn[..., None] * n_w + ft[..., None] * t_w                     # on i, (N,K,4,2)
    f_i = jnp.sum(f, axis=(1, 2))
    t_i = jnp.sum(cross2(r_corner[:, None], f), axis=(1, 2))
    f_j = jax.ops.segment_sum(-jnp.sum(f, axis=2).reshape(-1, 2), nbr.reshape(-1),
                              num_segments=n_frag)
    t_j = jax.ops.segment_sum(cross2(d, -f).sum(axis=2).reshape(-1), nbr.reshape(-1),
                              num_segments=n_frag)
    return f_i + f_j, t_i + t_j


def joint_forces(pos, cs, sn, joints: Joints, intact, h, kn_c, ks_c, c_c, t_c, tan_phi):
    """Bonded joints: linear springs at the two end points of each shared face.

    With Delta = x_b(point) - x_a(point) (world) and the joint normal n rotating
    with fragment a: F_on_a = kn l_c (Delta.n) n + ks l_c (Delta.t) t, F_on_b =
    -F_on_a (for an elastic bond the incremental form of eq. 1 sums to this).
    A joint breaks for good (c = t = 0 afterwards) when at either point the
    compressive normal force F_c = -kn l_c Delta.n falls below -t l_c or the
    shear exceeds c l_c + max(F_c, 0) tan(phi) (eq. 2).

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
    f_a = w * (kn_c * un[..., None] * n_w + f_shear[..., None] * t_w)        # (J,2,2)
    force = (jax.ops.segment_sum(f_a.sum(1), a, num_segments=n_frag)
             - jax.ops.segment_sum(f_a.sum(1), b, num_segments=n_frag))
    torque = (jax.ops.segment_sum(cross2(ra, f_a).sum(1), a, num_segments=n_frag)
              + jax.ops.segment_sum(cross2(rb, -f_a).sum(1), b, num_segments=n_frag))
    return force, torque, intact_new


def _corners_into(xa, za, ca, sa, vxa, vza, wa, xb, zb, cb, sb, vxb, vzb, wb, ok, h,
                  kn_c, tan_phi, eps, width, smooth: bool, all_corners: bool = False):
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
        (the force on b is -(fx, fz)).
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
    fn = jnp.where(touch, penetration_force(delta, kn_c, width, smooth), 0.0)
    # relative velocity of a's corner w.r.t. the material point of b
    vrx = (vxa - vxb) - wa * rz + wb * dz
    vrz = (vza - vzb) + wa * rx - wb * dx
    vt = -vrx * nz + vrz * nx
    ft = -tan_phi * fn * jnp.tanh(vt / eps)
    fx = fn * nx - ft * nz
    fz = fn * nz + ft * nx
    # materialise the per-corner results once: without the barrier XLA's CPU
    # fusion recomputes the whole per-corner chain inside each of the four
    # reductions below (measured ~3x slower)
    out = lax.optimization_barrier(jnp.stack([fx, fz, rx * fz - rz * fx, dz * fx - dx * fz]))
    return tuple(jnp.sum(out[k], axis=0) for k in range(4))


def pair_list_forces(pos, cs, sn, vel, omega, pi, pj, ok, h, kn_c, tan_phi, eps, width,
                     smooth: bool, all_corners: bool = False):
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
        joint between them).

    Returns:
        force (N,2) and torque (N,) on every fragment.
    """
    n_frag = pos.shape[0]
    xi, zi, xj, zj = pos[pi, 0], pos[pi, 1], pos[pj, 0], pos[pj, 1]
    ci, si, cj, sj = cs[pi], sn[pi], cs[pj], sn[pj]
    vxi, vzi, vxj, vzj = vel[pi, 0], vel[pi, 1], vel[pj, 0], vel[pj, 1]
    wi, wj = omega[pi], omega[pj]
    args = (h, kn_c, tan_phi, eps, width, smooth, all_corners)
    fx0, fz0, ti0, tj0 = _corners_into(xi, zi, ci, si, vxi, vzi, wi,
                                       xj, zj, cj, sj, vxj, vzj, wj, ok, *args)
    fx1, fz1, tj1, ti1 = _corners_into(xj, zj, cj, sj, vxj, vzj, wj,
                                       xi, zi, ci, si, vxi, vzi, wi, ok, *args)
    fx, fz = fx0 - fx1, fz0 - fz1                       # on i; -(fx, fz) on j
    rows = jnp.concatenate([jnp.stack([fx, fz, ti0 + ti1], -1),
                            jnp.stack([-fx, -fz, tj0 + tj1], -1)])
    acc = jax.ops.segment_sum(rows, jnp.concatenate([pi, pj]), num_segments=n_frag)
    return acc[:, :2], acc[:, 2]
