"""Geometry of square fragments and of the slope polyline.

A block of side L is split into n x n square fragments of side s = L/n
(n = 1: a single block). Fragment k = a + n*b sits at local offset
((a + 1/2) s - L/2, (b + 1/2) s - L/2) from the block centre. Neighbouring
fragments share a joint (a face) carried by two points, its end points.

The slope is a height field z = g(x) made of segments; each corner tests only
the segment below its own abscissa (one contact test per corner, however long
the profile), which is the "local segment search" lever of NOTES.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from solvers.profile import Profile

__all__ = ["Joints", "SegmentTable", "corner_offsets", "cross2", "fragment_layout",
           "joints_of", "rotate", "segment_lookup", "segment_table"]

_UNIT_CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])


def rotate(v: jax.Array, c: jax.Array, s: jax.Array) -> jax.Array:
    """Rotate 2-vectors ``v[..., 2]`` by the angle with cosine c and sine s."""
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def cross2(r: jax.Array, f: jax.Array) -> jax.Array:
    """z-component of r x f (torque of force f applied at lever arm r)."""
    return r[..., 0] * f[..., 1] - r[..., 1] * f[..., 0]


def corner_offsets(half_side: jax.Array) -> jax.Array:
    """(4, 2) body-frame corners of a square of half side h, counter-clockwise."""
    return jnp.asarray(_UNIT_CORNERS) * half_side


def fragment_layout(n: int) -> np.ndarray:
    """(n*n, 2) fragment centres in units of the fragment side, block-centred."""
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    off = np.stack([a.T.reshape(-1), b.T.reshape(-1)], axis=-1) + 0.5 - n / 2.0
    return off.astype(np.float64)


class Joints(NamedTuple):
    """Bonded faces between neighbouring fragments (J joints, 2 points each).

    Attributes:
        a, b: (J,) int32 fragment indices; the joint normal points from a to b.
        qa, qb: (J, 2, 2) joint points in the body frames of a and b, in units
            of the half side h.
        normal: (J, 2) joint normal in a's body frame.
    """

    a: np.ndarray
    b: np.ndarray
    qa: np.ndarray
    qb: np.ndarray
    normal: np.ndarray


def joints_of(n: int) -> Joints:
    """Joints of an n x n grid: 2 n (n - 1) faces (static, numpy)."""
    a_list, b_list, qa, qb, nrm = [], [], [], [], []
    for bb in range(n):
        for aa in range(n):
            k = aa + n * bb
            if aa + 1 < n:  # face on +x
                a_list.append(k)
                b_list.append(k + 1)
                qa.append([[1.0, -1.0], [1.0, 1.0]])
                qb.append([[-1.0, -1.0], [-1.0, 1.0]])
                nrm.append([1.0, 0.0])
            if bb + 1 < n:  # face on +z
                a_list.append(k)
                b_list.append(k + n)
                qa.append([[-1.0, 1.0], [1.0, 1.0]])
                qb.append([[-1.0, -1.0], [1.0, -1.0]])
                nrm.append([0.0, 1.0])
    return Joints(np.asarray(a_list, np.int32).reshape(-1),
                  np.asarray(b_list, np.int32).reshape(-1),
                  np.asarray(qa, np.float64).reshape(-1, 2, 2),
                  np.asarray(qb, np.float64).reshape(-1, 2, 2),
                  np.asarray(nrm, np.float64).reshape(-1, 2))


class SegmentTable(NamedTuple):
    """Per-segment constants of the wall, each (S,).

    xa, za: first vertex, m; tx, tz: unit tangent (downslope, tx > 0);
    tan_phi: tangent of the zone friction angle; x_inner: (S-1,) interior
    vertex abscissae used to find the segment below a point.
    """

    xa: jax.Array
    za: jax.Array
    tx: jax.Array
    tz: jax.Array
    tan_phi: jax.Array
    x_inner: jax.Array


def segment_table(profile: Profile) -> SegmentTable:
    x, z = profile.x_m, profile.z_m
    dx, dz = jnp.diff(x), jnp.diff(z)
    length = jnp.sqrt(dx * dx + dz * dz)
    phi = profile.phi_deg[profile.zone_id]
    return SegmentTable(x[:-1], z[:-1], dx / length, dz / length,
                        jnp.tan(jnp.deg2rad(phi)), x[1:-1])


def segment_lookup(table: SegmentTable, x: jax.Array):
    """Constants of the segment below abscissa ``x`` (any shape).

    Short profiles (<= 16 segments) use a one-hot sum (vectorises well on
    CPU); longer ones a binary search and a gather: O(log S) per corner.

    Returns:
        (xa, za, tx, tz, tan_phi), each of the shape of ``x``.
    """
    n_seg = table.xa.shape[0]
    fields = (table.xa, table.za, table.tx, table.tz, table.tan_phi)
    if n_seg <= 16:
        idx = jnp.sum(x[..., None] >= table.x_inner, axis=-1)
        onehot = idx[..., None] == jnp.arange(n_seg)
        return tuple(jnp.sum(jnp.where(onehot, f, 0.0), axis=-1) for f in fields)
    idx = jnp.searchsorted(table.x_inner, x, side="right")
    return tuple(f[idx] for f in fields)
