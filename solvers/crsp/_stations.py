"""First passages of CRSP blocks at the analysis stations, written after the events.

The record and its conventions are ``solvers.stations``'. This module fills it
without touching every station at every event, and without putting station
work inside the event loop's step (both cost as much as the physics in
``python -m solvers.bench`` with 61 stations):

* Each event leaves a ``Passage``: the few numbers that give the block's speed,
  kinetic energy and clearance at any abscissa the event crossed (the flight's
  parabola, or the closed-form rolling speed of ``_contact.speed2_after``),
  and the abscissa where the event ended. A loop step in which the block did
  not move leaves a passage that ends at -inf (it passes nothing).
* The event loop keeps the passages of its last few steps (a (lanes, steps)
  buffer; one step for ``simulate``) and hands them to ``write`` between
  steps. Stations are taken in ascending order. A block has passed a station
  once its centre has reached it moving downslope; positions are continuous
  from event to event, so the stations first passed during an event are
  exactly those between the farthest point reached before it (exclusive) and
  its end point (inclusive): the sorted indices ``[reached before, reached
  after)``, with ``reached`` the count of stations at or before the farthest
  point so far (a running maximum over the events).
* ``write`` lists those (event, station) pairs of all lanes and steps one
  after another and evaluates them ``width`` at a time (a prefix sum over the
  pair counts and a search give each of the ``width`` slots its event and
  station), storing each value straight into the caller's (rows, n_stations)
  arrays, in the caller's station order. Its cost follows the number of
  passages, not lanes x steps x stations, none of it runs inside the physics
  step, and ``record`` then builds the record without rewriting the arrays.

Stations at or behind the release point are never passed (the block starts
there: ``reached`` starts at ``first_beyond(release)``), and neither is a
station the block reaches only by rolling back and then forward again over
ground it had already covered: this is the "first crossing moving downslope"
of ``solvers.stations``.

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

__all__ = ["Passage", "empty_values", "first_beyond", "record", "write"]


class Passage(NamedTuple):
    """One event's motion, enough to evaluate it at any abscissa it crossed.

    Attributes:
        x0_m: abscissa at the start of the event, m.
        x_end_m: abscissa at its end, m (-inf: no event, nothing passed).
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
    x_end_m: jax.Array
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


def _count_upto(stations_x_m: jax.Array, x_m: jax.Array) -> jax.Array:
    """Number of stations at or before ``x_m`` (stations ascending; any shape)."""
    return jnp.sum(stations_x_m <= x_m[..., None], axis=-1, dtype=jnp.int32)


def first_beyond(stations_x_m: jax.Array, release_x_m: jax.Array) -> jax.Array:
    """Index of the first station beyond the release point (``reached`` at
    release; ``stations_x_m`` ascending)."""
    return _count_upto(stations_x_m, release_x_m)


def _evaluate(p: Passage, x_s: jax.Array, ground_s: jax.Array, g: float):
    """Energy (kJ), speed (m/s) and clearance (m) of passage ``p`` at ``x_s``."""
    safe_vx = jnp.where(p.vx_m_s > 0.0, p.vx_m_s, 1.0)
    ts = (x_s - p.x0_m) / safe_vx
    vzs = p.vz_m_s - g * ts
    v2_flight = p.vx_m_s * p.vx_m_s + vzs * vzs
    e_flight = 0.5 * p.mass_kg * (v2_flight + p.spin_energy_m2_s2) / 1000.0
    h_flight = jnp.maximum(p.z0_m + p.vz_m_s * ts - 0.5 * g * ts * ts - ground_s, 0.0)
    d_s = jnp.maximum((x_s - p.x0_m) / p.slope_cos, 0.0)
    v2_roll = speed2_after(p.u2_m2_s2, p.accel_m_s2, p.drag_per_m, d_s)
    e_roll = 0.5 * p.mass_kg * (1.0 + p.inertia_ratio) * v2_roll / 1000.0
    return (jnp.where(p.flight, e_flight, e_roll),
            jnp.sqrt(jnp.where(p.flight, v2_flight, v2_roll)),
            jnp.where(p.flight, h_flight, 0.0))


