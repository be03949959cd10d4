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

Several CRSP effects can be switched on together (``effect_names``; a model
is named by ``model_label``, e.g. ``size_dissipation+fragmentation``): each
has its own solver fields, so their columns simply follow one another in
theta (``full_box``, ``crsp_overrides``). ``python -m calib.fit --effect``
fits such a model, ``calibration.json`` records it (``crsp.effects``), and the
hazard run and the predictive check map each draw's columns back onto the
solver (``draw_overrides``) as the fit did.

DEM effects (the paper's: damping and fragmentation): the baseline is one
damping coefficient for all sizes (theta = (alpha,)); ``size_dissipation`` is
the power law alpha(L) = a L^-b (theta = (a, b)); ``fragmentation`` is one alpha
plus 2 x 2 bonded fragments whose joints have tensile strength and cohesion
10^log10_joint_strength_pa (theta = (alpha, log10_joint_strength_pa)).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from calib.model.priors import CRSP_BOX, DEM_BOXES, Box, has_rolling, rest_possible_box

__all__ = [
    "CRSP_EFFECTS",
    "DEM_EFFECTS",
    "EFFECTS",
    "EFFECT_NAMES",
    "Effect",
    "effect",
    "SYNTH_BASE",
    "belt_geometry_m",
    "check_combination",
    "crsp_overrides",
    "draw_overrides",
    "effect_box",
    "effect_columns",
    "effect_names",
    "full_box",
    "model_label",
    "rest_possible_base",
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
        columns: the names of the columns it adds to CRSP's theta (the names of
            ``crsp_box``'s box, known without a profile).
        crsp_box: profile -> prior box of the columns it adds to CRSP's theta.
        crsp_overrides: (extra (T, k), profile) -> CRSP ``Params`` fields (the
            solver switch; the physics is in ``solvers.crsp._effects``).
        crsp_truth: (strength, profile) -> its columns in synthetic data.
        valid: column -> (lower, upper, lower inclusive): the values the solver
            can run (wider than the prior box; a calibration file's values are
            checked against them, ``calib.files.calibration_file``).
        dem_box: () -> the DEM candidate's whole prior box, or None (no DEM form).
        dem_truth: strength -> the DEM candidate's parameters in synthetic data.
        dem_grid: points per axis of the DEM candidate's design grid.
        adds_rolling_resistance: the effect raises the rolling resistance
            somewhere, so blocks may come to rest where the baseline's angle
            alone lets none (``calib.model.priors.rest_possible_box``).
    """

    name: str
    columns: tuple[str, ...]
    crsp_box: Callable[[object], Box]
    crsp_overrides: Callable[[np.ndarray, object], dict]
    crsp_truth: Callable[[float, object], list]
    valid: dict = dataclasses.field(default_factory=dict)
    dem_box: Callable[[], Box] | None = None
    dem_truth: Callable[[float], list] | None = None
    dem_grid: tuple[int, ...] | None = None
    adds_rolling_resistance: bool = False


_ANY = (-math.inf, math.inf, True)

#: The registry: every effect, in the order candidates are tried.
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("none", (), lambda profile: Box((), (), ()), _no_overrides, lambda s, profile: [],
           dem_box=lambda: DEM_BOXES["constant"], dem_truth=lambda s: [0.40],
           dem_grid=(16,)),
    Effect("size_dissipation", ("gamma",), lambda profile: Box(("gamma",), (-0.6,), (0.6,)),
           lambda e, profile: {"restitution_size_exponent": e[:, 0]},
           lambda s, profile: [0.25 * s], valid={"gamma": _ANY},
           dem_box=lambda: DEM_BOXES["power"], dem_truth=lambda s: [0.40, 0.5 * s],
           dem_grid=(8, 8)),
    Effect("fragmentation", ("log10_frag_energy_kJ",),
           lambda profile: Box(("log10_frag_energy_kJ",), (1.0,), (4.0,)),
           lambda e, profile: {"frag_energy_kJ": 10.0 ** e[:, 0]},
           lambda s, profile: [np.log10(300.0 / s)], valid={"log10_frag_energy_kJ": _ANY},
           dem_box=_fragment_box, dem_truth=lambda s: [0.40, 5.0 - s], dem_grid=(4, 3)),
    Effect("rolling_resistance", ("delta_mu",), lambda profile: Box(("delta_mu",), (0.0,), (1.0,)),
           lambda e, profile: {"rolling_resistance": e[:, 0]},
           lambda s, profile: [0.4 * s], valid={"delta_mu": (0.0, math.inf, True)},
           adds_rolling_resistance=True),
    Effect("vegetation_belt", ("belt_start_m", "belt_loss"), _belt_box, _belt_overrides,
           _belt_truth, valid={"belt_start_m": _ANY, "belt_loss": (0.0, 1.0 - 1e-9, True)},
           adds_rolling_resistance=True),
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


def effect_names(effects) -> tuple[str, ...]:
    """The CRSP effects switched on together, as a tuple in their order: ``effects``
    is one name, "none" (no effect: ()), or a sequence of names. A ValueError
    for an unknown name or a name given twice.

    Every combination of distinct CRSP effects can run together: each has its
    own ``Params`` fields (``solvers.crsp._effects``), and where two act on the
    same quantity the solver composes them (the rolling resistance and the
    belt's add to the rolling phase's ``tan(phi_r)``; a fragment's restitution
    is size-scaled at its own radius). The one combination refused is
    ``rolling_resistance`` on a baseline that fits the rolling angle
    (``full_box``)."""
    names = (effects,) if isinstance(effects, str) else tuple(effects)
    out = tuple(n for n in names if n != "none")
    for n in out:
        effect(n)
    twice = sorted({n for n in out if out.count(n) > 1})
    if twice:
        raise ValueError(f"effect {', '.join(twice)} given twice")
    return out


def model_label(effects) -> str:
    """The name of the baseline with ``effects`` added: "none", or the effects
    joined by "+" in their order (e.g. ``size_dissipation+fragmentation``)."""
    return "+".join(effect_names(effects)) or "none"


def effect_columns(effects) -> tuple[str, ...]:
    """The theta columns the CRSP ``effects`` (``effect_names``) add, in order."""
    return tuple(c for n in effect_names(effects) for c in EFFECTS[n].columns)


def effect_box(name, profile, model: str = "crsp") -> Box:
    """Prior box of the effect's extra parameters (CRSP; ``name`` may be several
    effects, ``effect_names``: their boxes one after the other) or of the whole
    law (DEM: one name)."""
    if model == "dem":
        return effect(name, model).dem_box()
    boxes = [EFFECTS[n].crsp_box(profile) for n in effect_names(name)]
    return Box(*(tuple(v for b in boxes for v in getattr(b, f))
                 for f in ("names", "lower", "upper")))


def check_combination(effects, base_names) -> tuple[str, ...]:
    """``effect_names(effects)``, after checking that they can join a baseline with
    parameters ``base_names``: a ValueError for ``rolling_resistance`` on a
    baseline that fits the rolling resistance angle (one parameter, not two)."""
    names = effect_names(effects)
    if "rolling_resistance" in names and has_rolling(base_names):
        raise ValueError("the rolling_resistance effect adds to a rolling resistance the "
                         "baseline already fits (rolling_friction_deg): the two are one "
                         "parameter")
    return names


def rest_possible_base(base: Box, profiles, effects=()) -> Box:
    """The CRSP baseline box ``base`` with its one rolling angle bounded below
    where a block can rest on ``profiles`` (``calib.model.priors.
    rest_possible_box``), unless one of ``effects`` adds rolling resistance
    (the forest belt lets blocks rest where the angle alone does not)."""
    if any(EFFECTS[n].adds_rolling_resistance for n in effect_names(effects)):
        return base
    return rest_possible_box(base, profiles)


def full_box(name, profile, model: str = "crsp", base: Box = CRSP_BOX) -> Box:
    """Prior box of all parameters of a candidate model (CRSP: the baseline box
    ``base``, ``CRSP_BOX`` or ``CRSP_ROLLING_BOX`` with the rolling resistance
    fitted, then the columns of the effect, or of each effect of a sequence in
    its order)."""
    extra = effect_box(name, profile, model)
    if model == "dem":
        return extra
    check_combination(name, base.names)
    twice = [n for n in extra.names if n in base.names]
    if twice:
        raise ValueError(f"the base box already has the {model_label(name)} effect's "
                         f"parameter(s) {', '.join(twice)}")
    return Box(base.names + extra.names, base.lower + extra.lower, base.upper + extra.upper)


def crsp_overrides(name, extra, profile) -> dict[str, np.ndarray]:
    """CRSP ``Params`` fields (arrays (T,)) of the effects' columns ``extra`` (T, k):
    ``name`` one effect or several (``effect_names``), their columns in that order."""
    extra = np.atleast_2d(np.asarray(extra, float))
    n_cols = len(effect_columns(name))
    if n_cols != extra.shape[1]:
        raise ValueError(f"the effects {model_label(name)} have {n_cols} column(s), got "
                         f"{extra.shape[1]}")
    out, j = {}, 0
    for n in effect_names(name):
        e = EFFECTS[n]
        out.update(e.crsp_overrides(extra[:, j:j + len(e.columns)], profile))
        j += len(e.columns)
    return out


def draw_overrides(effects, names, values, profile) -> dict:
    """``solvers.crsp.params_from_profile`` overrides of ONE parameter set
    (``names``, ``values``: a posterior draw or point estimate of a calibration
    with ``effects``): the baseline's columns (the first ones) as
    ``calib.model.forward.named_overrides`` gives them, the effects' columns (the
    last ones, ``effect_columns``) mapped by ``crsp_overrides``, as the fit's
    ``CrspForward.params`` maps them; scalars."""
    from calib.model.forward import named_overrides

    names, values = tuple(names), [float(v) for v in values]
    cols = effect_columns(effects)
    n_base = len(names) - len(cols)
    if n_base < 0 or names[n_base:] != cols:
        raise ValueError(f"parameters {', '.join(names)} do not end with the columns "
                         f"{', '.join(cols)} of the effects {model_label(effects)}")
    out = named_overrides(names[:n_base], values[:n_base], profile)
    if cols:
        extra = crsp_overrides(effects, np.asarray(values[n_base:])[None], profile)
        out.update({k: float(np.asarray(v).reshape(-1)[0]) for k, v in extra.items()})
    return out


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
