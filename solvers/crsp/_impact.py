"""CRSP impact law: roughness-tilted facet, normal and tangential restitution.

All functions are pure, scalar (one block), jit- and vmap-able.

References:
    Pfeiffer, T.J. & Bowen, T.D. (1989). Computer simulation of rockfalls.
        Bull. Assoc. Eng. Geol. 26(1), 135-146.
    Jones, C.L., Higgins, J.D. & Andrew, R.D. (2000). Colorado Rockfall
        Simulation Program, Version 4.0 (manual), Colorado Geological Survey.
    The metric constants and the algebraic form below are those of the open
    re-implementations PyRockfall (``_analysis.py``) and PlatRock (bounce model
    "Pfeiffer"), which convert CRSP's foot constants: 20 ft/s = 6.096 m/s,
    250 ft/s = 76.2 m/s, 30 ft/s = 9.144 m/s (../shared/NOTES.md, checked).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = [
    "FRICTION_SPEED_M_S",
    "NORMAL_SPEED_M_S",
    "SCALING_SPEED_M_S",
    "ImpactOut",
    "crsp_impact",
    "roughness_tilt",
]

FRICTION_SPEED_M_S = 6.096  # 20 ft/s, friction-function speed scale
SCALING_SPEED_M_S = 76.2  # 250 ft/s, scaling-factor speed scale
NORMAL_SPEED_M_S = 9.144  # 30 ft/s, normal-velocity scaling ("K")
_MAX_FACET_RAD = 0.5 * jnp.pi - 0.01  # keep the facet normal's vertical part >= 0.01


class ImpactOut(NamedTuple):
    """Rebound of one impact.

    Attributes:
        vx_m_s, vz_m_s: rebound velocity in the global frame, m/s.
        spin_rad_s: rolling-positive spin after impact, rad/s (w2 = Vt2 / r).
        facet_rad: angle of the (tilted) facet that was hit, rad.
    """

    vx_m_s: jax.Array
    vz_m_s: jax.Array
    spin_rad_s: jax.Array
    facet_rad: jax.Array


def roughness_tilt(
    u: jax.Array, roughness_m: jax.Array, radius_m: jax.Array
) -> jax.Array:
    """Random facet tilt at an impact, in [0, theta_max).

    CRSP defines the roughness S as the largest deviation perpendicular to the
    mean slope within a slope distance equal to the rock radius R, so that the
    local slope angle can deviate by up to ``theta_max = arctan(S / R)``
    (Pfeiffer & Bowen 1989; CRSP 4.0 manual). Large rocks therefore feel less
    roughness: the source of CRSP's size effect.

    Sampling chosen here: ``delta = U * theta_max`` with U ~ U(0, 1), applied
    towards the incoming rock (the facet faces the rock more steeply, so
    roughness only brakes). This is PlatRock's reading of CRSP
    (``BounceModels.set_updated_normal2D``, checked in ../shared/NOTES.md). The
    CRSP manual's text on one- or two-sided sampling was not available to us.

    Args:
        u: uniform draw in [0, 1).
        roughness_m: S, m (>= 0).
        radius_m: R, m (> 0).

    Returns:
        Tilt magnitude in radians.
    """
    return u * jnp.arctan2(roughness_m, radius_m)


def crsp_impact(
    vx_m_s: jax.Array,
    vz_m_s: jax.Array,
    spin_rad_s: jax.Array,
    slope_rad: jax.Array,
    tilt_rad: jax.Array,
    Kn: jax.Array,
    Kt: jax.Array,
    radius_m: jax.Array,
    inertia_ratio: jax.Array,
    slope_cos: jax.Array | None = None,
    slope_sin: jax.Array | None = None,
) -> ImpactOut:
    """One CRSP impact of a rotating rock on a roughness-tilted facet.

    The facet angle is ``slope + s * tilt`` where s is the sign of the rock's
    tangential velocity along the mean slope (tilting towards the rock). In the
    facet frame (tangent t along +x, outward normal n), with incoming normal
    speed ``Vn1 = -v.n > 0``, tangential speed ``Vt1 = v.t`` and rolling-positive
    spin ``w1``:

    Normal (CRSP velocity scaling, K = 9.144 m/s):
        ``Vn2 = Kn Vn1 / (1 + (Vn1 / K)^2)``

    Tangential (friction function FF and scaling factor SF, Rt = Kt):
        ``FF = Rt + (1 - Rt) / (((Vt1 - w1 r) / 6.096)^2 + 1.2)``
        ``SF = Rt / ((Vn1 / (76.2 Rn))^2 + 1)``
        ``Vt2 = sqrt(r^2 (I w1^2 + m Vt1^2) FF SF / (I + m r^2))``, ``w2 = Vt2 / r``

    One source has ``+ 1`` in SF's denominator and the manual may have ``+ 1.2``;
    we use ``+ 1`` as found in the checked code (NOTES.md). With I = k m r^2 the
    mass cancels: ``Vt2 = sqrt((k r^2 w1^2 + Vt1^2) FF SF / (1 + k))``. The
    rock leaves rolling (``w2 = Vt2 / r``) in the sense of its angular momentum
    about the contact point, ``sign(Vt1 + k r w1)``. Since FF < 1 and SF <= Rt
    <= 1, the tangential energy ``(1/2)(I w^2 + m Vt^2)`` is multiplied by
    ``FF SF < 1`` and the normal one by ``(Vn2/Vn1)^2 <= Kn^2``: an impact never
    creates energy.

    Args:
        vx_m_s, vz_m_s: incoming velocity, m/s (global frame, z up).
        spin_rad_s: rolling-positive spin (rolls the rock towards +x), rad/s.
        slope_rad: angle of the mean segment, rad (negative = descending to +x).
        tilt_rad: roughness tilt magnitude (see ``roughness_tilt``), rad.
        Kn, Kt: normal and tangential restitution coefficients (Rn, Rt).
        radius_m: rock radius r, m.
        inertia_ratio: k = I / (m r^2): 0.4 sphere, 0.5 cylinder or disc.
        slope_cos, slope_sin: optional precomputed cos/sin of ``slope_rad``.

    Returns:
        ``ImpactOut`` with the rebound velocity, spin and facet angle.
    """
    ct = jnp.cos(slope_rad) if slope_cos is None else slope_cos
    st = jnp.sin(slope_rad) if slope_sin is None else slope_sin
    vt_mean = vx_m_s * ct + vz_m_s * st
    side = jnp.where(vt_mean >= 0.0, 1.0, -1.0)
    facet = jnp.clip(slope_rad + side * tilt_rad, -_MAX_FACET_RAD, _MAX_FACET_RAD)
    cf, sf = jnp.cos(facet), jnp.sin(facet)
    # facet tangent (cf, sf), outward normal (-sf, cf)
    vt1 = vx_m_s * cf + vz_m_s * sf
    vn1 = jnp.maximum(-(-vx_m_s * sf + vz_m_s * cf), 0.0)

    vn2 = Kn * vn1 / (1.0 + (vn1 / NORMAL_SPEED_M_S) ** 2)

    slip = vt1 - spin_rad_s * radius_m
    ff = Kt + (1.0 - Kt) / ((slip / FRICTION_SPEED_M_S) ** 2 + 1.2)
    sf_scale = Kt / ((vn1 / (SCALING_SPEED_M_S * Kn)) ** 2 + 1.0)
    k = inertia_ratio
    energy_t = k * (radius_m * spin_rad_s) ** 2 + vt1**2  # 2 E_t / m
    vt2_mag = jnp.sqrt(energy_t * ff * sf_scale / (1.0 + k))
    sense = jnp.where(vt1 + k * radius_m * spin_rad_s >= 0.0, 1.0, -1.0)
    vt2 = sense * vt2_mag

    vx2 = vt2 * cf - vn2 * sf
    vz2 = vt2 * sf + vn2 * cf
    return ImpactOut(vx2, vz2, vt2 / radius_m, facet)
