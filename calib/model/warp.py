"""Warped parameter coordinates: where the runouts' response to CRSP's
parameters is closer to stationary.

Per parameter, by name (our choice, input warping for a GP with one length
scale per input; the prior stays uniform in the parameters themselves,
``calib.model.priors``):

====================  ===================  =========================================
parameter             warped coordinate    why
====================  ===================  =========================================
Kt                    u = log(1 - Kt)      runouts change fastest as Kt -> 1
roughness_m (S)       u = log(S)           and as S -> 0 (the Tschamut slab,
                                           S 0.05-0.1 m in a 0.01-4 m box)
rolling_friction_deg  u = tan(phi_r)       the rolling phase's Coulomb resistance
(and [<zone>])                             is mu = tan(phi_r)
any other             u = theta            (Kn, the effects' parameters)
====================  ===================  =========================================

Used by the CRSP emulator's inputs (``calib.model.forward.CrspForward.to_input``)
and by the discovery workflow's importance-sampling proposals
(``calib.discovery.discrepancy``), which need the density change
log |du/dtheta| = sum_j log |u_j'(theta_j)| to weight draws made in u against
the prior in theta.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from calib.model.priors import Box, base_name

__all__ = ["log_jacobian", "unit_coordinates", "unwarp", "warp", "warped_box",
           "warped_names"]

_DEG = np.pi / 180.0

# name: (u(theta), theta(u), log |du/dtheta|, name of u), jnp for the forward, np for the rest
_WARPS = {
    "Kt": (lambda t: jnp.log1p(-t), lambda u: -np.expm1(u), lambda t: -np.log1p(-t),
           "log(1-Kt)"),
    "roughness_m": (jnp.log, np.exp, lambda t: -np.log(t), "log(S)"),
    "rolling_friction_deg": (lambda t: jnp.tan(jnp.deg2rad(t)),
                             lambda u: np.degrees(np.arctan(u)),
                             lambda t: np.log(_DEG) - 2.0 * np.log(np.cos(np.deg2rad(t))),
                             "tan(phi_r)"),
}


def _of(name):
    """The warp of ``name`` (a zone's rolling resistance warps as the slope's), or None."""
    return _WARPS.get(base_name(name))


def warp(names, theta):
    """u (..., d) from theta (..., d); jnp, so it traces inside NUTS's target."""
    t = jnp.asarray(theta)
    return jnp.stack([_of(n)[0](t[..., j]) if _of(n) else t[..., j]
                      for j, n in enumerate(names)], axis=-1)


def unwarp(names, u) -> np.ndarray:
    """theta (..., d) from u (..., d): the inverse of ``warp``."""
    u = np.asarray(u, float)
    return np.stack([_of(n)[1](u[..., j]) if _of(n) else u[..., j]
                     for j, n in enumerate(names)], axis=-1)


def log_jacobian(names, theta) -> np.ndarray:
    """(...,) log |du/dtheta| = sum_j log |u_j'(theta_j)| (0 for unwarped parameters)."""
    t = np.asarray(theta, float)
    out = np.zeros(t.shape[:-1])
    for j, n in enumerate(names):
        if _of(n):
            out = out + _of(n)[2](t[..., j])
    return out


def warped_names(names) -> tuple[str, ...]:
    return tuple(_of(n)[3] + n[len(base_name(n)):] if _of(n) else n for n in names)


def warped_box(box: Box) -> Box:
    """The prior box in warped coordinates (every warp is monotone)."""
    a = np.asarray(warp(box.names, box.lo))
    b = np.asarray(warp(box.names, box.hi))
    return Box(warped_names(box.names), tuple(np.minimum(a, b)), tuple(np.maximum(a, b)))


def unit_coordinates(box: Box):
    """The unit cube the discovery workflow's adaptive proposals live in
    (``calib.discovery.discrepancy``): the prior box in the warped coordinates,
    scaled to [0, 1]^d.

    Returns (to_z, to_theta, log_jac): theta (N, d) -> z; z -> theta (inside
    the box); and log of the density of the uniform on the cube relative to the
    uniform prior on the box at z, log |dz/dtheta| + log vol(box): a draw made
    with density q(z) on the cube has density q(z) exp(log_jac(z)) relative to
    the prior.

    Why (our choice): a Sobol stage uniform in theta puts about 1 % of its
    points at S < 0.1 m, where the Tschamut likelihood peaks, and every
    candidate's weights then rest on one design point (Tschamut, 62 runs,
    ``--rolling-resistance fit``: ESS 1.0-1.3 of 384-512, the baseline's
    score -698 against -286 with these coordinates). The same reason made the
    calibration's design fill them (``calib.model.forward.CrspForward.design``).
    Stage 0 keeps half its points uniform in theta (``discrepancy.fit_candidate``): on the
    synthetic size-dissipation case of the tests (S box 0.25-4 m), proposals
    drawn in the warped cube alone fitted the baseline worse (score -149.2
    against -144.4, ESS 1.4 against 5.3) and lost the size trend the residuals
    had located; with the pair: -144.6, ESS 5.2, trend located.
    """
    wbox = warped_box(box)
    const = float(np.sum(np.log(box.hi - box.lo)) - np.sum(np.log(wbox.hi - wbox.lo)))

    def to_z(theta):
        return wbox.to_unit(np.asarray(warp(box.names, np.asarray(theta, float))))

    def to_theta(z):
        return np.clip(unwarp(box.names, wbox.from_unit(np.asarray(z, float))), box.lo, box.hi)

    def log_jac(z):
        return log_jacobian(box.names, to_theta(z)) + const

    return to_z, to_theta, log_jac
