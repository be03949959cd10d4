"""Prior ranges of the calibrated parameters, with their sources.

All priors are uniform on a box: the published ranges are ranges, not
distributions, and a uniform box makes the posterior's shape come from the data
alone. The gradient fit searches the same box.

CRSP (restitution coefficients are velocity ratios, dimensionless):

* Kn in [0.15, 0.60]. CRSP's parameter tables (Jones et al. 2000, CRSP 4.0
  manual, as reproduced in a Colorado DRMS mine-permit report, "Table 4: CRSP3
  Parameter Ranges for Representative Site Conditions") give normal
  coefficients 0.28-0.37 for colluvium, talus and sandstone faces; NOTES.md
  recalls 0.37-0.42 for smooth hard surfaces (unverified). The paper uses 0.41.
  The box doubles the width around 0.28-0.42 (assumption).
* Kt in [0.60, 0.98]. Same sources: tangential 0.78-0.87 (0.87-0.92 for smooth
  hard surfaces, recalled); the paper uses 0.87. Widened below to 0.60 so that
  soft ground is admitted (assumption); 1.0 (no tangential loss) excluded.
  The Tschamut runs bound Kt from below only: scored by the simulator alone,
  their likelihood rises to Kt ~ 0.92 and is flat to 0.98 (docs/studies.md, "The
  simulator's own posterior at Tschamut"), so the box's upper bound, not the
  data, sets how much of that posterior lies near it.
* roughness_m S in [0.25, 4.0] m. The paper: "2 m, which is typical for talus
  and firm soil slopes (Jones et al., 2000)". The box spans smooth rock
  (S ~ 0.3 m) to very blocky talus (assumption; CRSP's surface roughness is the
  relief within one rock radius of the surface).

* rolling_friction_deg phi_r in [5, 40] deg (``CRSP_ROLLING_BOX``, fitted by
  default by ``python -m calib.fit``): the Coulomb rolling resistance
  mu = tan(phi_r) of the rolling phase (``solvers.crsp._contact``), a site
  parameter. Published values: tan(phi_r) = 0.30 for carbonate rock, lava and
  intrusive rock, 0.35-0.40 for clastic deposits, marl, flysch and schists,
  0.65 for anthropic, landslide and glacial deposits, 0.80 for alluvial and
  colluvial deposits (STONE, Guzzetti et al. 2002, Computers & Geosciences 28,
  1079-1093), i.e. 16.7-38.7 deg; RocFall's lumped-mass rolling friction
  arctan((1 - Rt) / Rt) is 8.5 deg at Rt = 0.87, 5 deg at Rt = 0.92 and
  6-14 deg for Rt 0.8-0.9. The box spans 5-40 deg (rounded out from those,
  assumption).
* In ``CRSP_ROLLING_BOX`` (the default of ``python -m calib.fit``) S goes down to
  0.01 m: a grassy or soil slope has centimetres of relief within one radius of a
  0.3 m block, and with S >= 0.25 m such blocks (S / R >= 1.4, theta_max >= 54
  deg) cannot roll at all (measured on the Tschamut profile: every block stopped
  at the same point whatever Kn, Kt and phi_r). Assumption; the three-parameter
  ``CRSP_BOX`` of the discrepancy studies keeps 0.25 m.

* Where a block can come to rest (``rest_possible_box``, applied to the box
  above by ``python -m calib.fit`` and ``calib.discover``'s candidates): a
  rolling block stops only on a segment whose downhill angle beta has
  tan(beta) <= mu = tan(phi_r) (``solvers.crsp._contact``: on a steeper
  segment gravity beats the rolling
  resistance and the roughness only caps the speed; a pit needs such a segment
  on one side, ``solvers.crsp._vertex``). With phi_r below the flattest slope of
  a profile no block can come to rest anywhere on it: every block leaves the
  profile, and each observed runout (a block at rest on that profile) keeps only
  the observation model's defensive floor (``calib.inference.likelihood``,
  -13.8 nats a row). The posterior the simulator implies has no mass there,
  but the log-likelihood GP smooths that cliff and NUTS sampled it: on Postignano
  (lowest zone 6.0 deg down to the profile's end) 2 % of a main job's draws lay
  at 5-6 deg, and the hazard run made every block of those draws creep off the
  profile past the road (docs/studies.md, "Rest where the profile allows it").
  So the lower bound of the one phi_r is raised, before fitting and from the
  profiles alone, to the flattest downhill angle of the profiles that carry
  observed rows (the largest of their minima: rows rest on each). Our choice;
  left as it is where that angle is below the published 5 deg (Tschamut's
  profiles have flat or rising stretches), for zoned angles (rest on the
  profile then needs any one zone's angle above that zone's flattest slope, not
  a box) and for effects that add rolling resistance (the forest belt makes
  rest possible where phi_r alone does not, ``calib.model.effects``).

* Zoned rolling resistance (``zoned_rolling_box``, ``python -m calib.fit
  --rolling-resistance zones``): one phi_r per material zone of the profile,
  named ``rolling_friction_deg[<zone>]``, each with the same 5-40 deg box. Our
  choice, for a slope whose parts differ (the STONE table above gives 16.7 deg
  for a rock face and 38.7 deg for colluvium; RocFall and CRSP assign
  parameters per material): on Tschamut one phi_r must both stop blocks on the
  near-flat run-out and let them roll down the 34-41 deg meadow above it.

DEM damping law:

* power law alpha(L) = a L^-b (L in m): a in [0.05, 0.95] (alpha of a 1 m
  block; local damping lies in [0, 1), Cundall's default 0.8; Table 1 gives
  0.30-0.90), b in [0.0, 1.5] (b = 0 is constant damping; Table 1 follows
  b ~ 0.5). Evaluated alphas are clipped to [0, 0.95] everywhere
  (``calib.model.alpha_law``: why a clip and not a smaller box).
* constant alpha in [0.02, 0.95].
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

__all__ = ["Box", "CRSP_BOX", "CRSP_ROLLING_BOX", "DEM_BOXES", "ROLLING", "NoRestError",
           "base_name", "crsp_box", "flattest_slope_deg", "has_rolling", "rest_possible_box",
           "rolling_zone", "zoned_name", "zoned_rolling_box"]

ROLLING = "rolling_friction_deg"


@dataclasses.dataclass(frozen=True)
class Box:
    """Named parameters with lower and upper bounds (a uniform prior)."""

    names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]

    @property
    def dim(self) -> int:
        return len(self.names)

    @property
    def lo(self) -> np.ndarray:
        return np.asarray(self.lower, float)

    @property
    def hi(self) -> np.ndarray:
        return np.asarray(self.upper, float)

    def to_unit(self, theta):
        """theta -> [0, 1]^d."""
        return (theta - self.lo) / (self.hi - self.lo)

    def from_unit(self, z):
        """[0, 1]^d -> theta."""
        return self.lo + z * (self.hi - self.lo)

    def contains(self, theta) -> bool:
        t = np.asarray(theta, float)
        return bool(np.all((t >= self.lo) & (t <= self.hi)))


CRSP_BOX = Box(("Kn", "Kt", "roughness_m"), (0.15, 0.60, 0.25), (0.60, 0.98, 4.0))
CRSP_ROLLING_BOX = Box(("Kn", "Kt", "roughness_m", "rolling_friction_deg"),
                       (0.15, 0.60, 0.01, 5.0), (0.60, 0.98, 4.0, 40.0))
DEM_BOXES = {
    "power": Box(("a", "b"), (0.05, 0.0), (0.95, 1.5)),
    "constant": Box(("alpha",), (0.02,), (0.95,)),
}


def zoned_name(zone: str) -> str:
    """The name of zone ``zone``'s own rolling-resistance angle."""
    return f"{ROLLING}[{zone}]"


