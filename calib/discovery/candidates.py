"""The candidate models of the discrepancy workflow, ready to fit.

CRSP: the baseline (Kn, Kt, roughness_m, and with ``base = CRSP_ROLLING_BOX``
the rolling resistance angle; one set for the slope) and the baseline plus
each effect of ``calib.model.effects``, all simulated by
``calib.model.forward.CrspForward`` (the effects run inside the solver,
``solvers.crsp._effects``). ``crsp_model`` builds the baseline with several
effects at once, the models of discovery's later steps. DEM: see
``calib.discovery.dem_candidates``.
"""

from __future__ import annotations

import functools

from calib.discovery.candidate_fit import Candidate
from calib.model.effects import CRSP_EFFECTS, effect_names, full_box, model_label
from calib.model.forward import CrspForward
from calib.model.priors import CRSP_BOX, Box, has_rolling

__all__ = ["crsp_candidates", "crsp_model"]


def _crsp_forward(profile, effect, base, entries, n_blocks, key, stations_x_m=()):
    return CrspForward(profile, entries, n_blocks, key, box=base, effect=effect,
                       stations_x_m=tuple(stations_x_m))


def crsp_model(profile, effects, base: Box = CRSP_BOX) -> Candidate:
    """The baseline ``base`` with ``effects`` (one name, or several switched on
    together in that order, ``calib.model.effects.effect_names``) as a
    ``Candidate`` named by ``model_label`` (e.g. ``size_dissipation+fragmentation``)."""
    names = effect_names(effects)
    effect = names if len(names) > 1 else (names[0] if names else "none")
    return Candidate(model_label(names), full_box(names, profile, base=base),
                     functools.partial(_crsp_forward, profile, effect, base))


def crsp_candidates(profile, effects=CRSP_EFFECTS, base: Box = CRSP_BOX) -> list[Candidate]:
    """Baseline first, then one candidate per effect. Blocks start where
    ``calib.discovery.discrepancy.discover`` releases them (each row's own
    point, or the profile's first vertex). With a baseline that fits the
    rolling resistance (``base = CRSP_ROLLING_BOX``) the ``rolling_resistance``
    effect is part of the baseline and is left out."""
    names = ["none"] + [e for e in effects if e != "none"]
    if has_rolling(base.names):
        names = [e for e in names if e != "rolling_resistance"]
    return [crsp_model(profile, e, base) for e in names]
