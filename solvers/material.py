"""The rock's density: the one default both solvers build their blocks with.

``ROCK_DENSITY_KG_M3`` = 2350 kg/m^3 is the seed paper's value for the
Postignano limestone (Sect. 4.1: "rho = 2350 kg/m3"). It is only the default:
a site states its own density in its site file (``rock_density_kg_m3``,
``calib.files.site``), the calibration file records the density it was fitted
at, and every simulation that reports a mass or an energy uses the site's.
In CRSP the density sets the block's mass and so its energies (and the
fragmentation effect's energy threshold); the runout of a lumped mass does not
depend on it. In the DEM it sets the mass per metre of width, and the contact
and damping forces scale with it.
"""

ROCK_DENSITY_KG_M3 = 2350.0

__all__ = ["ROCK_DENSITY_KG_M3", "check_density"]


def check_density(density_kg_m3: float) -> float:
    """``density_kg_m3`` as a float; a ValueError unless it is a positive finite number."""
    rho = float(density_kg_m3)
    if not (rho > 0 and rho < float("inf")):
        raise ValueError(f"rock density must be a positive number of kg/m^3, got "
                         f"{density_kg_m3!r}")
    return rho
