"""The candidate models of the discrepancy workflow, ready to fit.

CRSP: the baseline (Kn, Kt, roughness_m, and with ``base = CRSP_ROLLING_BOX``
the rolling resistance angle; one set for the slope) and the baseline plus
each effect of ``calib.model.effects``, all simulated by
``calib.model.forward.CrspForward`` (the effects run inside the solver,
``solvers.crsp._effects``). ``crsp_model`` builds the baseline with several
effects at once, the models of discovery's later steps. DEM: see
``calib.discovery.dem_candidates``. ``candidate_set`` chooses the candidates
of a run by model and effect names (``python -m calib.discover``'s
``--model``, ``--effects`` and ``--rolling-resistance``).
"""

from __future__ import annotations

import functools

from calib.discovery.candidate_fit import Candidate
from calib.model.effects import (
    CRSP_EFFECTS,
    DEM_EFFECTS,
    effect_names,
    full_box,
    model_label,
    rest_possible_base,
)
from calib.model.forward import CrspForward
from calib.model.priors import CRSP_BOX, CRSP_ROLLING_BOX, Box, has_rolling
from solvers.crsp import ROLLING_THRESHOLD_M_S

__all__ = ["DEM_DEFAULT", "candidate_set", "crsp_candidates", "crsp_model"]

# The DEM's fragmentation candidate (2 x 2 bonded fragments) is opt-in: on
# Postignano its 12-point grid took 1548 s of a 1738 s run (2 cores, under load),
# and 1517 s of 1865 s with each block side in calls of its own (2026-12-07).
DEM_DEFAULT = ("none", "size_dissipation")


def _crsp_forward(profile, effect, base, threshold, entries, n_blocks, key, stations_x_m=()):
    return CrspForward(profile, entries, n_blocks, key, box=base, effect=effect,
                       stations_x_m=tuple(stations_x_m), rolling_threshold_m_s=threshold)


def crsp_model(profile, effects, base: Box = CRSP_BOX,
               rolling_threshold_m_s: float = ROLLING_THRESHOLD_M_S) -> Candidate:
    """The baseline ``base`` with ``effects`` (one name, or several switched on
    together in that order, ``calib.model.effects.effect_names``) as a
    ``Candidate`` named by ``model_label`` (e.g. ``size_dissipation+fragmentation``),
    simulated with the rolling threshold ``rolling_threshold_m_s`` (the site's,
    ``calib.files.site``). A fitted rolling angle starts where a block can rest
    on ``profile``, as in ``calib.fit`` (``calib.model.effects.rest_possible_base``)."""
    names = effect_names(effects)
    effect = names if len(names) > 1 else (names[0] if names else "none")
    base = rest_possible_base(base, [profile], names)
    return Candidate(model_label(names), full_box(names, profile, base=base),
                     functools.partial(_crsp_forward, profile, effect, base,
                                       float(rolling_threshold_m_s)))


def crsp_candidates(profile, effects=CRSP_EFFECTS, base: Box = CRSP_BOX,
                    rolling_threshold_m_s: float = ROLLING_THRESHOLD_M_S) -> list[Candidate]:
    """Baseline first, then one candidate per effect. Blocks start where
    ``calib.discovery.discrepancy.discover`` releases them (each row's own
    point, or the profile's first vertex). With a baseline that fits the
    rolling resistance (``base = CRSP_ROLLING_BOX``) the ``rolling_resistance``
    effect is part of the baseline and is left out. Every candidate runs with
    the rolling threshold ``rolling_threshold_m_s``."""
    names = ["none"] + [e for e in effects if e != "none"]
    if has_rolling(base.names):
        names = [e for e in names if e != "rolling_resistance"]
    return [crsp_model(profile, e, base, rolling_threshold_m_s) for e in names]


def candidate_set(model: str, effects=None, profile=None, rolling: str = "profile",
                  rolling_threshold_m_s: float = ROLLING_THRESHOLD_M_S, dem_run=None):
    """The candidates of one discovery run and how later steps combine effects.

    Args:
        model: "crsp" or "dem".
        effects: effect names to try (a sequence, or one comma-separated text);
            None: every CRSP effect, or ``DEM_DEFAULT`` for the DEM.
        profile: the slope profile (``solvers.profile.Profile``).
        rolling: CRSP baseline: "profile" (the profile's per-zone rolling
            resistance, Kn, Kt, S fitted) or "fit" (the rolling resistance angle
            fitted too, ``CRSP_ROLLING_BOX``; the ``rolling_resistance`` effect is
            then part of the baseline and left out).
        rolling_threshold_m_s: CRSP's rolling threshold, m/s (the site's,
            ``calib.files.site``); the DEM has none.
        dem_run: the DEM's numerics (``calib.model.dem_run.DemRun``; None:
            ``DEM_RUN``), e.g. with the site's simulated time.

    Returns:
        (candidates, baseline first, as ``calib.discovery.discrepancy.discover``
        takes them; ``combine``: effects -> the baseline with them, for the
        later steps, or None for the DEM, whose candidates cannot be combined).

    Raises:
        ValueError: an effect the model does not have, none at all, or a
            choice that contradicts ``rolling`` (the message names the option
            of ``python -m calib.discover`` that gives it).
    """
    allowed = CRSP_EFFECTS if model == "crsp" else DEM_EFFECTS
    if effects is None:
        chosen = list(allowed) if model == "crsp" else list(DEM_DEFAULT)
    else:
        parts = effects.split(",") if isinstance(effects, str) else effects
        chosen = [e.strip() for e in parts if e.strip()]
        bad = [e for e in chosen if e not in allowed]
        if bad or not chosen:
            raise ValueError(f"--effects: {', '.join(bad) or '(empty)'}: expected effects of "
                             f"the {model} model among "
                             f"{', '.join(a for a in allowed if a != 'none')}")
    if model == "crsp":
        if rolling == "fit":
            if effects is not None and "rolling_resistance" in chosen:
                raise ValueError("--effects rolling_resistance: with --rolling-resistance fit "
                                 "the baseline already fits the rolling resistance angle; "
                                 "leave it out or use --rolling-resistance profile")
            base = CRSP_ROLLING_BOX
        else:
            base = CRSP_BOX
        return (crsp_candidates(profile, chosen, base, rolling_threshold_m_s),
                functools.partial(crsp_model, profile, base=base,
                                  rolling_threshold_m_s=rolling_threshold_m_s))
    if rolling == "fit":
        raise ValueError("--rolling-resistance fit: the rolling resistance is a CRSP "
                         "parameter; the DEM candidates have none")
    from calib.discovery.dem_candidates import dem_candidates

    return (dem_candidates(profile, chosen) if dem_run is None
            else dem_candidates(profile, chosen, dem_run)), None
