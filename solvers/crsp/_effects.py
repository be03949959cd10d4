"""Optional physics of the CRSP model: the candidate effects of the discrepancy workflow.

Each effect is switched off by its default parameter value (``params_from_profile``),
so a plain CRSP run is unchanged; each has its own parameters in ``Params``, may
be traced and differentiated like the others, and acts inside the solver (never
as a correction of its outputs). All functions are pure and scalar (one block).

* Size-dependent restitution (``restitution_size_exponent`` gamma):
  ``K(d) = min(K (d / d_ref)^gamma, K_MAX)`` for both Kn and Kt, with d = 2 r the
  block diameter and d_ref = 1 m. gamma > 0: small blocks lose more energy per
  impact than large ones, the trend of the paper's UDEC damping law
  ``alpha(L) = a L^-b`` (Table 1: alpha falls with block size); gamma < 0 the
  reverse. The power-law form is this toolkit's assumption, chosen to mirror
  the paper's alpha(L). Mass-dependent restitution is an option of RocFall's
  lumped-mass method ("Scale Rn by mass", Rocscience RocFall FAQ) and a
  measured effect (Asteriou & Tsiambaos 2018, "Effect of impact velocity, block
  mass and hardness on the coefficients of restitution for rockfall analysis",
  IJRMMS 106, 41-50).
* Fragmentation on a hard impact (``frag_energy_kJ`` E_f, ``frag_radius_ratio``
  rho, ``frag_speed_ratio`` s): at the first impact whose normal kinetic energy
  ``(1/2) m v_n^2`` (v_n: incoming speed normal to the mean slope) exceeds E_f,
  the block breaks into 1 / rho^3 equal fragments of radius rho r and mass
  rho^3 m. The model follows one of them (they are alike), leaving the impact
  with the rebound velocity times s: fragmentation consumes kinetic energy, a
  fraction 1 - s^2 of the rebound's. A fragment does not break again. This is
  the lumped-mass treatment of RockGIS-type codes (the block is replaced by
  smaller blocks that travel on from the impact point); equal fragments and
  the single break are simplifications of this toolkit. RockGIS (Matas et al.
  2017, Landslides 14, 1565-1578) breaks a block when its impact energy passes
  a threshold and sends the fragments on as new lumped masses; Giacomini et al.
  (2009, IJRMMS 46, 708-715) found the share of impact energy spent on
  fragmentation roughly constant (the value of s is an assumption). Large blocks carry
  more energy, so they break first: the effect shortens the runout of large
  blocks only.
* Rolling resistance (``rolling_resistance`` Delta-mu): an extra Coulomb
  rolling-resistance coefficient added to every zone's ``tan(phi_r)`` in the
  ground-contact phase (``_contact``): ``(1 + k) du/dt = -g sin(beta) -
  sign(u) (tan(phi_r) + Delta-mu) g cos(beta)``. It stands for energy lost by
  rolling over soft soil, debris or litter (the "rolling friction" of 2D
  lumped-mass codes: Azzoni et al. 1995, IJRMMS 32(7), 709-724, whose CADMA
  code has restitution and rolling friction coefficients; the DEM analogue is
  the constant rolling-resistance moment ``mu_r R F_n`` of Ai et al. 2011,
  Powder Technol. 206, 269-282). It acts only where blocks roll, i.e. mostly
  on the gentle runout zone.
* Vegetation / forest belt (``belt_start_m``, ``belt_end_m``, ``belt_loss`` e):
  over the stretch ``belt_start_m <= x <= belt_end_m`` trees and undergrowth
  brake the block: the rebound velocity of an impact there is multiplied by
  ``sqrt(1 - e)`` (a fraction e of the rebound energy goes into the trees), and
  a rolling block feels the extra resistance Delta-mu = e. Blocks flying over
  the belt are not slowed. Forests stop blocks: Jahn (1988, Interpraevent)
  found about 60 % of stones in forested stretches stopped by tree contacts,
  and Stoffel et al. (2006) that about three times as many rocks would reach
  the slope foot without the forest. The representation (a stretch of lower
  restitution and higher rolling resistance rather than tree by tree, as 3D
  forest models such as Rockyfor3D do) is this toolkit's choice; RocFall's
  lumped-mass method has no forest option. The contact phase applies the belt
  from the position where each contact event starts (events on rough ground
  are at most one radius long).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = [
    "D_REF_M",
    "K_MAX",
    "breaks",
    "in_belt",
    "size_scaled",
]

D_REF_M = 1.0  # reference diameter of the size-dependent restitution, m
K_MAX = 0.99  # restitution coefficients are kept below 1 (no energy gain)


def size_scaled(K: jax.Array, radius_m: jax.Array, exponent: jax.Array) -> jax.Array:
    """Size-dependent restitution ``min(K (2 r / d_ref)^gamma, K_MAX)``."""
    return jnp.minimum(K * (2.0 * radius_m / D_REF_M) ** exponent, K_MAX)


def breaks(mass_kg: jax.Array, vn_in_m_s: jax.Array, energy_kJ: jax.Array,
           already: jax.Array) -> jax.Array:
    """Whether an impact breaks the block: ``(1/2) m v_n^2 / 1000 > E_f`` (kJ), once."""
    return ~already & (0.5 * mass_kg * vn_in_m_s**2 / 1000.0 > energy_kJ)


def in_belt(x_m: jax.Array, start_m: jax.Array, end_m: jax.Array) -> jax.Array:
    """Whether abscissa ``x_m`` lies in the vegetation belt."""
    return (x_m >= start_m) & (x_m <= end_m)