def write(values: tuple, rows: jax.Array, reached: jax.Array, passages: Passage,
          stations_x_m: jax.Array, stations_z_m: jax.Array, order: jax.Array, g: float,
          width: int) -> tuple[jax.Array, tuple]:
    """Store the first passages of a buffer of events (pure; not per block).

    Args:
        values: (energy kJ, speed m/s, clearance m) arrays of shape
            (n_rows, n_stations), in the caller's station order.
        rows: (B,) the row of ``values`` of each lane's block (n_rows or more:
            the lane's passages are dropped).
        reached: (B,) int32, stations passed by each lane's block so far.
        passages: ``Passage`` with fields of shape (B, E): E events per lane,
            in the order they happened.
        stations_x_m, stations_z_m: (n_stations,) ascending, ground under them.
        order: the argsort that sorted the caller's stations (ascending station
            i is the caller's column ``order[i]``).
        g: gravity, m/s^2.
        width: passages evaluated per pass (more take further passes).

    Returns:
        (reached after the E events, values with the passages stored).
    """
    n = stations_x_m.shape[0]
    if n == 0:  # static: no stations, nothing to write
        return reached, values
    b, e = passages.x_end_m.shape
    ends = jax.lax.cummax(jnp.maximum(_count_upto(stations_x_m, passages.x_end_m),
                                      reached[:, None]), axis=1)
    starts = jnp.concatenate([reached[:, None], ends[:, :-1]], axis=1).reshape(-1)
    count = ends.reshape(-1) - starts
    stop = jnp.cumsum(count)  # passages of pairs 0..i
    total = stop[-1]
    flat = jax.tree_util.tree_map(lambda a: a.reshape(-1), passages)
    row_of = jnp.repeat(rows, e)
    n_rows = values[0].shape[0]

    def one_pass(carry):
        base, values = carry
        slot = base + jnp.arange(width, dtype=jnp.int32)
        pair = jnp.minimum(jnp.searchsorted(stop, slot, side="right"), b * e - 1)
        station = jnp.clip(starts[pair] + slot - (stop[pair] - count[pair]), 0, n - 1)
        p = jax.tree_util.tree_map(lambda a: a[pair], flat)
        got = _evaluate(p, stations_x_m[station], stations_z_m[station], g)
        row = jnp.where(slot < total, row_of[pair], n_rows)  # empty slots: dropped
        values = tuple(v.at[row, order[station]].set(w, mode="drop")
                       for v, w in zip(values, got, strict=True))
        return base + width, values

    _, values = jax.lax.while_loop(lambda c: c[0] < total, one_pass,
                                   (jnp.zeros((), jnp.int32), values))
    return ends[:, -1], values


def empty_values(shape: tuple[int, ...], dtype=jnp.float64) -> tuple:
    """(energy, speed, clearance) arrays of ``shape``, all NaN."""
    nan = jnp.full(shape, jnp.nan, dtype)
    return nan, nan, nan


def record(first: jax.Array, reached: jax.Array, values: tuple, order: jax.Array) -> StationRecord:
    """The ``StationRecord`` (caller's station order) from ``first`` and
    ``reached`` (leading batch shape B) and the values ``write`` stored (B +
    (n_stations,)). ``order``: the argsort that sorted the caller's stations."""
    n = order.shape[0]
    idx = jnp.arange(n, dtype=jnp.int32)
    rank = jnp.zeros((n,), jnp.int32).at[order].set(idx)  # caller's j: ascending rank
    passed = (rank >= jnp.asarray(first)[..., None]) & (rank < jnp.asarray(reached)[..., None])
    energy, speed, height = values
    return StationRecord(passed=passed, energy_kJ=energy, velocity_m_s=speed,
                         bounce_height_m=height)
