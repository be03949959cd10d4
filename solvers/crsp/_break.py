"""The break of a CRSP block, recorded so that every fragment can run on as a block.

The source's model (``_effects``, RockGIS-type lumped-mass fragmentation, Matas
et al. 2017, Landslides 14, 1565-1578): at the first impact whose normal
kinetic energy ``(1/2) m v_n^2`` exceeds ``frag_energy_kJ`` the block breaks
into n = 1 / rho^3 equal fragments of radius rho r and mass rho^3 m
(rho = ``frag_radius_ratio``), which leave the impact with the rebound velocity
times s (``frag_speed_ratio``) and the spin scaled so that the surface speed
r w is scaled by s too. ``_model`` follows ONE of these fragments. This module
lets a caller follow all of them:

* ``BreakRecord`` (``Result.breakup``): the block's state right after the
  breaking impact, exactly as the model hands it to the fragment it follows:
  the impact point on the ground line, the velocity and spin after the break,
  the segment, the mode (in flight, or rolling when the rebound stays on the
  ground), a pending impact (a rebound into the mean slope), the fragment's
  radius and mass, the count n = 1 / rho^3, and the block's kinetic energy
  just before the impact.
* ``Settings.split_at_break`` (static; off by default): the block's run ends
  at the break. Its event budget is closed there, so its status is
  ``BUDGET`` (``solvers.status``: still moving, never a runout) and its
  station passages are those of the whole block before the break; its
  record says it broke.
* ``fragment_state`` / ``simulate_fragment``: one fragment from the record,
  with its own key, run as a block of its own: the model's fragment (radius,
  mass, roughness angle and size-scaled restitution of ``segment_table``'s
  fragment fields, reached through ``State.fragmented``), which never breaks
  again (as in ``_effects``). It starts in the record's state with no events
  and no impacts, an event budget for its own radius
  (``_model.event_budget``), and the barrier still ahead of it only if the
  block had not met it.

Our choices: all n fragments leave the impact point with the same velocity
and spin and differ afterwards only by their own roughness draws (their own
keys); a spread of directions at the break is not modelled. A caller that
needs whole fragments takes rho = n^(-1/3) for a whole n (``calib.hazard``
does), so that the n fragments have the block's mass.

Invariants (``tests/test_hazard_fragments.py``): the n fragments' masses sum
to the block's; their kinetic energy right after the break,
``n (1/2) rho^3 m (v'^2 + k (rho r w')^2)``, is at most the block's just
before the impact (the CRSP impact dissipates and s <= 1); they start on the
ground line of their segment (never below it).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from solvers.crsp._barrier import start_crossing
from solvers.crsp._params import Block, Params, Settings
from solvers.profile import Profile

__all__ = ["FRAGMENT_STREAM", "BreakRecord", "fragment_key", "fragment_state", "no_break",
           "note_break", "simulate_fragment", "simulate_fragments"]

# the word folded into a block's key before the fragment index (fragment_key): it
# keeps the fragments' keys apart from the block's own split release/event keys
FRAGMENT_STREAM = 0x46524147  # "FRAG"


class BreakRecord(NamedTuple):
    """A block's break (``Result.breakup``; NaN and False where it did not break).

    Attributes:
        broken: bool, the block broke.
        x_m, z_m: the impact point, on the ground line of segment ``seg``, m.
        vx_m_s, vz_m_s: a fragment's velocity right after the break, m/s.
        spin_rad_s: its rolling-positive spin, rad/s.
        seg: the segment under it.
        mode: its mode, ``_model.FLIGHT`` or ``_model.CONTACT`` (rolling).
        pending: bool, its next event is an immediate impact on ``seg``.
        radius_m: a fragment's radius rho r, m.
        mass_kg: a fragment's mass rho^3 m, kg.
        n_fragments: n = 1 / rho^3 (a whole number only where rho = n^(-1/3)).
        energy_before_kJ: the block's kinetic energy just before the impact
            (translational + rotational), kJ.
        fragment_energy_kJ: one fragment's kinetic energy right after the
            break, kJ.
    """

    broken: jax.Array
    x_m: jax.Array
    z_m: jax.Array
    vx_m_s: jax.Array
    vz_m_s: jax.Array
    spin_rad_s: jax.Array
    seg: jax.Array
    mode: jax.Array
    pending: jax.Array
    radius_m: jax.Array
    mass_kg: jax.Array
    n_fragments: jax.Array
    energy_before_kJ: jax.Array
    fragment_energy_kJ: jax.Array


def no_break() -> BreakRecord:
    """The record of a block that has not broken."""
    nan = jnp.full((), jnp.nan, jnp.float64)
    return BreakRecord(broken=jnp.asarray(False), x_m=nan, z_m=nan, vx_m_s=nan, vz_m_s=nan,
                       spin_rad_s=nan, seg=jnp.asarray(-1, jnp.int32),
                       mode=jnp.asarray(-1, jnp.int32), pending=jnp.asarray(False),
                       radius_m=nan, mass_kg=nan, n_fragments=nan, energy_before_kJ=nan,
                       fragment_energy_kJ=nan)


def note_break(before, after, brk: jax.Array, vx_in_m_s: jax.Array, vz_in_m_s: jax.Array,
               block: Block, params: Params, frag_mass_kg: jax.Array, settings: Settings):
    """The flight event ``before`` -> ``after`` (``_model.State``s) with its break noted.

    Where ``brk`` (the event's impact broke the block), ``after.breakup`` becomes
    the ``BreakRecord`` of ``after`` (the fragment's state), with the block's
    energy before the impact from its incoming velocity ``(vx_in, vz_in)`` and
    spin ``before.spin_rad_s``:
    ``E = (1/2) m (vx^2 + vz^2 + k (r w)^2) / 1000`` kJ; with
    ``settings.split_at_break`` the block's budget closes at this event.
    """
    k = block.inertia_ratio
    r0, r1 = before.radius_m, after.radius_m
    e_in = 0.5 * block.mass_kg * (vx_in_m_s**2 + vz_in_m_s**2
                                  + k * (r0 * before.spin_rad_s) ** 2) / 1000.0
    e_frag = 0.5 * frag_mass_kg * (after.vx_m_s**2 + after.vz_m_s**2
                                   + k * (r1 * after.spin_rad_s) ** 2) / 1000.0
    rec = BreakRecord(
        broken=jnp.asarray(True), x_m=after.x_m, z_m=after.z_m, vx_m_s=after.vx_m_s,
        vz_m_s=after.vz_m_s, spin_rad_s=after.spin_rad_s, seg=after.seg.astype(jnp.int32),
        mode=after.mode.astype(jnp.int32), pending=after.pending, radius_m=r1,
        mass_kg=frag_mass_kg, n_fragments=1.0 / params.frag_radius_ratio**3,
        energy_before_kJ=e_in, fragment_energy_kJ=e_frag)
    rec = jax.tree_util.tree_map(lambda a, b: jnp.where(brk, a, b), rec, before.breakup)
    budget = after.budget
    if settings.split_at_break:
        budget = jnp.where(brk, after.n_events, budget).astype(budget.dtype)
    return after._replace(breakup=rec, budget=budget)


def fragment_key(block_key: jax.Array, i) -> jax.Array:
    """Key of fragment ``i`` of the block keyed ``block_key``:
    ``fold_in(fold_in(block_key, FRAGMENT_STREAM), i)``."""
    return jax.random.fold_in(jax.random.fold_in(block_key, FRAGMENT_STREAM), i)


def fragment_state(record: BreakRecord, params: Params, profile: Profile,
                   barrier_open: jax.Array, settings: Settings = Settings()):
    """A fragment's first ``_model.State``: the record's state (module docstring).

    Args:
        record: the block's ``BreakRecord`` (broken).
        params: the block's ``Params`` (barrier and fragment ratios).
        profile: the slope.
        barrier_open: bool, the block had not met the barrier (``Result.barrier``
            not reached): only then can the fragment meet it (ignored without
            a barrier).
        settings: static settings (the event budget).
    """
    from solvers.crsp._model import State, event_budget

    crossing = None  # a run without a barrier (Params.barrier_x_m None) carries none
    if params.barrier_x_m is not None:
        crossing = start_crossing(record.x_m, params.barrier_x_m)
        crossing = crossing._replace(open=crossing.open & barrier_open)
    zero = jnp.asarray(0, jnp.int32)
    return State(
        x_m=record.x_m, z_m=record.z_m, vx_m_s=record.vx_m_s, vz_m_s=record.vz_m_s,
        spin_rad_s=record.spin_rad_s, seg=record.seg, mode=record.mode, n_events=zero,
        n_impacts=zero, pending=record.pending, radius_m=record.radius_m,
        fragmented=jnp.asarray(True), budget=event_budget(profile, record.radius_m, settings),
        barrier=crossing, breakup=no_break() if settings.split_at_break else None)


def simulate_fragment(params: Params, block: Block, record: BreakRecord, key: jax.Array,
                      barrier_open: jax.Array, *, profile: Profile,
                      stations_x_m: jax.Array | None = None, settings: Settings = Settings()):
    """ONE fragment of the block ``block`` that broke as ``record`` says, run to
    its end with ``key`` (``fragment_key``) as its event key: a ``_model.Result``
    whose ``release_x_m`` is the break's abscissa (its runout is counted from
    there) and whose stations are those it passes after the break."""
    from solvers.crsp._model import simulate_from

    state0 = fragment_state(record, params, profile, barrier_open, settings)
    return simulate_from(state0, params, block, key, profile=profile,
                         stations_x_m=stations_x_m, settings=settings)


@functools.partial(jax.jit, static_argnames=("settings",))
def simulate_fragments(params: Params, block: Block, records: BreakRecord, keys: jax.Array,
                       barrier_open: jax.Array, profile: Profile, stations_x_m: jax.Array,
                       settings: Settings = Settings()):
    """``simulate_fragment`` vmapped over fragments: every argument but
    ``profile``, ``stations_x_m`` and ``settings`` has a leading axis F (one
    fragment each: its block's parameters, block, record, key, barrier flag).
    The loop runs until the slowest fragment of the batch ends."""
    fn = functools.partial(simulate_fragment, profile=profile, stations_x_m=stations_x_m,
                           settings=settings)
    return jax.vmap(fn)(params, block, records, keys, barrier_open)
