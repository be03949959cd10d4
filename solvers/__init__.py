"""Rockfall solvers along a 2D slope profile, in JAX.

* ``solvers.profile``: the slope (height-field polyline with material zones).
* ``solvers.crsp``: the CRSP lumped-mass impact model (Pfeiffer & Bowen 1989).
* ``solvers.dem``: a smooth-contact rigid-block DEM in the spirit of UDEC.

Positions are carried in float64: at 100 m the float32 spacing (7.6e-6 m) is
about one DEM step's displacement, and the CRSP impact-time roots lose digits
near grazing contacts. Importing ``solvers`` therefore enables JAX's x64 mode.

The names re-exported from ``solvers.profile`` are loaded on first use (PEP
562), so that ``python -m solvers.profile`` does not find its own module
already imported by the package (runpy's RuntimeWarning).
"""

import jax

jax.config.update("jax_enable_x64", True)

__all__ = ["Profile", "ProfileError", "ground_z", "load_profile", "make_profile"]


def __getattr__(name):
    if name in __all__:
        from solvers import profile

        return getattr(profile, name)
    raise AttributeError(f"module 'solvers' has no attribute {name!r}")
