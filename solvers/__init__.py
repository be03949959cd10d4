"""Rockfall solvers along a 2D slope profile, in JAX.

* ``solvers.profile``: the slope (height-field polyline with material zones).
* ``solvers.crsp``: the CRSP lumped-mass impact model (Pfeiffer & Bowen 1989).
* ``solvers.dem``: a smooth-contact rigid-block DEM in the spirit of UDEC.

Positions are carried in float64: at 100 m the float32 spacing (7.6e-6 m) is
about one DEM step's displacement, and the CRSP impact-time roots lose digits
near grazing contacts. Importing ``solvers`` therefore enables JAX's x64 mode.
"""

import jax

jax.config.update("jax_enable_x64", True)

from solvers.profile import Profile, ProfileError, ground_z, load_profile, make_profile  # noqa: E402

__all__ = ["Profile", "ProfileError", "ground_z", "load_profile", "make_profile"]
