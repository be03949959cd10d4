"""The candidate models of the discrepancy workflow, ready to fit.

CRSP: the baseline (Kn, Kt, roughness_m, and with ``base = CRSP_ROLLING_BOX``
the rolling resistance angle; one set for the slope) and the baseline plus
each effect of ``calib.model.effects``, all simulated by
``calib.model.forward.CrspForward`` (the effects run inside the solver,
``solvers.crsp._effects``). DEM: see ``calib.discovery.dem_candidates``.
"""

from __future__ import annotations

import functools

from calib.discovery.discrepancy import Candidate
from calib.model.effects import CRSP_EFFECTS, full_box
from calib.model.forward import CrspForward
from calib.model.priors import CRSP_BOX, Box, has_rolling

__all__ = ["crsp_candidates"]


def _crsp_forward(profile, effect, base, entries, n_blocks, key, stations_x_m=()):
    return CrspForward(profile, entries, n_blocks, key, box=base, effect=effect,
                       stations_x_m=tuple(stations_x_m))


def crsp_candidates(profile, effects=CRSP_EFFECTS, base: Box = CRSP_BOX) -> list[Candidate]:
    """Baseline first, then one candidate per effect. Blocks start where
    ``calib.discovery.discrepancy.discover`` releases them (each row's own
    point, or the profile's first vertex). With a baseline that fits the
    rolling resistance (``base = CRSP_ROLLING_BOX``) the ``rolling_resistance``
    effect is part of the baseline and is left out."""
    names = ["none"] + [e for e in effects if e != "none"]
    if has_rolling(base.names):
        names = [e for e in names if e != "rolling_resistance"]
    return [Candidate(e, full_box(e, profile, base=base),
                      functools.partial(_crsp_forward, profile, e, base))
            for e in names]
