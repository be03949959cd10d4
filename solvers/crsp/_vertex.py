"""A rolling CRSP rock reaching a vertex of the profile (ONE block, pure).

This is this toolkit's own treatment, not an equation of the CRSP manual; see
``vertex_transition`` for the rules and the criteria they rest on. The contact
event of ``_model`` calls it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["VertexTransition", "vertex_transition"]

_COLLINEAR_RAD = 1e-9  # |turn angle| below this: a collinear vertex (round-off)


class VertexTransition(NamedTuple):
    """What a rolling rock does at a vertex (see ``vertex_transition``).

    Attributes:
        launch: bool, it separates and flies (a real hop).
        impact: bool, a concave break hit fast enough for a CRSP impact.
        u_next_m_s: speed (>= 0) with which it rolls on along the next segment
            when neither.
        launch_rad: inclination of the launch direction below the horizontal,
            in the direction of motion, rad.
        rest: bool, the rock is at rest in a pit (a local low vertex).
    """

    launch: jax.Array
    impact: jax.Array
    u_next_m_s: jax.Array
    launch_rad: jax.Array
    rest: jax.Array


_PIT_REST_HEIGHT_M = 1e-3  # a rock in a pit that could rise less than this is at rest


def vertex_transition(speed_m_s, direction, beta, beta_next, radius_m, inertia_ratio,
                      threshold_m_s, g_m_s2: float,
                      next_length_m=jnp.inf) -> VertexTransition:
    """A rolling rock of speed v reaching a vertex (this toolkit's treatment).

    With ``a1 = -d beta`` and ``a2 = -d beta_next`` the inclinations of the two
    segments below the horizontal in the direction of motion d, the path turns
    by ``delta = a2 - a1``:

    * ``|delta| <= 1e-9`` rad: collinear (a resampled straight line): the rock
      rolls on with its speed.
    * concave (delta < 0): the rock meets the next segment with normal speed
      ``v sin|delta|``. At or above the rolling threshold that is a CRSP
      impact on the next segment; below it a touch-down that keeps the
      tangential component ``v cos(delta)`` (second order in delta, so a
      refined smooth curve converges).
    * convex (delta > 0): the rock may leave the edge (``_convex_edge``: where,
      and whether that is a real hop launched into a flight whose landing is
      found by ``next_impact`` and may be a touch-down). One that separates
      without a real hop touches down at once and rolls on with ``v cos(phi)``,
      ``phi = a2 - psi*`` its angle above the next segment. A rock that does
      not separate rounds the edge and rolls on with its speed.

    * a pit (the rock arrives going down, a1 >= 0, and the next segment rises,
      a2 < 0): both segments push the rock back to the vertex, so rest there is
      statically admissible whatever the slopes. A rock that could rise there
      by less than 1 mm (``v^2 < 2 g 1 mm``) is at rest at the vertex: its
      remaining back-and-forth converges to the vertex in finite time (a Zeno
      sequence that an event loop cannot end by itself).

    The lumped mass stays at the contact point, so the drop of the rock's
    centre over the edge, ``r (cos(a1) - cos(a2))``, is not added: no event
    at a vertex ever creates energy.

    Args:
        speed_m_s: v >= 0 at the vertex, m/s. direction: +1 or -1.
        beta, beta_next: segment angles (to +x), rad.
        radius_m: r, m. inertia_ratio: k. threshold_m_s: rolling threshold, m/s.
        g_m_s2: gravity. next_length_m: slope length of the next segment, m.

    Returns:
        ``VertexTransition``.
    """
    v = speed_m_s
    a1 = -direction * beta
    a2 = -direction * beta_next
    delta = a2 - a1
    concave = delta < -_COLLINEAR_RAD
    convex = delta > _COLLINEAR_RAD
    # concave
    impact = concave & (v * jnp.sin(-delta) >= threshold_m_s)
    psi, separates, turn, launch = _convex_edge(v, a1, a2, convex, radius_m, inertia_ratio,
                                                threshold_m_s, g_m_s2, next_length_m)
    u_next = jnp.where(concave, v * jnp.cos(delta), jnp.where(separates, v * jnp.cos(turn), v))
    rest = (a1 >= 0.0) & (a2 < 0.0) & (v * v < 2.0 * g_m_s2 * _PIT_REST_HEIGHT_M)
    return VertexTransition(launch=launch & ~rest, impact=impact & ~rest, u_next_m_s=u_next,
                            launch_rad=psi, rest=rest)


def _convex_edge(v, a1, a2, convex, radius_m, k, threshold_m_s, g_m_s2: float, next_length_m):
    """Where a rock rolling at speed v leaves a convex edge, and whether it flies.

    A rigid body pivoting over an edge keeps contact while the normal force
    ``m (g cos(psi) - v^2 / r) >= 0``, psi the inclination of the contact normal
    (the particle-on-a-sphere condition; e.g. Meriam & Kraige, Engineering
    Mechanics: Dynamics, normal and tangential coordinates). It leaves at once
    when ``v^2 >= g r cos(a1)``; else, rolling without slip with energy
    conserved, at ``cos(psi*) = ((1 + k) v^2 / (g r) + 2 cos(a1)) / (3 + k)``
    (10/17 from rest for a sphere), if ``psi* < a2``. A rock that separates
    leaves along the path's tangent at psi*, at the angle ``phi = a2 - psi*``
    above the next segment. It is launched into a flight when that is a real
    hop (this toolkit's criterion): when it would land back on the next segment
    with a normal speed ``v sin(phi)`` at or above the rolling threshold, or
    when its hop length over that segment's line,
    ``s = v cos(phi) t + g sin(a2) t^2 / 2`` with ``t = 2 v sin(phi) / (g cos(a2))``,
    exceeds the segment's length (the ground beyond falls away further: on a
    finely sampled convex curve of radius rho this launches when
    ``v^2 > g rho cos(a) / 2`` whatever the sampling step, so refining the curve
    converges).

    Args:
        v: speed at the vertex, m/s. a1, a2: inclinations of the two segments
            below the horizontal in the direction of motion, rad.
        convex: bool, the path turns downward (``a2 - a1`` above round-off).
        radius_m: r, m. k: inertia ratio. threshold_m_s: rolling threshold, m/s.
        g_m_s2: gravity. next_length_m: slope length of the next segment, m.

    Returns:
        (psi, separates, phi, launch): the inclination where it leaves (a1 when at
        once), rad; bool, it separates; phi (0 where it does not), rad; bool, a
        real hop.
    """
    ratio = v * v / (g_m_s2 * radius_m)
    cos_a1 = jnp.cos(a1)
    at_once = ratio >= cos_a1
    cos_psi = ((1.0 + k) * ratio + 2.0 * cos_a1) / (3.0 + k)
    psi = jnp.where(at_once, a1, jnp.arccos(jnp.clip(cos_psi, -1.0, 1.0)))
    separates = convex & (at_once | (psi < a2))
    turn = jnp.where(separates, a2 - psi, 0.0)
    cos_a2 = jnp.cos(a2)
    t_hop = 2.0 * v * jnp.sin(turn) / (g_m_s2 * jnp.where(cos_a2 > 1e-6, cos_a2, 1e-6))
    s_hop = v * jnp.cos(turn) * t_hop + 0.5 * g_m_s2 * jnp.sin(a2) * t_hop * t_hop
    launch = separates & ((v * jnp.sin(turn) >= threshold_m_s) | (s_hop > next_length_m))
    return psi, separates, turn, launch
