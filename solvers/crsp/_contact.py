"""Ground-contact (rolling/sliding) phase of the lumped mass, in closed form.

When a rebound leaves the ground with a normal speed (relative to the mean
segment) below a threshold, the rock stays in contact and moves along the
segment. Along the segment's tangent t (pointing to +x), with signed speed u:

    ``(1 + k) du/dt = -g sin(beta) - sign(u) mu g cos(beta)``,   ``mu = tan(phi_r)``

where beta is the segment angle, k = I / (m r^2) (rolling without slip stores
``(1 + k)`` times the translational energy) and phi_r the zone's rolling-
resistance angle. The acceleration is constant on a segment, so the motion to
the segment's end, or to rest, is solved exactly. A rock at rest stays at rest
only where ``tan|beta| <= mu``: a stop is only recorded where it is physically
possible (the failure mode of PlatRock noted in ../shared/NOTES.md).

Roughness acts in this phase too, as CRSP intends (CRSP represents rolling as a
sequence of small impacts on the rough surface): every slope distance equal to
the rock radius R (the length over which CRSP defines the roughness S) the
rock meets an asperity, and a full CRSP impact on a randomly tilted facet
follows (``_model``). With S = 0 there are no asperities and the rock rolls with
the Coulomb resistance alone. The Coulomb term between asperities is an
explicit modelling choice of this toolkit (as in RocFall's rolling mode).

At a vertex the rock either launches into flight (the next segment falls away:
convex break) or continues on the next segment with the tangential component of
its velocity, ``u2 = u cos(beta2 - beta)`` (concave break: the normal component
is lost, energy never increases).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["ContactMove", "contact_move"]


class ContactMove(NamedTuple):
    """Result of one contact event on a segment.

    Attributes:
        dist_m: signed distance travelled along the segment tangent, m.
        u_end_m_s: signed speed at the end of the event, m/s.
        accel_m_s2: the (constant) signed acceleration used, m/s^2.
        at_end: bool, the event ends at the segment's end (in direction ``dir``).
        stopped: bool, the rock comes to rest and can stay there.
        direction: +1 or -1, direction of motion during the event.
        kicked: bool, the event ends at a roughness asperity (an impact follows).
    """

    dist_m: jax.Array
    u_end_m_s: jax.Array
    accel_m_s2: jax.Array
    at_end: jax.Array
    stopped: jax.Array
    direction: jax.Array
    kicked: jax.Array


def contact_move(
    u_m_s: jax.Array,
    slope_cos: jax.Array,
    slope_sin: jax.Array,
    mu: jax.Array,
    dist_fwd_m: jax.Array,
    dist_back_m: jax.Array,
    inertia_ratio: jax.Array,
    g_m_s2: float,
    dist_kick_m: jax.Array = jnp.inf,
) -> ContactMove:
    """Advance a rock in contact along one segment, exactly.

    Args:
        u_m_s: signed speed along the tangent (+ towards +x), m/s.
        slope_cos, slope_sin: cos and sin of the segment angle beta.
        mu: rolling-resistance coefficient tan(phi_r).
        dist_fwd_m: slope distance to the segment's +x end, m (>= 0).
        dist_back_m: slope distance to the segment's -x end, m (>= 0).
        inertia_ratio: k = I / (m r^2).
        g_m_s2: gravity, m/s^2.
        dist_kick_m: slope distance to the next roughness asperity, m; the event
            ends there (``kicked``) unless it ends earlier.

    Returns:
        ``ContactMove``.
    """
    cb, sb = slope_cos, slope_sin
    g_t = -g_m_s2 * sb  # gravity along +t
    resist = mu * g_m_s2 * cb
    at_rest = u_m_s == 0.0
    can_rest = jnp.abs(g_t) <= resist
    direction = jnp.where(at_rest, jnp.where(g_t >= 0.0, 1.0, -1.0),
                          jnp.where(u_m_s > 0.0, 1.0, -1.0))
    a = (g_t - direction * resist) / (1.0 + inertia_ratio)
    speed = jnp.abs(u_m_s)
    a_dir = a * direction  # > 0 speeds up, < 0 slows down
    d_end = jnp.where(direction > 0, dist_fwd_m, dist_back_m)
    safe = jnp.where(a_dir < 0.0, -a_dir, 1.0)
    d_stop = jnp.where(a_dir < 0.0, speed * speed / (2.0 * safe), jnp.inf)
    stops_first = d_stop <= jnp.minimum(d_end, dist_kick_m)
    kick_first = ~stops_first & (dist_kick_m < d_end)
    d = jnp.where(stops_first, d_stop, jnp.minimum(d_end, dist_kick_m))
    v_end = jnp.sqrt(jnp.maximum(speed * speed + 2.0 * a_dir * d, 0.0))
    v_end = jnp.where(stops_first, 0.0, v_end)
    resting = at_rest & can_rest
    stopped = resting | (stops_first & can_rest)
    d = jnp.where(resting, 0.0, d)
    return ContactMove(
        dist_m=direction * d,
        u_end_m_s=direction * v_end,
        accel_m_s2=a,
        at_end=~stops_first & ~kick_first & ~resting,
        stopped=stopped,
        direction=direction,
        kicked=kick_first & ~resting,
    )
