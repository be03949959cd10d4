"""How calib runs the DEM: one configuration for the fit (``calib.model.forward``),
the discrepancy candidates (``calib.discovery.dem_candidates``) and the hazard run
(``calib.hazard``), so that a block of a given size and alpha is simulated the
same way by the calibration and by the hazard run that uses it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from solvers.dem import RUN_STIFFNESS_SCALE, check_run_numerics
from solvers.profile import Profile

__all__ = ["DEM_RUN", "DemRun", "with_max_time"]


@dataclasses.dataclass(frozen=True)
class DemRun:
    """DEM numerics shared by every calib DEM run.

    Attributes:
        stiffness_scale: multiplies the contact stiffnesses kn = ks = 50 GPa/m of
            ``solvers.dem.Params`` (the paper's UDEC values). Our choice,
            ``solvers.dem.RUN_STIFFNESS_SCALE`` (0.01, the default of
            ``python -m solvers.dem`` too): the time step grows 10x, and the
            DEM's documented check (``scripts/dem_reproduce.py``) found runouts
            unchanged within Monte Carlo noise.
        max_time_s: simulated time, s, that every block gets at least; a block
            still moving then has status BUDGET and no runout
            (``calib.model.unfinished``). 150 s: the fit's value (the hazard run used
            120 s before; a block that stops between 120 and 150 s was a runout
            to the fit and unfinished to the hazard).
        dt_size_m: the step bound is set by the stable step of a square of side
            min(dt_size_m, smallest side run), so that runs on different sets of
            sizes at or above it share one compiled program and one step bound.

    The step rule (``options``): explicit central differences with the stable
    step dt(L) of ``solvers.dem.stable_dt`` (dt grows as sqrt(L)); one static
    bound max_steps = ceil(max_time_s / dt(L_ref)), L_ref = min(dt_size_m,
    smallest side), so a block of side L gets max_steps dt(L) >= max_time_s of
    simulated time, the same whichever other sizes share its run as long as
    they are all >= dt_size_m.
    """

    stiffness_scale: float = RUN_STIFFNESS_SCALE
    max_time_s: float = 150.0
    dt_size_m: float = 0.2

    def __post_init__(self):
        check_run_numerics(self.stiffness_scale, self.max_time_s)
        if not (math.isfinite(self.dt_size_m) and self.dt_size_m > 0):
            raise ValueError(f"dt_size_m: expected a positive size, got {self.dt_size_m:g}")

    def params(self, profile: Profile, **kw):
        """``solvers.dem.make_params`` with this stiffness scale (``kw``: other fields,
        e.g. the joint strengths of fragmented blocks)."""
        from solvers import dem

        return dem.make_params(profile, stiffness_scale=self.stiffness_scale, **kw)

    def options(self, params, sides_m, n_fragments: int = 1, **kw):
        """``solvers.dem.Options`` with the step bound of the class docstring.

        Args:
            params: from ``params``.
            sides_m: (S,) square sides that the run simulates, m.
            n_fragments: fragments per block (the step is a fragment's).
            **kw: other ``Options`` fields (e.g. ``adaptive``, ``release_errors``).

        Returns:
            ``solvers.dem.Options`` (static: equal configurations give equal
            options, hence one compiled program).
        """
        from solvers import dem

        side = min(self.dt_size_m, float(np.min(np.asarray(sides_m, float))))
        block = dem.make_block(side, alpha=0.0, n_fragments=n_fragments)
        return dem.Options(max_steps=dem.max_steps_for(self.max_time_s, params, block), **kw)


DEM_RUN = DemRun()


def with_max_time(max_time_s: float, name: str = "max_time_s") -> DemRun:
    """``DEM_RUN`` with ``max_time_s`` of simulated time (a site's, or an option's),
    checked by the DEM's one rule (``solvers.dem.check_run_numerics``).

    Raises:
        ValueError: not a positive time; the message names ``name`` (the option
            or the site file's key).
    """
    check_run_numerics(max_time_s=float(max_time_s), names={"max_time_s": name})
    return dataclasses.replace(DEM_RUN, max_time_s=float(max_time_s))