def rolling_zone(name: str) -> str | None:
    """The zone of a rolling-resistance parameter: "" for ``rolling_friction_deg``
    (every zone), the zone for ``rolling_friction_deg[<zone>]``, None otherwise."""
    if name == ROLLING:
        return ""
    m = re.fullmatch(re.escape(ROLLING) + r"\[(.+)\]", name)
    return m.group(1) if m else None


def has_rolling(names) -> bool:
    """``names`` include a rolling-resistance angle (for every zone, or per zone)."""
    return any(rolling_zone(n) is not None for n in names)


def base_name(name: str) -> str:
    """``rolling_friction_deg`` for any rolling-resistance parameter, else ``name``."""
    return ROLLING if rolling_zone(name) is not None else name


def zoned_rolling_box(zones) -> Box:
    """Kn, Kt, S as in ``CRSP_ROLLING_BOX``, then one phi_r per zone (same range)."""
    zones = tuple(zones)
    if not zones or len(set(zones)) != len(zones):
        raise ValueError(f"zoned rolling resistance needs distinct zone names, got {zones}")
    b = CRSP_ROLLING_BOX
    return Box(b.names[:3] + tuple(zoned_name(z) for z in zones),
               b.lower[:3] + (b.lower[3],) * len(zones), b.upper[:3] + (b.upper[3],) * len(zones))


class NoRestError(ValueError):
    """No rolling-resistance angle of the prior box lets a block rest on the profile."""


def flattest_slope_deg(profile) -> float:
    """The smallest downhill angle of a profile's segments, deg (blocks travel
    towards +x; a flat or rising segment gives 0 or less)."""
    from solvers.profile import segment_angles_rad

    return float(-np.degrees(np.asarray(segment_angles_rad(profile))).max())


def rest_possible_box(box: Box, profiles) -> Box:
    """``box`` with the lower bound of its one rolling-resistance angle raised to
    the flattest downhill angle of ``profiles`` (the largest of their minima),
    where that is above it: below it no block can come to rest on one of them
    (module docstring). Boxes without that angle, or with one angle per zone,
    are returned as they are.

    Args:
        box: a CRSP prior box (``CRSP_ROLLING_BOX`` or a narrower one).
        profiles: the ``solvers.profile.Profile``s the observed rows lie on.
    """
    if ROLLING not in box.names or not profiles:
        return box
    i = box.names.index(ROLLING)
    floor_deg = max(flattest_slope_deg(p) for p in profiles)
    if floor_deg <= box.lower[i]:
        return box
    if floor_deg >= box.upper[i]:
        raise NoRestError(f"no block can come to rest on the profile below a rolling "
                         f"resistance angle of {floor_deg:.1f} deg, above the prior's "
                         f"{box.upper[i]:g} deg")
    lower = box.lower[:i] + (round(floor_deg, 6),) + box.lower[i + 1:]
    return Box(box.names, lower, box.upper)


def crsp_box(names) -> Box:
    """The CRSP prior box whose parameters are ``names`` (a calibration's)."""
    for box in (CRSP_BOX, CRSP_ROLLING_BOX):
        if tuple(names) == box.names:
            return box
    zones = [rolling_zone(n) for n in tuple(names)[3:]]
    if tuple(names)[:3] == CRSP_BOX.names and zones and all(zones):
        return zoned_rolling_box(zones)
    raise ValueError(f"no CRSP prior box has the parameters {', '.join(names)}")
