"""The inputs of a calibration command: observations and their profile, read and
checked together, and the one release of a data set.

Shared by ``python -m calib.fit`` and ``python -m calib.discover`` (the
commands only parse options and print). Bad input is an ``InputError`` naming
the file, line and column (the commands turn it into one line and exit 2).
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["InputError", "common_release_m", "default_profile", "load_inputs"]


class InputError(ValueError):
    """Bad calibration input; the message names the file, line and column."""


def default_profile(data: str) -> str:
    """``<data stem>_profile.csv`` next to DATA, or, where that does not exist, a
    ``profile.csv`` in DATA's folder (a site folder such as data/tschamut2014/)."""
    stem, _ = os.path.splitext(data)
    named = stem + "_profile.csv"
    folder = os.path.join(os.path.dirname(data), "profile.csv")
    return named if os.path.isfile(named) or not os.path.isfile(folder) else folder


def common_release_m(obs, profile) -> float:
    """One release abscissa for the whole data set: the median of the rows'
    ``release_x_m`` where the data give it, else the profile's first vertex.
    The fits release each row from its own point (``release_groups``); this one
    release is where the runout-vs-size figure is simulated, and the default
    release of ``calib.hazard`` (recorded as ``release_x_m`` in calibration.json)."""
    rel = getattr(obs, "release_x_m", None)
    if rel is None or not np.any(np.isfinite(rel)):
        return float(profile.x_m[0])
    return float(np.nanmedian(rel))


def _check_reach(obs, profile, profile_path: str) -> None:
    """Every row's release lies on the profile and its observed runout between
    that release and the profile's end."""
    start, x1 = float(profile.x_m[0]), float(profile.x_m[-1])
    rel = np.asarray(getattr(obs, "release_x_m", np.full(obs.n_obs, np.nan)), float)
    for i in range(obs.n_obs):
        x0 = rel[i] if np.isfinite(rel[i]) else start
        if not start <= x0 < x1:
            raise InputError(f"{obs.path}: line {i + 2}, column 'release_x_m': release {x0:g} m "
                           f"lies outside the profile {profile_path} ({start:g} to {x1:g} m)")
        col, val = (("runout_min_m", obs.runout_min_m[i]) if obs.is_interval[i]
                    else ("runout_m", obs.runout_m[i]))
        if val > x1 - x0:
            raise InputError(f"{obs.path}: line {i + 2}, column {col!r}: runout {val:g} m lies "
                           f"beyond the end of the profile {profile_path} (it covers "
                           f"{x1 - x0:g} m from the release at x = {x0:g} m); the blocks can "
                           f"never reach it")


def load_inputs(data: str, profile_arg: str | None, out: str):
    """Observations, profile and its path, checked for a command (``InputError``
    on bad input): the files exist and parse, every runout lies on the profile, ``out``
    can be a folder. Shared by ``calib.fit`` and ``calib.discover``."""
    from calib.files.observations import ObservationError, load_observations
    from solvers.profile import ProfileError, load_profile

    profile_path = profile_arg or default_profile(data)
    try:
        obs = load_observations(data)
    except ObservationError as e:
        raise InputError(str(e)) from None
    if not os.path.isfile(profile_path):
        raise InputError(f"{profile_path}: no such profile file (give --profile)")
    try:
        profile = load_profile(profile_path)
    except ProfileError as e:
        raise InputError(str(e)) from None
    _check_reach(obs, profile, profile_path)
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"--out {out}: exists and is not a folder")
    return obs, profile, profile_path
