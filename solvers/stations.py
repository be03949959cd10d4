"""Analysis stations: what a block does when it first passes a given abscissa.

Practitioners read rockfall results at candidate barrier positions: whether a
block got there, with what kinetic energy, speed and passing (bounce) height.
Both solvers fill the same record for a user-given list of station abscissae.

Conventions (shared by CRSP and the DEM):
* A block "passes" station x_s the first time its centre crosses x_s moving
  downslope (+x). Later passages are ignored.
* ``energy_kJ`` = translational + rotational kinetic energy, 1/2 m v^2 + 1/2 I w^2,
  in kJ (per metre of thickness for the 2D DEM, per block for CRSP's 3D shapes).
* ``velocity_m_s`` = speed of the centre of mass.
* ``bounce_height_m`` = clearance: vertical height of the block's lowest point
  above the ground at x_s, >= 0. In the lumped-mass CRSP model the trajectory
  point is the rock's lowest point, so it is that point's height.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["StationRecord", "empty_record", "record_passage"]


class StationRecord(NamedTuple):
    """Per-station results for one block; each field has shape (n_stations,).

    Attributes:
        passed: bool, the block crossed the station moving downslope.
        energy_kJ: kinetic energy at first passage, kJ (NaN if not passed).
        velocity_m_s: speed at first passage, m/s (NaN if not passed).
        bounce_height_m: clearance above ground at first passage, m (NaN if not).
    """

    passed: jax.Array
    energy_kJ: jax.Array
    velocity_m_s: jax.Array
    bounce_height_m: jax.Array


def empty_record(n_stations: int, dtype=jnp.float64) -> StationRecord:
    nan = jnp.full((n_stations,), jnp.nan, dtype)
    return StationRecord(jnp.zeros((n_stations,), bool), nan, nan, nan)


def record_passage(
    rec: StationRecord,
    crossed: jax.Array,
    energy_kJ: jax.Array,
    velocity_m_s: jax.Array,
    bounce_height_m: jax.Array,
) -> StationRecord:
    """Write values for stations crossed now and not passed before.

    Args:
        rec: the record so far.
        crossed: (n_stations,) bool, crossed downslope during this event/step.
        energy_kJ, velocity_m_s, bounce_height_m: (n_stations,) values at the
            crossing.

    Returns:
        The updated record (first passage wins).
    """
    new = crossed & ~rec.passed
    return StationRecord(
        passed=rec.passed | crossed,
        energy_kJ=jnp.where(new, energy_kJ, rec.energy_kJ),
        velocity_m_s=jnp.where(new, velocity_m_s, rec.velocity_m_s),
        bounce_height_m=jnp.where(new, jnp.maximum(bounce_height_m, 0.0), rec.bounce_height_m),
    )
