"""The inputs of a calibration command: observations, their profile and site,
read and checked together (``Inputs``), the one release of a data set, and
what the rows make the solvers simulate (``Inputs.entries``).

Shared by ``python -m calib.fit`` and ``python -m calib.discover`` (the
commands only parse options and print). Bad input is an ``InputError`` naming
the file, line and column (the commands turn it into one line and exit 2).
"""

from __future__ import annotations

import dataclasses
import functools
import os

import numpy as np

__all__ = ["InputError", "Inputs", "common_release_m", "default_profile", "load_inputs",
           "own_profile"]


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


@functools.cache
def own_profile(path: str):
    """The profile a row names (``Observations.profile``), read once per process:
    every caller gets the same object, which is how the forward models tell
    entries on one profile from entries on another (``profile_parts``).

    Raises:
        InputError: the file does not parse (file, line and column named).
    """
    from solvers.profile import ProfileError, load_profile

    try:
        return load_profile(path)
    except ProfileError as e:
        raise InputError(str(e)) from None


@dataclasses.dataclass(frozen=True)
class Inputs:
    """A calibration command's checked inputs.

    Attributes:
        obs: the observed rows (``calib.files.observations.Observations``).
        profile: the command's profile (``solvers.profile.Profile``).
        profile_path: its file.
        site: its site (``calib.files.site.Site``: station of interest,
            reference values, the rock density).
        speeds: passage speeds at stations
            (``calib.files.observations.Velocities``, its file in ``path``),
            or None.
    """

    obs: object
    profile: object
    profile_path: str
    site: object
    speeds: object = None

    @property
    def release_x_m(self) -> float:
        """The data set's one release (``common_release_m``)."""
        return common_release_m(self.obs, self.profile)

    @property
    def release_errors(self) -> tuple[float, float]:
        """The site's errors (sds) of the tracked release heights and speeds, m and
        m/s (``calib.files.site``), with which CRSP draws its blocks' releases."""
        return self.site.release_height_sd_m, self.site.release_speed_sd_m_s

    @property
    def own_releases(self) -> bool:
        """True where the rows give their own release points or profiles."""
        return bool(np.any(np.isfinite(self.obs.release_x_m)) or any(self.obs.profile))

    def entries(self, tol_m: float | None, row_shapes: bool = False):
        """What the rows make the solvers simulate (``calib.model.entries``), at the
        site's rock density, CRSP blocks in the rows' shape classes with
        ``row_shapes`` (else spheres): with ``tol_m`` (m) and rows that give their own
        releases, one entry per (profile, size, release) group within
        ``tol_m`` (``Entries.from_rows``, rows without a release at the
        profile's first vertex), with the site's release errors on the rows'
        tracked heights and speeds (``Entries.with_release_errors``,
        ``calib.files.site``); else one entry per size at the data set's one
        release (``Entries.one_per_size``, the solvers' default release)."""
        from calib.model.entries import Entries

        rho = self.site.rock_density_kg_m3
        if tol_m is None or not self.own_releases:
            return Entries.one_per_size(self.obs, self.release_x_m, density_kg_m3=rho)
        return Entries.from_rows(self.obs, float(self.profile.x_m[0]), tol_m,
                                 profile_of=own_profile, density_kg_m3=rho,
                                 row_shapes=row_shapes).with_release_errors(
            self.site.release_height_sd_m, self.site.release_speed_sd_m_s)


    def grouping_lines(self, entries, tol_m: float) -> list[str]:
        """How the rows' own releases were grouped into ``entries``
        (``Inputs.entries(tol_m)``), in lines for a command to print: the number
        of simulated releases and the largest shift of a row's release point,
        speed and height to its group's; the rows on their own profiles; the
        CRSP shape classes, where some row is not a sphere; the site's release
        errors."""
        obs, x0 = self.obs, float(self.profile.x_m[0])
        rel = np.asarray(obs.release_x_m, float)
        err = np.abs(entries.release_x_m[entries.index] - np.where(np.isfinite(rel), rel, x0))
        lines = [f"each row released from its own point, rows of one size within {tol_m:g} m "
                 f"grouped: {entries.n} simulated releases for {obs.n_obs} rows (largest "
                 f"release shift {err.max():.2f} m)"]
        own = [p for p in dict.fromkeys(obs.profile) if p]
        if own:
            lines.append("rows on their own profiles: " + "; ".join(
                f"{int(np.sum(obs.profile == p))} on {p}" for p in own)
                + f"; {int(np.sum(obs.profile == ''))} on {self.profile_path}")
        shapes = entries.shapes[entries.index]
        given = (np.asarray(["sphere" if not f else str(f) for f in obs.shape], dtype=object)
                 if getattr(obs, "shape", None) is not None else shapes)
        if np.any(shapes != "sphere"):
            lines.append("CRSP simulates each row's block in its shape class, of the volume of "
                         "the sphere of its block_size_m: " + ", ".join(
                             f"{int(np.sum(shapes == f))} rows {f}" for f in dict.fromkeys(shapes))
                         + " (the DEM: squares)")
        elif np.any(given != "sphere"):
            lines.append("the rows' shape column gives " + ", ".join(
                f"{int(np.sum(given == f))} {f}" for f in dict.fromkeys(given))
                + "; every row is simulated as a sphere of its block_size_m (--row-shapes "
                "simulates each in its CRSP class)")
        speed, height = (np.asarray(v, float) for v in (obs.release_speed_m_s,
                                                         obs.release_height_m))
        gspeed, gheight = (v[entries.index] for v in (entries.release_speed_m_s,
                                                      entries.release_height_m))
        known = np.isfinite(speed) & np.isfinite(gspeed)
        if known.any():
            lines.append(f"each group released at its rows' mean tracked speed (largest "
                         f"release-speed shift {np.abs(gspeed - speed)[known].max():.2f} m/s)")
        site = self.site
        if site.release_height_sd_m or site.release_speed_sd_m_s:
            lines.append(f"each block (CRSP's and the DEM's) draws its release height and speed "
                         f"about its group's, sd {site.release_height_sd_m:g} m and "
                         f"{site.release_speed_sd_m_s:g} m/s (the site file {site.path})")
        high = np.isfinite(height)
        if high.any():
            lines.append(f"each group released at its rows' mean height above the ground, "
                         f"{np.nanmin(entries.release_height_m):.2f} to "
                         f"{np.nanmax(entries.release_height_m):.2f} m (largest release-height "
                         f"shift {np.abs(gheight - height)[high].max():.2f} m)")
        return lines


