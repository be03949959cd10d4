"""Ground-contact (rolling) phase of the lumped mass, in closed form.

When a landing or a rebound has a normal speed (relative to the mean segment)
below the rolling threshold, the rock stays in contact and rolls along the
segment. Along the segment's tangent, with speed v >= 0 in the direction of
motion d = +-1 and slope distance s travelled, w = v^2 obeys

    ``dw/ds = 2 A - c w``,
    ``A = (-d g sin(beta) - mu g cos(beta)) / (1 + k)``,    ``c = lambda(theta_max) / R``

(a linear ODE in s, solved exactly), where beta is the segment angle, k = I /
(m r^2) (rolling without slip stores ``(1 + k)`` times the translational
energy), ``mu = tan(phi_r)`` the zone's rolling-resistance coefficient, R the
rock radius and ``lambda`` the mean fraction of kinetic energy lost at one
roughness asperity (``asperity_loss``). Solution and stopping distance:

    ``w(s) = w0 exp(-c s) + 2 A (1 - exp(-c s)) / c``   (-> ``w0 + 2 A s`` as c -> 0)
    ``s_stop = log(1 + c w0 / (2 |A|)) / c``  when A < 0 (-> ``w0 / (2 |A|)``).

A rock at rest stays at rest only where ``tan|beta| <= mu``: a stop is recorded
only where it is physically possible (the failure mode of PlatRock noted in
../shared/NOTES.md).

What is CRSP and what is this toolkit's choice:

* CRSP (Pfeiffer & Bowen 1989; Jones et al. 2000) defines the roughness S
  over a slope distance equal to the rock radius R, so the local slope can
  deviate from the mean by up to ``theta_max = arctan(S / R)``; impacts use a
  random facet angle in that range (``_impact``). That is kept for impacts.
* Rolling over that rough surface is this toolkit's own treatment. The rock
  meets one asperity per slope distance R (CRSP's roughness window) whose
  face is tilted by ``theta = U theta_max``, U ~ U(0, 1), towards the rock. A
  rolling rigid body of inertia ratio k that pivots onto a face tilted by
  theta keeps its angular momentum about the new contact point, so its speed
  becomes ``v (cos(theta) + k) / (1 + k)`` (the classical sphere-over-a-step
  result, e.g. Goldsmith 1960, "Impact", ch. 2; an inelastic contact, no
  bounce). Over the many asperities of a segment we replace the random
  sequence by its mean: the energy fraction lost per asperity is
  ``lambda = 1 - E_U[((cos(U theta_max) + k) / (1 + k))^2]``, in closed form
  with ``E[cos(U t)] = sinc(t)`` and ``E[cos^2(U t)] = (1 + sinc(2 t)) / 2``.
  Consequences, all checked by tests: ``lambda -> 0`` as S -> 0 (the S -> 0
  limit is the S = 0 model, no jump); lambda grows with S (more roughness
  never carries a rock further); the dissipation per metre ``lambda / R``
  vanishes at S = 0 for every size, so there is no size effect that does not
  come through S / R. Each contact event ends at a segment end or at rest, so
  rolling costs one event per segment, not one per radius.
* The Coulomb rolling resistance ``mu = tan(phi_r)`` is the rolling friction
  of 2D lumped-mass codes (RocFall's rolling friction angle; the rolling
  friction coefficient of Azzoni et al. 1995, CADMA), a per-zone material
  parameter (``rolling_friction_deg``). It is a site parameter to calibrate,
  not a hidden constant: see ``solvers.profile`` for its published range.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["ContactMove", "asperity_loss", "contact_move", "speed2_after"]


class ContactMove(NamedTuple):
    """Result of one contact event on a segment.

    Attributes:
        dist_m: signed distance travelled along the segment tangent, m.
        u_end_m_s: signed speed at the end of the event, m/s.
        accel_m_s2: A, the signed (gravity + Coulomb) acceleration along the
            direction of motion, m/s^2 (before the asperity loss).
        drag_per_m: c, the asperity loss rate per metre of slope, 1/m.
        at_end: bool, the event ends at the segment's end (in direction ``direction``).
        stopped: bool, the rock comes to rest and can stay there.
        direction: +1 or -1, direction of motion during the event.
    """

    dist_m: jax.Array
    u_end_m_s: jax.Array
    accel_m_s2: jax.Array
    drag_per_m: jax.Array
    at_end: jax.Array
    stopped: jax.Array
    direction: jax.Array


def _sinc(t):
    """sin(t) / t with the removable singularity at 0 (radians)."""
    return jnp.sinc(t / jnp.pi)


def asperity_loss(theta_max_rad: jax.Array, inertia_ratio: jax.Array) -> jax.Array:
    """Mean energy fraction lost when a rolling rock meets one asperity.

    ``lambda = 1 - E_U[((cos(U theta_max) + k) / (1 + k))^2]``, U ~ U(0, 1) (see the
    module docstring); 0 at theta_max = 0, increasing in theta_max.

    Args:
        theta_max_rad: arctan(S / R), rad, in [0, pi/2].
        inertia_ratio: k = I / (m r^2).

    Returns:
        lambda in [0, 1).
    """
    k = inertia_ratio
    e_cos = _sinc(theta_max_rad)
    e_cos2 = 0.5 * (1.0 + _sinc(2.0 * theta_max_rad))
    keep = (e_cos2 + 2.0 * k * e_cos + k * k) / (1.0 + k) ** 2
    return jnp.clip(1.0 - keep, 0.0, 1.0)


def _expm1_ratio(c, s):
    """(1 - exp(-c s)) / c, -> s as c -> 0 (safe for c = 0 and s = inf)."""
    cs = c * s
    small = cs < 1e-8
    safe_c = jnp.where(small, 1.0, c)
    return jnp.where(small, s * (1.0 - 0.5 * cs), -jnp.expm1(-jnp.where(small, 0.0, cs)) / safe_c)


def speed2_after(w0: jax.Array, accel: jax.Array, drag_per_m: jax.Array,
                 dist_m: jax.Array) -> jax.Array:
    """Squared speed after rolling ``dist_m`` (>= 0) from squared speed ``w0``:
    ``w0 exp(-c s) + 2 A (1 - exp(-c s)) / c``, clipped at 0."""
    decay = jnp.exp(-drag_per_m * dist_m)
    return jnp.maximum(w0 * decay + 2.0 * accel * _expm1_ratio(drag_per_m, dist_m), 0.0)


def contact_move(
    u_m_s: jax.Array,
    slope_cos: jax.Array,
    slope_sin: jax.Array,
    mu: jax.Array,
    dist_fwd_m: jax.Array,
    dist_back_m: jax.Array,
    inertia_ratio: jax.Array,
    g_m_s2: float,
    drag_per_m: jax.Array = 0.0,
) -> ContactMove:
    """Advance a rolling rock along one segment, exactly, to its end or to rest.

    Args:
        u_m_s: signed speed along the tangent (+ towards +x), m/s.
        slope_cos, slope_sin: cos and sin of the segment angle beta.
        mu: rolling-resistance coefficient tan(phi_r).
        dist_fwd_m: slope distance to the segment's +x end, m (>= 0).
        dist_back_m: slope distance to the segment's -x end, m (>= 0).
        inertia_ratio: k = I / (m r^2).
        g_m_s2: gravity, m/s^2.
        drag_per_m: c = lambda / R, asperity loss rate, 1/m (>= 0).

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
    a_dir = (direction * g_t - resist) / (1.0 + inertia_ratio)  # > 0 speeds up
    w0 = u_m_s * u_m_s
    d_end = jnp.where(direction > 0, dist_fwd_m, dist_back_m)
    decel = a_dir < 0.0
    safe_a = jnp.where(decel, -a_dir, 1.0)
    # s_stop = log1p(c w0 / (2|A|)) / c  (-> w0 / (2|A|) as c -> 0)
    x = drag_per_m * w0 / (2.0 * safe_a)
    small = x < 1e-8
    safe_c = jnp.where(small, 1.0, drag_per_m)
    d_stop = jnp.where(small, w0 / (2.0 * safe_a) * (1.0 - 0.5 * x),
                       jnp.log1p(jnp.where(small, 0.0, x)) / safe_c)
    d_stop = jnp.where(decel, d_stop, jnp.inf)
    stops_first = d_stop <= d_end
    d = jnp.where(stops_first, d_stop, d_end)
    v_end = jnp.sqrt(speed2_after(w0, a_dir, drag_per_m, d))
    v_end = jnp.where(stops_first, 0.0, v_end)
    resting = at_rest & can_rest
    stopped = resting | (stops_first & can_rest)
    d = jnp.where(resting, 0.0, d)
    return ContactMove(
        dist_m=direction * d,
        u_end_m_s=direction * v_end,
        accel_m_s2=a_dir,
        drag_per_m=drag_per_m + 0.0 * a_dir,
        at_end=~stops_first & ~resting,
        stopped=stopped,
        direction=direction,
    )
