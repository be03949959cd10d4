"""The impact angle at a barrier: the direction of the blocks' velocity where they cross
its abscissa, which the hazard results do not hold (they keep speed, height and
energy only), from a CRSP run of the same draws with the barrier element.

Definition (the solver's, ``solvers.crsp.BarrierRecord.angle_deg``): the inclination
of the block's velocity below the horizontal at the crossing, degrees, positive
descending. Beside it, the angle to the ground there: inclination minus the
ground's slope angle below the horizontal at the barrier (0: moving along the
ground, as a rolling block does; positive: descending into it). ETAG 027 / EAD
340059-00-0106 test kits with impacts normal to the net (NOTES.md, "Protection
design"): a net inclined from the vertical by the impact angle meets the blocks
head-on; that choice is the designer's, the sheet gives the angles.

What is simulated (our choice): for each draw of the hazard run (its
``parameter_value``, the calibration's effects), ``n_blocks`` blocks of the design
size released as the hazard run without release conditions releases them (at its
``release_x_m``, the solver's release state), with an unlimited barrier at x: the
crossing is recorded before the barrier acts, so the angles are those of the run
without it. Block j of draw d has the key fold_in(fold_in(key(seed), d), j), the
hazard run's (``calib.hazard``'s random-number scheme), and the event budget is the
hazard run's (its ``crsp_max_events``; ``calib.hazard.HAZARD_SETTINGS`` by default),
so with the same seed the blocks are the hazard run's blocks.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from calib.design._values import band

__all__ = ["ImpactAngles", "impact_angles"]

PERCENTILES = (5.0, 50.0, 95.0)


@dataclasses.dataclass
class ImpactAngles:
    """Impact angles of the blocks that cross the barrier's abscissa.

    Attributes:
        x_m: the barrier's abscissa, m.
        size_m: the block size D, m.
        angle_deg: (N,) inclination below the horizontal of every crossing of all
            draws, degrees.
        draw: (N,) the draw of each crossing.
        ground_slope_deg: the ground's slope angle below the horizontal at x (the
            segment downslope of x), degrees.
        n_draws, n_blocks_per_draw: the run's size.
        max_events: the CRSP event budget per block it ran with (None: the
            solver's size- and profile-derived budget).
    """

    x_m: float
    size_m: float
    angle_deg: np.ndarray
    draw: np.ndarray
    ground_slope_deg: float
    n_draws: int
    n_blocks_per_draw: int
    max_events: int | None = None

    def percentiles(self, to_ground: bool = False) -> dict[float, float]:
        """The 5th, 50th and 95th percentiles of the pooled angles, degrees (to the
        ground: minus the ground's slope); NaN where no block crossed."""
        a = self.angle_deg - (self.ground_slope_deg if to_ground else 0.0)
        if a.size == 0:
            return {p: math.nan for p in PERCENTILES}
        return {p: float(v) for p, v in zip(PERCENTILES, np.percentile(a, PERCENTILES),
                                            strict=True)}

    def median_band(self) -> tuple[float, float]:
        """5-95 % over draws of each draw's median angle, degrees."""
        meds = [np.median(self.angle_deg[self.draw == d]) for d in range(self.n_draws)
                if np.any(self.draw == d)]
        return band(np.asarray(meds, float))

    def record(self) -> dict:
        """A JSON-ready record (what ``design.json`` holds under ``impact_angle``)."""
        return {"x_m": self.x_m, "size_m": self.size_m, "n_crossings": int(self.angle_deg.size),
                "n_draws": self.n_draws, "n_blocks_per_draw": self.n_blocks_per_draw,
                "crsp_max_events": ("profile" if self.max_events is None
                                    else int(self.max_events)),
                "ground_slope_deg": self.ground_slope_deg,
                "below_horizontal_deg": {f"p{p:g}": v for p, v in self.percentiles().items()},
                "to_ground_deg": {f"p{p:g}": v for p, v in self.percentiles(True).items()},
                "median_band_deg": list(self.median_band()),
                "definition": "inclination of the velocity below the horizontal at the "
                              "crossing (solvers.crsp.BarrierRecord.angle_deg); to the "
                              "ground: minus the ground's slope angle at x"}


def _ground_slope_deg(profile, x_m: float) -> float:
    xs, zs = np.asarray(profile.x_m), np.asarray(profile.z_m)
    i = int(np.clip(np.searchsorted(xs, x_m, side="right") - 1, 0, len(xs) - 2))
    return float(np.degrees(np.arctan2(zs[i] - zs[i + 1], xs[i + 1] - xs[i])))


def impact_angles(cal, values: np.ndarray, names, profile, x_m: float, size_m: float,
                  n_blocks: int, seed: int, release_x_m: float,
                  settings=None, shape: str = "sphere") -> ImpactAngles:
    """Impact angles at ``x_m`` of blocks of size ``size_m`` (module docstring).

    Args:
        cal: the calibration (``calib.hazard.load_calibration``): its effects and rock
            density; CRSP only.
        values: (D, P) parameter sets, one per draw (a hazard file's
            ``parameter_value``, or ``Draws.values``).
        names: the P parameter names.
        profile: the slope (``solvers.load_profile`` of the calibration's profile).
        x_m: the barrier's abscissa, m (downslope of the release).
        size_m: block size D (diameter), m.
        n_blocks: blocks per draw.
        seed: the hazard run's seed.
        release_x_m: where the blocks are released, m.
        settings: the hazard run's CRSP settings (``solvers.crsp.Settings``; its
            event budget); None: ``calib.hazard.HAZARD_SETTINGS``.
        shape: the hazard run's CRSP shape class of the blocks (the block of that
            shape with the volume of the sphere of diameter D, as the hazard run
            makes it: ``calib.model.entries.crsp_radius_m``).

    Raises:
        ValueError: not a CRSP calibration, or the barrier at or above the release.
    """
    from calib.hazard import HAZARD_SETTINGS
    from calib.model.effects import draw_overrides
    from calib.model.entries import Entries
    from solvers import crsp

    if cal.model != "crsp":
        raise ValueError(f"impact angles need a CRSP calibration, not {cal.model!r}")
    if not x_m > release_x_m:
        raise ValueError(f"barrier at x = {x_m:g} m: at or above the release at "
                         f"x = {release_x_m:g} m")
    settings = HAZARD_SETTINGS if settings is None else settings
    block = Entries.at_sizes([float(size_m)], float(release_x_m), shapes=[shape],
                             density_kg_m3=cal.rock_density_kg_m3).crsp_blocks()[0]
    angles, draws = [], []
    values = np.atleast_2d(np.asarray(values, np.float64))
    for d, row in enumerate(values):
        p = crsp.params_from_profile(profile, release_x_m=float(release_x_m),
                                     barrier_x_m=float(x_m),
                                     rolling_threshold_m_s=cal.rolling_threshold_m_s,
                                     **draw_overrides(cal.effects, names, row, profile))
        key = jax.random.fold_in(jax.random.key(seed), d)
        res = crsp.run_blocks(p, block, key, n_blocks, profile, settings=settings)
        hit = np.asarray(res.barrier.reached, bool)
        angles.append(np.asarray(res.barrier.angle_deg, np.float64)[hit])
        draws.append(np.full(int(hit.sum()), d))
    return ImpactAngles(x_m=float(x_m), size_m=float(size_m),
                        angle_deg=np.concatenate(angles), draw=np.concatenate(draws),
                        ground_slope_deg=_ground_slope_deg(profile, x_m),
                        n_draws=len(values), n_blocks_per_draw=int(n_blocks),
                        max_events=settings.max_events)