def load_inputs(data: str, profile_arg: str | None, out: str,
                velocities: str | None = None) -> Inputs:
    """Profile, its site, observations and passage speeds, checked for a command
    (``InputError`` on bad input): the files exist and parse, every runout
    lies on the profile, every speed station inside it, ``out`` can be a
    folder. Shared by ``calib.fit`` and ``calib.discover``.

    Args:
        data: the observations CSV (``calib.files.observations``).
        profile_arg: the profile CSV; None: ``default_profile(data)``.
        out: the command's output folder (need not exist).
        velocities: a CSV of passage speeds at stations
            (``calib.files.observations.load_velocities``, every station
            strictly inside the profile); None: none.
    """
    from calib.files.observations import (
        ObservationError,
        load_observations,
        load_velocities,
        rows_on_profile,
    )
    from calib.files.site import SiteError, load_site
    from solvers.profile import ProfileError, load_profile

    profile_path = profile_arg or default_profile(data)
    if not os.path.isfile(data):  # named before its profile, which is found next to it
        raise InputError(f"{data}: no such file")
    if not os.path.isfile(profile_path):
        raise InputError(f"{profile_path}: no such profile file (give --profile)")
    try:
        profile = load_profile(profile_path)
        site = load_site(profile_path)
        obs = rows_on_profile(load_observations(data), profile, profile_path, own_profile)
        speeds = None if velocities is None else load_velocities(velocities,
                                                                 profile.x_range_m)
    except (ProfileError, SiteError, ObservationError) as e:
        raise InputError(str(e)) from None
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"--out {out}: exists and is not a folder")
    return Inputs(obs, profile, profile_path, site, speeds)
