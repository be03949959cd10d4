"""Exact parabolic flight and the next impact against a local window of segments.

Free flight of the lumped mass (no air drag):
    ``x(t) = x0 + vx t``,  ``z(t) = z0 + vz t - g t^2 / 2``.

Against the line of segment j, ``z = za + s_j (x - xa)``, the height above the
line is ``h(t) = h0 + b t - g t^2 / 2`` with ``h0 = z0 - za - s_j (x0 - xa)`` and
``b = vz - s_j vx``. The block passes downwards through the line at the larger
root ``t = (b + sqrt(b^2 + 2 g h0)) / g``; it is an impact on segment j when
``x(t)`` lies inside that segment. On a height-field profile the earliest such
crossing is the first impact.

Local search: only the W segments starting at the current one, in the direction
of travel, are tested per event. When none is hit the block is advanced to the
edge of that window and the next event tests the next W segments, so cost per
event does not grow with the number of profile segments.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from solvers.profile import Profile

__all__ = ["FlightHit", "next_impact"]

_T_MIN_S = 1e-9
_X_TOL_M = 1e-9
_H_TOL_M = 1e-9


class FlightHit(NamedTuple):
    """Where the current flight ends.

    Attributes:
        t_s: flight time to the end of this event, s.
        hit: bool, the event ends in an impact (else at the window edge).
        seg: segment hit, or the segment just beyond the window edge.
        left_profile: bool, the block flew past either end of the profile.
    """

    t_s: jax.Array
    hit: jax.Array
    seg: jax.Array
    left_profile: jax.Array


def next_impact(
    profile: Profile,
    seg: jax.Array,
    x_m: jax.Array,
    z_m: jax.Array,
    vx_m_s: jax.Array,
    vz_m_s: jax.Array,
    g_m_s2: float,
    window: int,
) -> FlightHit:
    """First downward crossing of the parabola through the ground in a window.

    Args:
        profile: the slope.
        seg: int, segment under the block (flight starts above it).
        x_m, z_m: position, m.
        vx_m_s, vz_m_s: velocity, m/s.
        g_m_s2: gravity, m/s^2.
        window: number of segments tested (static).

    Returns:
        ``FlightHit``.
    """
    n_seg = profile.x_m.shape[0] - 1
    step = jnp.where(vx_m_s >= 0.0, 1, -1)
    j_raw = seg + step * jnp.arange(window)
    in_range = (j_raw >= 0) & (j_raw < n_seg)
    j = jnp.clip(j_raw, 0, n_seg - 1)
    xa, xb = profile.x_m[j], profile.x_m[j + 1]
    za, zb = profile.z_m[j], profile.z_m[j + 1]
    s = (zb - za) / (xb - xa)
    h0 = z_m - za - s * (x_m - xa)
    b = vz_m_s - s * vx_m_s
    disc = b * b + 2.0 * g_m_s2 * h0
    t = (b + jnp.sqrt(jnp.maximum(disc, 0.0))) / g_m_s2
    xt = x_m + vx_m_s * t
    valid = in_range & (disc >= 0.0) & (t > _T_MIN_S) & (xt >= xa - _X_TOL_M) & (
        xt <= xb + _X_TOL_M)
    at_once = in_range & (h0 <= _H_TOL_M) & (b < 0.0) & (x_m >= xa - _X_TOL_M) & (
        x_m <= xb + _X_TOL_M)
    t_valid = jnp.where(at_once, 0.0, jnp.where(valid, t, jnp.inf))
    k = jnp.argmin(t_valid)
    hit = jnp.isfinite(t_valid[k])

    # No hit: advance to the far edge of the last in-range segment of the window.
    last = jnp.sum(in_range) - 1
    j_last = j[last]
    x_edge = jnp.where(step > 0, profile.x_m[j_last + 1], profile.x_m[j_last])
    safe_vx = jnp.where(vx_m_s == 0.0, 1.0, vx_m_s)
    t_edge = jnp.where(vx_m_s == 0.0, 0.0, (x_edge - x_m) / safe_vx)
    beyond = j_last + step
    left = (~hit) & ((beyond < 0) | (beyond >= n_seg))
    return FlightHit(
        t_s=jnp.where(hit, t_valid[k], jnp.maximum(t_edge, 0.0)),
        hit=hit,
        seg=jnp.where(hit, j[k], jnp.clip(beyond, 0, n_seg - 1)).astype(jnp.int32),
        left_profile=left,
    )
