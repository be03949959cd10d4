"""A flexible rockfall protection barrier in the CRSP model (ONE block, pure).

The source's model. RocFall (Rocscience, "RocFall 4.0 Features: Barriers",
rocscience.com/products/rocfall/Barriers.asp, read 2026-11-26) draws a barrier
as a line segment with one end on the slope; it can be given a capacity, "the
energy required to break through the barrier": a rock that meets it with a
kinetic energy above the capacity passes through it "with a reduced velocity",
and rocks that fly over it are not affected. Flexible barrier kits are rated by
the energy they absorb (MEL, SEL; ../shared/NOTES.md, "Protection design"),
which is the capacity here. The page does not say by how much the velocity is
reduced.

This toolkit's model (our choices):

* The barrier is vertical, at abscissa ``barrier_x_m``, of height H
  (``barrier_height_m``) above the ground there, with capacity E_cap
  (``barrier_capacity_kJ``). By default there is none (``Params`` fields
  None); ``barrier_x_m = +inf`` is none either, and a barrier beyond the
  profile's end or behind the release is never met.
* A block meets the barrier the first time its trajectory crosses
  ``barrier_x_m`` moving downslope: in flight where the event's parabola
  crosses it (exact), rolling where the closed-form rolling move passes it
  (exact, ``_contact.speed2_after``). It meets it once: after that the
  barrier is gone for this block, whatever it does later. A block released
  at or beyond the barrier never meets it (as a station behind the release,
  ``_stations``).
* Passing height h: the clearance of the block's lowest point above the ground
  at ``barrier_x_m``, the ``bounce_height_m`` of ``solvers.stations`` (the CRSP
  lumped mass is the rock's lowest point, so h = z - ground; 0 while rolling).
  The block's centre passes at h + r.
* h >= H: the block passes over the barrier, untouched (so H = 0 is no
  barrier). h < H, the block hits the net, with E its kinetic energy at the
  crossing, translational plus rotational, ``1/2 m v^2 + 1/2 I w^2`` (as
  ``solvers.stations``):
  - E <= E_cap: the barrier stops it. It rests at ``barrier_x_m`` at the
    height where it hit the net, with status ``STOPPED_BY_BARRIER``
    (``solvers.status``); ``E_cap = +inf`` stops every block that hits it.
  - E > E_cap: it breaks through, keeping ``E - E_cap``: velocity and spin are
    scaled by ``f = sqrt((E - E_cap) / E)`` with their directions kept, so
    both kinetic energies scale by f^2 and the total is exactly E - E_cap. It
    goes on from the crossing point (in flight on the parabola's new
    velocity, rolling along the same segment).
* Whatever the event would have done beyond the barrier (its landing, a
  vertex, a break) is discarded for a block that hits the net: the event ends
  at the barrier. The roughness draws are counted per impact (``_model``), so
  the discarded landing consumes none.

``Barrier`` holds a run's barrier (set up once outside the event loop),
``Crossing`` what a block carries through the loop, ``Kinematics`` and ``Cut``
an event at the barrier, ``BarrierRecord`` what the ``Result`` reports.

Cost. The barrier decides how an event ends, so its work enters every quantity
the event ends with, and XLA repeats it in each fused output: a 256-lane event
step on Postignano costs 873,573 floating-point operations with a barrier and
580,812 without (XLA's cost analysis, 2026-11-26). A run without a barrier
(``Params.barrier_x_m`` None) therefore compiles none of it: ``NO_CUT`` holds
constants that the compiler folds away, and the step is the one of a solver
without barriers, operation for operation.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from solvers.crsp._contact import speed2_after
from solvers.profile import Profile, ground_z, segment_index

__all__ = ["NO_CUT", "Barrier", "BarrierRecord", "Crossing", "Cut", "Kinematics", "barrier_site",
           "cut", "flight_at", "hits", "record", "rolling_at", "start_crossing"]


class Barrier(NamedTuple):
    """One run's barrier (a pytree of scalars; per task in a batch).

    Attributes:
        x_m: abscissa, m (+inf: none).
        height_m: H, height above the ground at ``x_m``, m.
        capacity_kJ: E_cap, energy the barrier can absorb, kJ (+inf: unlimited).
        seg: the segment under ``x_m``.
        ground_z_m: ground height at ``x_m``, m.
    """

    x_m: jax.Array
    height_m: jax.Array
    capacity_kJ: jax.Array
    seg: jax.Array
    ground_z_m: jax.Array


def barrier_site(profile: Profile, x_m, height_m, capacity_kJ) -> Barrier:
    """The ``Barrier`` at ``x_m`` on ``profile`` (its segment and ground, once);
    a height or capacity None is unlimited (+inf)."""
    x = jnp.asarray(x_m, jnp.float64)
    # an absent barrier (inf) or one beyond the ends looks up a finite abscissa
    x_in = jnp.clip(x, profile.x_m[0], profile.x_m[-1])
    inf = jnp.inf
    return Barrier(x_m=x, height_m=jnp.asarray(inf if height_m is None else height_m, jnp.float64),
                   capacity_kJ=jnp.asarray(inf if capacity_kJ is None else capacity_kJ,
                                           jnp.float64),
                   seg=segment_index(profile, x_in), ground_z_m=ground_z(profile, x_in))


class Crossing(NamedTuple):
    """A block's meeting with the barrier, carried through the event loop.

    Attributes:
        open: bool, the block can still meet the barrier.
        reached: bool, it has met it (crossed its abscissa downslope).
        clearance_m: passing height h of the lowest point above the ground, m.
        vx_m_s, vz_m_s: velocity at the crossing, before the barrier acts, m/s.
        energy_kJ: E, kinetic energy brought to the barrier, kJ.
        keep: the factor of velocity and spin after it (1 over the barrier, 0
            stopped, ``sqrt((E - E_cap) / E)`` through it).
    """

    open: jax.Array
    reached: jax.Array
    clearance_m: jax.Array
    vx_m_s: jax.Array
    vz_m_s: jax.Array
    energy_kJ: jax.Array
    keep: jax.Array


def start_crossing(release_x_m: jax.Array, barrier_x_m: jax.Array) -> Crossing:
    """The ``Crossing`` at release: open when the block starts before the barrier."""
    nan = jnp.full_like(release_x_m, jnp.nan)
    return Crossing(open=release_x_m < barrier_x_m, reached=jnp.asarray(False), clearance_m=nan,
                    vx_m_s=nan, vz_m_s=nan, energy_kJ=nan, keep=nan)


class Kinematics(NamedTuple):
    """An event's motion evaluated at the barrier's abscissa.

    Attributes:
        z_m: height of the lumped mass, m.
        vx_m_s, vz_m_s: velocity, m/s.
        spin_rad_s: rolling-positive spin, rad/s.
        clearance_m: h, height above the ground at the barrier (>= 0), m.
        energy_kJ: E = 1/2 m v^2 + 1/2 I w^2, kJ.
    """

    z_m: jax.Array
    vx_m_s: jax.Array
    vz_m_s: jax.Array
    spin_rad_s: jax.Array
    clearance_m: jax.Array
    energy_kJ: jax.Array


def flight_at(x0_m, z0_m, vx_m_s, vz_m_s, spin_rad_s, spin_energy_m2_s2, mass_kg,
              barrier: Barrier, g: float) -> Kinematics:
    """A flight from ``(x0, z0)`` with ``(vx, vz)`` at ``barrier.x_m`` (exact):
    ``t = (x_b - x0) / vx``, ``z = z0 + vz t - g t^2 / 2`` (not below the
    ground), velocity ``(vx, vz - g t)``, spin w unchanged,
    ``E = 1/2 m (v^2 + k (r w)^2)`` (``spin_energy_m2_s2`` = k (r w)^2)."""
    t = (barrier.x_m - x0_m) / jnp.where(vx_m_s > 0.0, vx_m_s, 1.0)
    vz = vz_m_s - g * t
    z = jnp.maximum(z0_m + (vz_m_s - 0.5 * g * t) * t, barrier.ground_z_m)
    energy = 0.5 * mass_kg * (vx_m_s * vx_m_s + vz * vz + spin_energy_m2_s2) / 1000.0
    return Kinematics(z_m=z, vx_m_s=vx_m_s, vz_m_s=vz, spin_rad_s=spin_rad_s,
                      clearance_m=z - barrier.ground_z_m, energy_kJ=energy)


def rolling_at(x0_m, z0_m, u2_m2_s2, accel_m_s2, drag_per_m, slope_cos, slope_sin, mass_kg,
               inertia_ratio, radius_m, barrier: Barrier) -> Kinematics:
    """A rolling move from ``x0`` (``z0`` on the segment's line) at ``barrier.x_m``
    (exact): slope distance ``d = (x_b - x0) / cos(beta)``,
    ``u^2 = speed2_after(u0^2, A, c, d)`` (``_contact``), velocity
    ``u (cos(beta), sin(beta))``, spin ``u / r``, ``z = z0 + (x_b - x0) tan(beta)``,
    clearance 0, ``E = 1/2 m (1 + k) u^2``."""
    dx = barrier.x_m - x0_m
    u2 = speed2_after(u2_m2_s2, accel_m_s2, drag_per_m, jnp.maximum(dx / slope_cos, 0.0))
    u = jnp.sqrt(u2)
    return Kinematics(z_m=z0_m + dx * slope_sin / slope_cos, vx_m_s=u * slope_cos,
                      vz_m_s=u * slope_sin, spin_rad_s=u / radius_m,
                      clearance_m=jnp.zeros_like(u),
                      energy_kJ=0.5 * mass_kg * (1.0 + inertia_ratio) * u2 / 1000.0)


def hits(kin: Kinematics, barrier: Barrier, cross: jax.Array
         ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The barrier's rule for an event that crosses its abscissa (``cross``;
    module docstring).

    Returns:
        (net: crossed with h < H, stopped: in the net with E <= E_cap, keep: the
        factor of velocity and spin, 1 unless in the net, 0 stopped,
        ``sqrt((E - E_cap) / E)`` through it).
    """
    e = kin.energy_kJ
    net = cross & (kin.clearance_m < barrier.height_m)
    stopped = net & (e <= barrier.capacity_kJ)
    through = jnp.sqrt(jnp.maximum(e - barrier.capacity_kJ, 0.0) / jnp.where(e > 0.0, e, 1.0))
    keep = jnp.where(net, jnp.where(stopped, 0.0, through), 1.0)
    return net, stopped, keep


class Cut(NamedTuple):
    """How an event ends against the barrier.

    Attributes:
        net: bool, the block hits the net: the event ends at the barrier.
        caught: bool, it stops there.
        keep: factor of its velocity and spin there (1 unless in the net).
        at: its ``Kinematics`` at the barrier.
        x_m: the barrier's abscissa, m.
        seg: the segment it goes on from.
        crossing: its ``Crossing`` after the event (None: no barrier).
    """

    net: jax.Array
    caught: jax.Array
    keep: jax.Array
    at: Kinematics
    x_m: jax.Array
    seg: jax.Array
    crossing: Crossing | None


def cut(c: Crossing, barrier: Barrier, cross: jax.Array, kin: Kinematics, seg) -> Cut:
    """The ``Cut`` of an event that crosses the barrier (``cross``) or not, with
    ``kin`` its motion there and ``seg`` the segment under it."""
    net, caught, keep = hits(kin, barrier, cross)
    new = Crossing(open=jnp.zeros_like(c.open), reached=jnp.ones_like(c.reached),
                   clearance_m=kin.clearance_m, vx_m_s=kin.vx_m_s, vz_m_s=kin.vz_m_s,
                   energy_kJ=kin.energy_kJ, keep=keep)
    return Cut(net=net, caught=caught, keep=keep, at=kin, x_m=barrier.x_m, seg=seg,
               crossing=jax.tree_util.tree_map(lambda a, b: jnp.where(cross, a, b), new, c))


# the ``Cut`` of a run without a barrier: constants that the compiler folds away
NO_CUT = Cut(net=np.False_, caught=np.False_, keep=1.0, at=Kinematics(*(0.0,) * 6), x_m=0.0,
             seg=0, crossing=None)


class BarrierRecord(NamedTuple):
    """What a block did at the barrier (``Result.barrier``; NaN where not reached).

    Attributes:
        reached: bool, the block crossed the barrier's abscissa downslope (over
            it, into it or through it).
        height_m: passing height, clearance of the lowest point above the
            ground at the barrier, m (the centre is r higher).
        speed_m_s: speed of the centre at the crossing, m/s.
        angle_deg: impact angle, the velocity's inclination below the
            horizontal (positive descending), degrees.
        energy_kJ: kinetic energy brought to the barrier (translational +
            rotational), kJ.
        energy_after_kJ: kinetic energy kept after it, kJ (``energy_kJ`` over
            the barrier, 0 stopped, ``energy_kJ - E_cap`` through it).
    """

    reached: jax.Array
    height_m: jax.Array
    speed_m_s: jax.Array
    angle_deg: jax.Array
    energy_kJ: jax.Array
    energy_after_kJ: jax.Array


def record(c: Crossing) -> BarrierRecord:
    """The ``BarrierRecord`` of a block's final ``Crossing`` (once, after the loop;
    the energy kept is ``keep^2 E``, so exactly E over the barrier)."""
    return BarrierRecord(
        reached=c.reached, height_m=c.clearance_m, speed_m_s=jnp.hypot(c.vx_m_s, c.vz_m_s),
        angle_deg=jnp.degrees(jnp.arctan2(-c.vz_m_s, c.vx_m_s)), energy_kJ=c.energy_kJ,
        energy_after_kJ=c.keep * c.keep * c.energy_kJ)
