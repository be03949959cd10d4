"""Candidate effects of the discrepancy workflow: names, parameters, priors, truths.

Each effect is a switchable extension of the solvers with its own parameters
(the physics and its sources: ``solvers.crsp._effects`` for CRSP,
``solvers.dem`` for the DEM's damping law and bonded fragments). This module
only says, for the calibration side, which parameters an effect adds, over
which prior box, how they map onto solver parameters, and what "strength S"
means when synthetic data are made with the effect switched on.

CRSP effects (theta = (Kn, Kt, roughness_m) + the effect's columns):

=====================  ==========================  ===================  ==================
effect                 extra columns               prior box            truth at strength S
=====================  ==========================  ===================  ==================
size_dissipation       gamma (restitution          [-0.6, 0.6]          gamma = 0.25 S
                       ``K (d / 1 m)^gamma``)
fragmentation          log10_frag_energy_kJ        [1, 4] (10 kJ-10 MJ) E_f = 300 kJ / S
rolling_resistance     delta_mu                    [0, 1]               delta_mu = 0.4 S
vegetation_belt        belt_start_m, belt_loss     [x0 + 0.3 W,         start x0 + 0.43 W,
                       (belt width 0.15 W fixed)   x1 - 0.15 W], [0,.8] loss = 0.4 S
=====================  ==========================  ===================  ==================

(W: the profile's horizontal extent x1 - x0; on Postignano the truth belt is
129-174 m, on the gentle runout zone below the 110 m slope break.) The boxes and
strengths are assumptions of this toolkit, not published values: the boxes span
"no effect" to "dominant effect"; strength 1 ("moderate") was chosen, before
any workflow run, as the value that moves the median runout of the most
affected size class by roughly 30-80 m on Postignano with the base truth
``SYNTH_BASE`` (the measured effects are in ``data/README.md``).

DEM effects (the paper's: damping and fragmentation): the baseline is one
damping coefficient for all sizes (theta = (alpha,)); ``size_dissipation`` is
the power law alpha(L) = a L^-b (theta = (a, b)); ``fragmentation`` is one alpha
plus 2 x 2 bonded fragments whose joints have tensile strength and cohesion
10^log10_joint_strength_pa (theta = (alpha, log10_joint_strength_pa)).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from calib.model.priors import CRSP_BOX, DEM_BOXES, Box, has_rolling

__all__ = [
    "CRSP_EFFECTS",
    "DEM_EFFECTS",
    "EFFECTS",
    "EFFECT_NAMES",
    "Effect",
    "effect",
    "SYNTH_BASE",
    "belt_geometry_m",
    "crsp_overrides",
    "effect_box",
    "full_box",
    "truth",
]

# base CRSP truth of synthetic data: close to the Postignano calibration
# (Kn 0.44, Kt 0.96, S 0.37 m): 2 m blocks reach a median of 220 m.
SYNTH_BASE = (0.40, 0.96, 0.40)
BELT_WIDTH_FRAC = 0.15


def belt_geometry_m(profile) -> tuple[float, float, float]:
    """(lowest start, highest start, width) of the vegetation belt on ``profile``, m."""
    x0, x1 = float(profile.x_m[0]), float(profile.x_m[-1])
    w = x1 - x0
    return x0 + 0.3 * w, x1 - BELT_WIDTH_FRAC * w, BELT_WIDTH_FRAC * w


def _no_overrides(e, profile):
    return {}


def _belt_overrides(e, profile):
    width = belt_geometry_m(profile)[2]
    return {"belt_start_m": e[:, 0], "belt_end_m": e[:, 0] + width, "belt_loss": e[:, 1]}


def _belt_truth(strength, profile):
    x0, x1 = float(profile.x_m[0]), float(profile.x_m[-1])
    return [x0 + 0.43 * (x1 - x0), min(0.4 * strength, 0.95)]


def _belt_box(profile):
    lo, hi, _ = belt_geometry_m(profile)
    return Box(("belt_start_m", "belt_loss"), (lo, 0.0), (hi, 0.8))


def _fragment_box():
    one = DEM_BOXES["constant"]  # the fit's boxes (calib.model.priors), one copy
    return Box(one.names + ("log10_joint_strength_pa",), one.lower + (4.0,), one.upper + (7.0,))


@dataclasses.dataclass(frozen=True)
class Effect:
    """One candidate effect, declared once (the table of the module docstring).

    Attributes:
        name: the effect's name on the command line and in outputs.
        crsp_box: profile -> prior box of the columns it adds to CRSP's theta.
        crsp_overrides: (extra (T, k), profile) -> CRSP ``Params`` fields (the
            solver switch; the physics is in ``solvers.crsp._effects``).
        crsp_truth: (strength, profile) -> its columns in synthetic data.
        dem_box: () -> the DEM candidate's whole prior box, or None (no DEM form).
        dem_truth: strength -> the DEM candidate's parameters in synthetic data.
        dem_grid: points per axis of the DEM candidate's design grid.
    """

    name: str
    crsp_box: Callable[[object], Box]
    crsp_overrides: Callable[[np.ndarray, object], dict]
    crsp_truth: Callable[[float, object], list]
    dem_box: Callable[[], Box] | None = None
    dem_truth: Callable[[float], list] | None = None
    dem_grid: tuple[int, ...] | None = None


#: The registry: every effect, in the order candidates are tried.
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("none", lambda profile: Box((), (), ()), _no_overrides, lambda s, profile: [],
           dem_box=lambda: DEM_BOXES["constant"], dem_truth=lambda s: [0.40],
           dem_grid=(16,)),
    Effect("size_dissipation", lambda profile: Box(("gamma",), (-0.6,), (0.6,)),
           lambda e, profile: {"restitution_size_exponent": e[:, 0]},
           lambda s, profile: [0.25 * s],
           dem_box=lambda: DEM_BOXES["power"], dem_truth=lambda s: [0.40, 0.5 * s],
           dem_grid=(8, 8)),
    Effect("fragmentation", lambda profile: Box(("log10_frag_energy_kJ",), (1.0,), (4.0,)),
           lambda e, profile: {"frag_energy_kJ": 10.0 ** e[:, 0]},
           lambda s, profile: [np.log10(300.0 / s)],
           dem_box=_fragment_box, dem_truth=lambda s: [0.40, 5.0 - s], dem_grid=(4, 3)),
    Effect("rolling_resistance", lambda profile: Box(("delta_mu",), (0.0,), (1.0,)),
           lambda e, profile: {"rolling_resistance": e[:, 0]},
           lambda s, profile: [0.4 * s]),
    Effect("vegetation_belt", _belt_box, _belt_overrides, _belt_truth),
)}

EFFECT_NAMES = tuple(EFFECTS)
CRSP_EFFECTS = EFFECT_NAMES
DEM_EFFECTS = tuple(n for n, e in EFFECTS.items() if e.dem_box is not None)


def effect(name: str, model: str = "crsp") -> Effect:
    """The registry's declaration of ``name``; a ValueError naming the choices if
    it is unknown or has no form for ``model``."""
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; expected one of {', '.join(EFFECT_NAMES)}")
    e = EFFECTS[name]
    if model == "dem" and e.dem_box is None:
        raise ValueError(f"effect {name!r} is not available for the DEM; expected one of "
                         f"{', '.join(DEM_EFFECTS)}")
    return e


def effect_box(name: str, profile, model: str = "crsp") -> Box:
    """Prior box of the effect's extra parameters (CRSP) or of the whole law (DEM)."""
    e = effect(name, model)
    return e.dem_box() if model == "dem" else e.crsp_box(profile)


