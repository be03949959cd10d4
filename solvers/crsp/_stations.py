"""First passages of ONE CRSP block at the analysis stations, a few per event.

The record and its conventions are ``solvers.stations``'. This module fills it
without touching every station at every event, which halved the throughput of
a run with 61 stations (issue 15's benchmark):

* Each event leaves a ``Passage``: the few numbers that give the block's speed,
  kinetic energy and clearance at any abscissa the event crossed (the flight's
  parabola, or the closed-form rolling speed of ``_contact.speed2_after``).
* Stations are walked in ascending order with a cursor. A block has passed a
  station once its centre has reached it moving downslope; positions are
  continuous from event to event, so the stations first passed during an event
  are exactly those between the farthest point reached before it (exclusive)
  and its end point (inclusive): the sorted indices ``[next, end)``.
* ``emit`` evaluates the last ``Passage`` at ``slots`` of those stations per
  loop iteration and returns them as ``Written`` values (station index and
  values); the caller stores them (``store`` for one block's record; the pooled
  batch writes them straight into its output). An event that crosses more
  stations leaves a backlog; the event loop then emits the rest before it
  simulates the next event (``backlog``), so every record is complete and the
  physics is not changed by it.
* The block's state carries only the cursor's scalars, never the (n_stations,)
  arrays: selecting and copying those every event cost as much as the event.

Stations at or behind the release point are never passed (the block starts
there), and neither is a station the block reaches only by rolling back and
then forward again over ground it had already covered: this is the "first
crossing moving downslope" of ``solvers.stations``, with the release point as
the farthest point reached at the start.

The evaluation formulas are the event's own (our code, exact for the event):
in flight t = (x_s - x0) / vx, v^2 = vx^2 + (vz - g t)^2, clearance
z0 + vz t - g t^2 / 2 - ground(x_s), energy 1/2 m (v^2 + k (r omega)^2); rolling
d = (x_s - x0) / cos(beta), v^2 = ``speed2_after``, clearance 0, energy
1/2 m (1 + k) v^2.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from solvers.crsp._contact import speed2_after
from solvers.stations import StationRecord

__all__ = ["Cursor", "Passage", "Written", "after_event", "backlog", "emit", "empty_values",
           "record", "start", "store"]


class Passage(NamedTuple):
    """One event's motion, enough to evaluate it at any abscissa it crossed.

    Attributes:
        x0_m: abscissa at the start of the event, m.
        flight: bool, a flight (else a rolling move along one segment).
        z0_m: height at the start (flight), m.
        vx_m_s, vz_m_s: velocity at the start (flight), m/s.
        spin_energy_m2_s2: k (r omega)^2, the rotational part of v^2 (flight).
        u2_m2_s2: squared speed along the segment at the start (rolling).
        accel_m_s2, drag_per_m: ``_contact.contact_move``'s acceleration and
            asperity loss rate (rolling).
        slope_cos: cos(beta) of the rolling segment.
        mass_kg: the block's (or fragment's) mass during the event.
        inertia_ratio: k = I / (m r^2).
    """

    x0_m: jax.Array
    flight: jax.Array
    z0_m: jax.Array
    vx_m_s: jax.Array
    vz_m_s: jax.Array
    spin_energy_m2_s2: jax.Array
    u2_m2_s2: jax.Array
    accel_m_s2: jax.Array
    drag_per_m: jax.Array
    slope_cos: jax.Array
    mass_kg: jax.Array
    inertia_ratio: jax.Array


class Cursor(NamedTuple):
    """Station bookkeeping of one block (stations in ascending order).

    Attributes:
        first: index of the first station beyond the release point.
        next: first station whose passage is not yet emitted.
        end: stations ``[next, end)`` were passed and wait to be emitted.
        passage: the last event's ``Passage``.
    """

    first: jax.Array
    next: jax.Array
    end: jax.Array
    passage: Passage


class Written(NamedTuple):
    """Passages emitted by one loop iteration; each field has shape (slots,).

    Attributes:
        index: ascending-order station index, or n_stations where the slot is
            empty (an out-of-range index: ``.at[].set(mode="drop")`` drops it).
        energy_kJ: kinetic energy at the passage, kJ.
        speed2_m2_s2: squared speed (the root is taken once, by ``record``).
        bounce_height_m: clearance, m (>= 0).
    """

    index: jax.Array
    energy_kJ: jax.Array
    speed2_m2_s2: jax.Array
    bounce_height_m: jax.Array


def _count_upto(stations_x_m: jax.Array, x_m: jax.Array) -> jax.Array:
    """Number of stations at or before ``x_m`` (stations ascending)."""
    return jnp.sum(stations_x_m <= x_m).astype(jnp.int32)


def start(stations_x_m: jax.Array, release_x_m: jax.Array) -> Cursor:
    """The cursor at release (``stations_x_m`` ascending)."""
    zero = jnp.zeros((), jnp.float64)
    first = _count_upto(stations_x_m, release_x_m)
    passage = Passage(release_x_m, jnp.asarray(False), *([zero] * 10))
    return Cursor(first, first, first, passage)


def backlog(cursor: Cursor) -> jax.Array:
    """bool: passages of the last event are still to be emitted."""
    return cursor.next < cursor.end


def after_event(cursor: Cursor, passage: Passage, x_end_m: jax.Array,
                stations_x_m: jax.Array) -> Cursor:
    """Take a new event (only when there is no backlog): the stations it passed
    first are those up to ``x_end_m`` beyond the farthest point reached before."""
    end = jnp.maximum(cursor.end, _count_upto(stations_x_m, x_end_m))
    return cursor._replace(passage=passage, end=end)


def _evaluate(p: Passage, x_s: jax.Array, ground_s: jax.Array, g: float):
    """Energy (kJ), squared speed (m^2/s^2) and clearance (m) of passage ``p``
    at ``x_s``."""
    safe_vx = jnp.where(p.vx_m_s > 0.0, p.vx_m_s, 1.0)
    ts = (x_s - p.x0_m) / safe_vx
    vzs = p.vz_m_s - g * ts
    v2_flight = p.vx_m_s * p.vx_m_s + vzs * vzs
    e_flight = 0.5 * p.mass_kg * (v2_flight + p.spin_energy_m2_s2) / 1000.0
    h_flight = jnp.maximum(p.z0_m + p.vz_m_s * ts - 0.5 * g * ts * ts - ground_s, 0.0)
    d_s = jnp.maximum((x_s - p.x0_m) / p.slope_cos, 0.0)
    v2_roll = speed2_after(p.u2_m2_s2, p.accel_m_s2, p.drag_per_m, d_s)
    e_roll = 0.5 * p.mass_kg * (1.0 + p.inertia_ratio) * v2_roll / 1000.0
    return (jnp.where(p.flight, e_flight, e_roll), jnp.where(p.flight, v2_flight, v2_roll),
            jnp.where(p.flight, h_flight, 0.0))


def emit(cursor: Cursor, stations_x_m: jax.Array, stations_z_m: jax.Array, g: float,
         slots: int) -> tuple[Cursor, Written]:
    """Emit up to ``slots`` waiting passages (the next ones in station order)."""
    n = stations_x_m.shape[0]
    j = cursor.next + jnp.arange(slots, dtype=jnp.int32)
    if n == 0:  # static: no stations, nothing to emit
        empty = jnp.zeros((slots,), jnp.float64)
        return cursor, Written(j * 0, empty, empty, empty)
    valid = j < cursor.end
    jc = jnp.minimum(j, n - 1)
    e, v2, h = _evaluate(cursor.passage, stations_x_m[jc], stations_z_m[jc], g)
    return (cursor._replace(next=jnp.minimum(cursor.end, cursor.next + slots)),
            Written(jnp.where(valid, j, n), e, v2, h))


def empty_values(shape: tuple[int, ...], dtype=jnp.float64) -> tuple:
    """(energy, squared speed, clearance) arrays of ``shape``, all NaN."""
    nan = jnp.full(shape, jnp.nan, dtype)
    return nan, nan, nan


def store(values: tuple, written: Written) -> tuple:
    """One block's (energy, squared speed, clearance) arrays with ``written``
    stored (empty slots dropped)."""
    at = written.index
    return tuple(v.at[at].set(w, mode="drop") for v, w in
                 zip(values, written[1:], strict=True))


def record(first: jax.Array, nxt: jax.Array, values: tuple, order: jax.Array) -> StationRecord:
    """The ``StationRecord`` in the caller's station order, from the cursor's
    ``first`` and ``next`` (leading batch shape B) and the stored values
    (B + (n_stations,), ascending order). ``order``: the argsort that sorted
    the caller's stations."""
    n = order.shape[0]
    idx = jnp.arange(n, dtype=jnp.int32)
    passed = (idx >= jnp.asarray(first)[..., None]) & (idx < jnp.asarray(nxt)[..., None])
    inv = jnp.zeros((n,), jnp.int32).at[order].set(idx)
    energy, speed2, height = values
    return StationRecord(passed=passed[..., inv], energy_kJ=energy[..., inv],
                         velocity_m_s=jnp.sqrt(speed2[..., inv]),
                         bounce_height_m=height[..., inv])
