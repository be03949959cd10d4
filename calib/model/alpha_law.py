"""The DEM damping law alpha(L): one law, one clipping rule, for the fit, the
discrepancy candidates and the hazard run.

The paper (Sect. 4.1, Table 1) lowered UDEC's local damping coefficient with
block size: alpha = 0.90, 0.43, 0.30 for square sides L = 0.2, 0.9, 1.8 m. We
calibrate either

* ``power``: alpha(L) = a L^-b (theta = (a, b), L in m), the trend of Table 1
  (the paper gives the three values, not a formula: the power law is our
  choice), or
* ``constant``: alpha(L) = alpha (theta = (alpha,)), the DEM before the paper
  made alpha depend on size;

and every model evaluates it as

    alpha(L) = clip(law(L), 0, ALPHA_MAX),   ALPHA_MAX = 0.95.

Source's model: Cundall local damping (UDEC, paper eq. 3) needs 0 <= alpha < 1
(alpha = 1 removes the whole unbalanced force: the block cannot move);
``solvers.dem.make_block`` refuses anything else.

Our choice, the clip at 0.95 (the largest value of the prior boxes,
``calib.model.priors``): a power law with b > 0 exceeds 1 for small enough L
(a = 0.95, b = 1.5 gives 10.6 at L = 0.2 m), and the hazard run evaluates sizes
the calibration never saw. We clip instead of restricting the prior box
because (i) the region a L_min^-b <= ALPHA_MAX is not a box, and the uniform
box is what the emulator and the samplers work in; (ii) a restriction holds
only on the calibrated sizes, while the clip holds for every L > 0. With the
clip, every finite theta accepted by ``PARAMETER_RANGES`` gives alpha in
[0, ALPHA_MAX] at every size, so every calibration the fit can write is one the
hazard run accepts, and both run the same alpha for a draw (``check_law``
verifies it at calibration time and again in the hazard run). The price: the
likelihood is flat in theta wherever the law is clipped at every calibrated
size, and a reported alpha(L) never exceeds 0.95.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

__all__ = ["ALPHA_MAX", "FORMS", "PARAMETER_RANGES", "alpha_of", "check_fit", "check_law"]

ALPHA_MAX = 0.95

#: law form -> its parameter names (columns of theta, of calibration.json and
#: of the posterior CSV).
FORMS = {"power": ("a", "b"), "constant": ("alpha",)}

#: parameter -> (lower, upper, lower bound inclusive): the values a calibration
#: file may hold (``calib.files.calibration_file``); the prior boxes lie inside.
PARAMETER_RANGES = {"a": (0.0, math.inf, False), "b": (-math.inf, math.inf, True),
                    "alpha": (0.0, 1.0, True)}


def alpha_of(form: str, theta, side_m):
    """Local damping alpha(L) = clip(law(L), 0, ALPHA_MAX) (module docstring).

    Pure and jit-able (``form`` static).

    Args:
        form: "power" (theta = (a, b): law a L^-b) or "constant" (theta = (alpha,)).
        theta: (..., n_params) law parameters.
        side_m: (S,) DEM square sides L, m (``calib.model.entries.dem_side_m``).

    Returns:
        (..., S) alpha per size, dimensionless, in [0, ALPHA_MAX] (NaN only for
        a NaN theta).

    References:
        Paper Sect. 4.1 and Table 1 (alpha decreasing with L); Itasca (1991)
        UDEC User's Manual, theory (local damping, 0 <= alpha < 1).
    """
    theta = jnp.asarray(theta)
    side_m = jnp.asarray(side_m)
    if form == "power":
        a, b = theta[..., 0:1], theta[..., 1:2]
        alpha = a * side_m ** (-b)
    elif form == "constant":
        alpha = theta[..., 0:1] * jnp.ones_like(side_m)
    else:
        raise ValueError(f"unknown alpha law form {form!r}; expected one of {', '.join(FORMS)}")
    return jnp.clip(alpha, 0.0, ALPHA_MAX)


def check_law(form: str, theta, side_m) -> tuple[int, str] | None:
    """Validate law parameters before any simulation (not jit-able).

    A row is accepted when its parameters lie in ``PARAMETER_RANGES`` and its
    alpha(L) (``alpha_of``) lies in [0, ALPHA_MAX] at every side. Used by the
    fit before it writes a calibration and by the hazard run before it
    simulates, so the two accept the same rows.

    Args:
        form: "power" or "constant".
        theta: (T, n_params) law parameters.
        side_m: (S,) square sides L, m.

    Returns:
        None when every row is accepted, else (index of the first bad row, why).
    """
    if form not in FORMS:
        raise ValueError(f"unknown alpha law form {form!r}; expected one of {', '.join(FORMS)}")
    theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
    names = FORMS[form]
    if theta.shape[-1] != len(names):
        raise ValueError(f"alpha law {form!r}: expected {len(names)} parameter(s) "
                         f"({', '.join(names)}), got {theta.shape[-1]}")
    side_m = np.atleast_1d(np.asarray(side_m, dtype=np.float64))
    alpha = np.asarray(alpha_of(form, theta, side_m))
    for t, row in enumerate(theta):
        for name, v in zip(names, row, strict=True):
            lo, hi, incl = PARAMETER_RANGES[name]
            if not (math.isfinite(v) and (v >= lo if incl else v > lo) and v <= hi):
                return t, f"{name} = {v:g} outside {'[' if incl else '('}{lo:g}, {hi:g}]"
        for s, a in zip(side_m, alpha[t], strict=True):
            if not (math.isfinite(a) and 0.0 <= a <= ALPHA_MAX):
                return t, (f"alpha = {a:g} for square side {s:g} m, outside "
                           f"[0, {ALPHA_MAX:g}]")
    return None


def check_fit(form: str, estimate, samples, sizes_m) -> None:
    """Calibration-time check: every parameter set a fit writes (the estimate
    and each posterior draw, ``samples`` (R, P) or None) passes ``check_law`` on
    the fitted sizes, the check ``calib.hazard`` applies before it simulates; with the one
    clipping rule a set that passes at some sizes passes at all, so the hazard
    run accepts the calibration and runs the alpha the fit ran.

    Raises:
        ValueError: naming the first set that would be refused, and why.
    """
    from calib.model.entries import dem_side_m

    est = np.asarray(estimate, float)[None]
    rows = est if samples is None else np.vstack([est, np.asarray(samples, float)])
    bad = check_law(form, rows, dem_side_m(sizes_m))
    if bad is not None:
        i, why = bad
        what = "the estimate" if i == 0 else f"posterior draw {i}"
        raise ValueError(f"DEM calibration: {what} would be refused by calib.hazard: {why}")