def full_box(name: str, profile, model: str = "crsp", base: Box = CRSP_BOX) -> Box:
    """Prior box of all parameters of a candidate model (CRSP: the baseline box
    ``base``, ``CRSP_BOX`` or ``CRSP_ROLLING_BOX`` with the rolling resistance
    fitted, then the effect's columns)."""
    extra = effect_box(name, profile, model)
    if model == "dem":
        return extra
    if name == "rolling_resistance" and has_rolling(base.names):
        raise ValueError("the rolling_resistance effect adds to a rolling resistance the "
                         "baseline already fits (rolling_friction_deg): the two are one "
                         "parameter")
    twice = [n for n in extra.names if n in base.names]
    if twice:
        raise ValueError(f"the base box already has the {name} effect's parameter(s) "
                         f"{', '.join(twice)}")
    return Box(base.names + extra.names, base.lower + extra.lower, base.upper + extra.upper)


def crsp_overrides(name: str, extra, profile) -> dict[str, np.ndarray]:
    """CRSP ``Params`` fields (arrays (T,)) of the effect's columns ``extra`` (T, k)."""
    return effect(name).crsp_overrides(np.atleast_2d(np.asarray(extra, float)), profile)


def truth(name: str, strength: float, profile, model: str = "crsp") -> np.ndarray:
    """Full parameter vector of synthetic data with ``effect`` at ``strength``.

    CRSP: ``SYNTH_BASE`` + the effect's columns (table in the module docstring).
    DEM: none -> alpha 0.40; size_dissipation -> a = 0.40, b = 0.5 S (Table 1's
    trend at S = 1); fragmentation -> alpha 0.40 and joint strength
    10^(5 - S) Pa (0.1 MPa at S = 1, the DEM's default joint strength; above
    S = 1 it lies below the candidate's prior box, 10^4-10^7 Pa, so the
    candidate cannot reach the truth: a limit of the DEM studies).
    """
    if not (np.isfinite(strength) and strength > 0):
        raise ValueError(f"strength must be a positive number, got {strength}")
    e = effect(name, model)
    if model == "dem":
        return np.asarray(e.dem_truth(strength), float)
    return np.concatenate([np.asarray(SYNTH_BASE, float),
                           np.asarray(e.crsp_truth(strength, profile), float)])
