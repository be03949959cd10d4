"""CRSP rockfall model for ONE block: state, events, simulate (its inputs: ``_params``).

The rock is a lumped mass with a radius (for roughness and rotational inertia)
moving along a 2D height-field profile. Its history is a sequence of events,
each solved in closed form:

* FLIGHT: exact parabola to the next impact (``_flight.next_impact``). A
  landing whose speed into the mean segment is below ``rolling_threshold_m_s``
  is a touch-down: the rock goes on rolling with the velocity's component
  along the segment (no impact law, no random draw). Any faster landing is a
  CRSP impact on a roughness-tilted facet (``_impact.crsp_impact``); if the
  rebound's normal speed relative to the mean segment is below the threshold
  the rock stays on the ground (CONTACT).
* CONTACT: rolling with Coulomb resistance and the mean asperity loss of the
  rough surface, in closed form, to the segment's end or to rest
  (``_contact``). At a vertex (our own treatment, see ``vertex_transition``):
  collinear segments continue; a concave break whose normal speed reaches the
  threshold is a CRSP impact on the next segment, a gentler one keeps the
  tangential component; a convex break launches the rock only when it
  physically separates from the edge (centripetal condition) and the hop is a
  real one (its landing speed into the next segment reaches the threshold);
  otherwise the rock rounds the edge and rolls on.
* STOPPED: at rest where rest is possible (``tan|beta| <= mu``).
* LEFT_PROFILE: passed either end of the profile (not a stop).
* A protection barrier (``_barrier``; none by default): the event in which
  the block first crosses its abscissa downslope is evaluated there; a block
  that passes lower than its height is stopped (STOPPED_BY_BARRIER) or breaks
  through with reduced energy, and the event ends at the barrier. A run
  without a barrier (``Params.barrier_x_m`` None) compiles none of its code.
* A break (``_effects``) is recorded in ``Result.breakup`` (``_break``) when
  ``Settings.split_at_break`` is set: the run then ends there, for a caller
  that runs every fragment on from the record. Without it (the default) the
  model follows one fragment and compiles none of the record's code.

Status codes are those of ``solvers.status``. After every event the block must
lie on or above the ground (``z >= ground - GROUND_TOL_M``) with finite values;
otherwise its status is ``INVALID`` (an error, never a stop or a passage).

The loop is a ``lax.while_loop`` bounded by a per-block event budget
(``event_budget``: it grows with the number of segments and with the slope
length over the block radius). A block still moving at the bound is flagged
``BUDGET``, never counted as stopped. This forward model is not
reverse-differentiated (calibration uses common-random-number objectives; see
``calib``).

Randomness: ``key`` is split into a release key (release jitter, height and
speed; ``init``) and an event key; the i-th CRSP impact (not the i-th event)
draws its roughness from a counter-based hash of the event key's words and i
(``solvers._rng``). Events
that draw nothing (window hops of a long flight, segment ends while rolling,
touch-downs) do not consume draws, so inserting collinear vertices into a
profile leaves every block's impact sequence, and so its result, unchanged
up to round-off. A block's history depends only on its own key, whatever the
batch it runs in.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from solvers._rng import key_words, uniform_from_counter
from solvers.crsp._barrier import (
    NO_CUT,
    Barrier,
    BarrierRecord,
    Crossing,
    barrier_site,
    cut,
    flight_at,
    rolling_at,
    start_crossing,
)
from solvers.crsp._barrier import record as barrier_record
from solvers.crsp._break import BreakRecord, no_break, note_break
from solvers.crsp._contact import asperity_loss, contact_move
from solvers.crsp._effects import breaks, in_belt, size_scaled
from solvers.crsp._flight import next_impact
from solvers.crsp._impact import crsp_impact, roughness_tilt
from solvers.crsp._params import Block, Params, Settings
from solvers.crsp._stations import Passage, empty_values, first_beyond, write
from solvers.crsp._stations import record as station_record
from solvers.crsp._vertex import vertex_transition
from solvers.profile import Profile, ground_z, segment_angles_rad, segment_index
from solvers.stations import StationRecord
from solvers.status import (
    BUDGET,
    GROUND_TOL_M,
    INVALID,
    LEFT_PROFILE,
    STOPPED,
    STOPPED_BY_BARRIER,
)
from solvers.truncated_normal import nonnegative_normal

__all__ = [
    "BUDGET",
    "CONTACT",
    "FLIGHT",
    "INVALID",
    "LEFT_PROFILE",
    "MAX_EVENTS",
    "STOPPED",
    "STOPPED_BY_BARRIER",
    "Result",
    "State",
    "event_budget",
    "raw_result",
    "result_from_state",
    "running",
    "simulate",
    "simulate_from",
    "sorted_stations",
]

# modes of a moving block (State.mode); a block that is not moving holds its
# final status (solvers.status: STOPPED, LEFT_PROFILE, INVALID) in the same field
FLIGHT, CONTACT = 0, 1
MAX_EVENTS = BUDGET  # former name of the budget status, kept for old imports

# per-block event budget (``event_budget``); see its docstring for the measurements
_BUDGET_BASE = 200
_BUDGET_PER_SEGMENT = 4
_BUDGET_PER_RADIUS = 1.0


def event_budget(profile: Profile, radius_m: jax.Array, settings: Settings) -> jax.Array:
    """Event budget of one block: ``Settings.max_events`` if given, else

        ``200 + 4 n_segments + L / r``

    with L the profile's slope length and r the block radius. Rolling costs one
    event per segment passed (a rock may roll back and forth a few times),
    a long flight one event per ``window`` segments, and bouncing about one
    event per impact; small rocks on rough ground bounce at most every few
    radii. The constants leave a wide margin over the event counts measured on
    the prior box of the calibration (see ``tests/test_crsp_invariants.py``:
    no block of 0.1-2 m diameter reaches the budget).
    """
    if settings.max_events is not None:
        return jnp.asarray(settings.max_events, jnp.int32)
    n_seg = profile.x_m.shape[0] - 1
    length_m = jnp.sum(jnp.hypot(jnp.diff(profile.x_m), jnp.diff(profile.z_m)))
    per_radius = jnp.ceil(_BUDGET_PER_RADIUS * length_m / radius_m)
    budget = _BUDGET_BASE + _BUDGET_PER_SEGMENT * n_seg + jnp.minimum(per_radius, 2.0**30)
    return budget.astype(jnp.int32)


class State(NamedTuple):
    """State of one block between events.

    Attributes:
        x_m, z_m: position of the lumped mass, m.
        vx_m_s, vz_m_s: velocity, m/s.
        spin_rad_s: rolling-positive spin, rad/s.
        seg: segment under the block.
        mode: FLIGHT or CONTACT while moving; then the final status
            (``solvers.status``: STOPPED, STOPPED_BY_BARRIER, LEFT_PROFILE or
            INVALID).
        n_events: events so far.
        n_impacts: CRSP impacts so far (the counter of the roughness draws).
        pending: bool, the next event is an immediate CRSP impact on ``seg``
            (a rebound into the mean slope, or a rolling rock meeting a
            concave break fast enough).
        radius_m: current radius (the fragment's after a break), m.
        fragmented: bool, the block has broken (``_effects``).
        budget: int, the event budget of this block (``event_budget``).
        barrier: ``_barrier.Crossing``, the block's meeting with the barrier
            (None in a run without one).
        breakup: ``_break.BreakRecord``, the block's break, if it broke (None
            unless ``Settings.split_at_break``).
    """

    x_m: jax.Array
    z_m: jax.Array
    vx_m_s: jax.Array
    vz_m_s: jax.Array
    spin_rad_s: jax.Array
    seg: jax.Array
    mode: jax.Array
    n_events: jax.Array
    n_impacts: jax.Array
    pending: jax.Array
    radius_m: jax.Array
    fragmented: jax.Array
    budget: jax.Array
    barrier: Crossing | None
    breakup: BreakRecord | None


class Result(NamedTuple):
    """Outcome for one block.

    Attributes:
        runout_m: horizontal distance from the release point to the final
            position, m (for blocks not stopped: to where they were at the end;
            never a runout unless ``solvers.status.finished(status)``).
        stop_x_m, stop_z_m: final position, m.
        stopped: bool, at rest: where rest is possible, or caught by the barrier.
        status: ``solvers.status`` code: STOPPED, STOPPED_BY_BARRIER,
            LEFT_PROFILE, BUDGET or INVALID.
        n_events, n_impacts: counts.
        release_x_m: the release abscissa actually used, m.
        stations: ``StationRecord`` with fields of shape (n_stations,).
        barrier: ``_barrier.BarrierRecord``, what the block did at the barrier
            (None in a run without one: ``Params.barrier_x_m`` None).
        breakup: ``_break.BreakRecord``, the block's break (``_effects``), if
            any (None unless ``Settings.split_at_break``).
    """

    runout_m: jax.Array
    stop_x_m: jax.Array
    stop_z_m: jax.Array
    stopped: jax.Array
    status: jax.Array
    n_events: jax.Array
    n_impacts: jax.Array
    release_x_m: jax.Array
    stations: StationRecord
    barrier: BarrierRecord | None
    breakup: BreakRecord | None


def _segment_geometry(profile: Profile, seg):
    xa, xb = profile.x_m[seg], profile.x_m[seg + 1]
    za, zb = profile.z_m[seg], profile.z_m[seg + 1]
    beta = jnp.arctan2(zb - za, xb - xa)
    return xa, xb, za, zb, beta


def _line_z(profile: Profile, seg, x_m):
    """Height of segment ``seg``'s line at ``x_m``."""
    xa, xb = profile.x_m[seg], profile.x_m[seg + 1]
    za, zb = profile.z_m[seg], profile.z_m[seg + 1]
    return za + (zb - za) * (x_m - xa) / (xb - xa)


class SegmentTable(NamedTuple):
    """Per-segment constants, computed once per block outside the event loop
    (transcendentals inside the loop dominated its cost on CPU). Shapes (S,).
    The ``*_frag`` fields are those of a fragment (``_effects``); ``barrier``:
    the run's ``_barrier.Barrier`` (scalars), looked up on the profile once, or
    None: no barrier, and no barrier code in the compiled loop."""

    beta: jax.Array
    cos: jax.Array
    sin: jax.Array
    length: jax.Array
    mu: jax.Array
    theta_max: jax.Array
    drag: jax.Array
    Kn: jax.Array
    Kt: jax.Array
    theta_max_frag: jax.Array
    drag_frag: jax.Array
    Kn_frag: jax.Array
    Kt_frag: jax.Array
    mass_frag_kg: jax.Array
    belt_keep: jax.Array
    barrier: Barrier | None


def segment_table(profile: Profile, params: Params, block: Block) -> SegmentTable:
    """Angles, their cos/sin, rolling resistance ``tan(phi_r) + Delta-mu``, the
    roughness angle ``theta_max = arctan(S / R)`` (see ``_impact.roughness_tilt``),
    the rolling asperity loss rate ``lambda(theta_max) / R`` (``_contact``) and the
    (size-scaled, ``_effects``) restitution per segment, for the block and for a
    fragment of it."""
    dx = jnp.diff(profile.x_m)
    dz = jnp.diff(profile.z_m)
    beta = segment_angles_rad(profile)
    zone = profile.zone_id
    r = block.radius_m
    r_frag = r * params.frag_radius_ratio
    gamma = params.restitution_size_exponent
    Kn, Kt = params.Kn[zone], params.Kt[zone]
    theta = roughness_tilt(1.0, params.roughness_m[zone], r)
    theta_frag = roughness_tilt(1.0, params.roughness_m[zone], r_frag)
    k = block.inertia_ratio
    return SegmentTable(
        beta=beta, cos=jnp.cos(beta), sin=jnp.sin(beta), length=jnp.hypot(dx, dz),
        mu=jnp.tan(jnp.deg2rad(params.rolling_friction_deg[zone])) + params.rolling_resistance,
        theta_max=theta, drag=asperity_loss(theta, k) / r,
        Kn=size_scaled(Kn, r, gamma), Kt=size_scaled(Kt, r, gamma),
        theta_max_frag=theta_frag, drag_frag=asperity_loss(theta_frag, k) / r_frag,
        Kn_frag=size_scaled(Kn, r_frag, gamma), Kt_frag=size_scaled(Kt, r_frag, gamma),
        mass_frag_kg=block.mass_kg * params.frag_radius_ratio**3,
        belt_keep=jnp.sqrt(1.0 - params.belt_loss),
        barrier=None if params.barrier_x_m is None else barrier_site(
            profile, params.barrier_x_m, params.barrier_height_m, params.barrier_capacity_kJ),
    )


def init(params: Params, block: Block, key: jax.Array, profile: Profile,
         settings: Settings = Settings()) -> State:
    """Initial state at the release point (``key``: release key).

    Release abscissa ``x0 = release_x_m + U spread_m``, U uniform from ``key``.
    Release height and speed are uncertain inputs: with their sds
    (``Params.release_height_sd_m``, ``release_speed_sd_m_s``) positive, the
    block's height above the ground is a draw of N(release_height_m, sd^2)
    truncated to >= 0, and its speed one of N(|v|, sd^2) truncated to >= 0
    in the direction of (release_vx_m_s, release_vz_m_s) (horizontal, +x,
    where that velocity is 0), by the inverse CDF
    (``solvers.truncated_normal``), from two uniforms of ``fold_in(key, 1)``
    (so U, and every result with both sds 0, are those of a point release).
    A NEGATIVE release height (a tracked release below a raster's ground) is
    then a release from the error's tail above the ground; with sd 0 it is
    clipped: on the ground. No block starts below the ground.

    The block starts in flight, or in ground contact when it is released on the
    ground (height 0) with a velocity that does not leave the slope (normal
    component below the rolling threshold)."""
    u = jax.random.uniform(key, dtype=jnp.float64)
    x0 = params.release_x_m + u * params.release_x_spread_m
    x0 = jnp.clip(x0, profile.x_m[0], profile.x_m[-1])
    u_h, u_v = jax.random.uniform(jax.random.fold_in(key, 1), (2,), dtype=jnp.float64)
    h0 = nonnegative_normal(u_h, params.release_height_m, params.release_height_sd_m)
    z0 = ground_z(profile, x0) + h0
    zero = jnp.zeros((), jnp.float64)
    seg = segment_index(profile, x0)
    *_, beta = _segment_geometry(profile, seg)
    vx0, vz0 = zero + params.release_vx_m_s, zero + params.release_vz_m_s
    # the drawn speed along the given velocity's direction (+x where it is 0)
    v0 = jnp.hypot(vx0, vz0)
    moving = v0 > 0.0
    safe_v0 = jnp.where(moving, v0, 1.0)
    v1 = nonnegative_normal(u_v, v0, params.release_speed_sd_m_s)
    drawn = params.release_speed_sd_m_s > 0.0
    vx0 = jnp.where(drawn, v1 * jnp.where(moving, vx0 / safe_v0, 1.0), vx0)
    vz0 = jnp.where(drawn, v1 * jnp.where(moving, vz0 / safe_v0, 0.0), vz0)
    # released on the ground without leaving it: start rolling along the segment
    on_ground = (h0 <= 0.0) & (
        -vx0 * jnp.sin(beta) + vz0 * jnp.cos(beta) < params.rolling_threshold_m_s)
    u0 = vx0 * jnp.cos(beta) + vz0 * jnp.sin(beta)
    return State(
        x_m=x0, z_m=z0, vx_m_s=jnp.where(on_ground, u0 * jnp.cos(beta), vx0),
        vz_m_s=jnp.where(on_ground, u0 * jnp.sin(beta), vz0), spin_rad_s=zero,
        seg=seg, mode=jnp.where(on_ground, CONTACT, FLIGHT).astype(jnp.int32),
        n_events=jnp.asarray(0, jnp.int32), n_impacts=jnp.asarray(0, jnp.int32),
        pending=jnp.asarray(False),
        radius_m=zero + block.radius_m, fragmented=jnp.asarray(False),
        budget=event_budget(profile, block.radius_m, settings),
        barrier=None if params.barrier_x_m is None else start_crossing(x0, params.barrier_x_m),
        breakup=no_break() if settings.split_at_break else None,
    )


def _flight_event(state: State, params: Params, block: Block, key, profile: Profile,
                  table: SegmentTable, settings: Settings) -> tuple[State, Passage]:
    """A flight to its landing (touch-down or CRSP impact), to the window's
    edge, or into the barrier's net. Longer than 80 lines: one event in closed
    form whose parts share the landing's values; a split would only pass them
    around."""
    g = settings.g_m_s2
    x, z, vx, vz = state.x_m, state.z_m, state.vx_m_s, state.vz_m_s
    fh = next_impact(profile, state.seg, x, z, vx, vz, g, settings.window)
    # a pending impact happens at once on state.seg (no flight)
    fh = fh._replace(t_s=jnp.where(state.pending, 0.0, fh.t_s),
                     hit=fh.hit | state.pending,
                     seg=jnp.where(state.pending, state.seg, fh.seg),
                     left_profile=fh.left_profile & ~state.pending)
    t = fh.t_s
    x1 = x + vx * t
    z1 = z + vz * t - 0.5 * g * t * t
    vz1 = vz - g * t

    # this flight, for the stations it passes (_stations)
    r, k = state.radius_m, block.inertia_ratio
    m = jnp.where(state.fragmented, table.mass_frag_kg, block.mass_kg)
    zero = jnp.zeros_like(x)
    spin_energy = k * (r * state.spin_rad_s) ** 2
    passage = Passage(x0_m=x, x_end_m=x1, flight=jnp.asarray(True), z0_m=z, vx_m_s=vx, vz_m_s=vz,
                      spin_energy_m2_s2=spin_energy, u2_m2_s2=zero,
                      accel_m_s2=zero, drag_per_m=zero, slope_cos=zero + 1.0, mass_kg=m,
                      inertia_ratio=k)

    # the barrier (_barrier): a flight into its net ends there, before any landing
    bc = NO_CUT
    if table.barrier is not None:  # static: without a barrier none of this is compiled
        site = table.barrier
        bc = cut(state.barrier, site, state.barrier.open & (x < site.x_m) & (x1 >= site.x_m),
                 flight_at(x, z, vx, vz, state.spin_rad_s, spin_energy, m, site, g), site.seg)

    seg = fh.seg
    xa, xb = profile.x_m[seg], profile.x_m[seg + 1]
    za, zb = profile.z_m[seg], profile.z_m[seg + 1]
    beta, cb, sb = table.beta[seg], table.cos[seg], table.sin[seg]
    thr = params.rolling_threshold_m_s
    # speed into the mean segment at landing: a touch-down below the threshold
    hit = fh.hit & ~bc.net
    vn_in = vx * sb - vz1 * cb
    touch = hit & (vn_in < thr)
    impact = hit & ~touch
    u_touch = vx * cb + vz1 * sb

    # CRSP impact on the hit segment (used only if ``impact``)
    frag = state.fragmented
    theta_max = jnp.where(frag, table.theta_max_frag[seg], table.theta_max[seg])
    tilt = uniform_from_counter(key, state.n_impacts) * theta_max
    imp = crsp_impact(vx, vz1, state.spin_rad_s, beta, tilt,
                      jnp.where(frag, table.Kn_frag[seg], table.Kn[seg]),
                      jnp.where(frag, table.Kt_frag[seg], table.Kt[seg]),
                      r, k, slope_cos=cb, slope_sin=sb)
    # optional effects (_effects): a break on a hard impact, a vegetation belt
    brk = impact & breaks(m, vn_in, params.frag_energy_kJ, frag)
    r_new = jnp.where(brk, r * params.frag_radius_ratio, r)
    f = jnp.where(in_belt(x1, params.belt_start_m, params.belt_end_m), table.belt_keep, 1.0)
    f_spin = f * jnp.where(brk, params.frag_speed_ratio / params.frag_radius_ratio, 1.0)
    f = f * jnp.where(brk, params.frag_speed_ratio, 1.0)
    imp = imp._replace(vx_m_s=f * imp.vx_m_s, vz_m_s=f * imp.vz_m_s,
                       spin_rad_s=f_spin * imp.spin_rad_s)
    vn_mean = -imp.vx_m_s * sb + imp.vz_m_s * cb
    roll = touch | (jnp.abs(vn_mean) < thr)
    into_slope = vn_mean <= -thr
    u_t = jnp.where(touch, u_touch, imp.vx_m_s * cb + imp.vz_m_s * sb)
    z_line = za + (zb - za) * (x1 - xa) / (xb - xa)

    free = jnp.where(fh.left_profile & ~bc.net, LEFT_PROFILE, FLIGHT)
    mode = jnp.where(hit, jnp.where(roll, CONTACT, FLIGHT),
                     jnp.where(bc.caught, STOPPED_BY_BARRIER, free)).astype(jnp.int32)
    new = State(
        x_m=jnp.where(bc.net, bc.x_m, x1),
        z_m=jnp.where(hit, z_line, jnp.where(bc.net, bc.at.z_m, z1)),
        vx_m_s=jnp.where(hit, jnp.where(roll, u_t * cb, imp.vx_m_s), bc.keep * vx),
        vz_m_s=jnp.where(hit, jnp.where(roll, u_t * sb, imp.vz_m_s),
                         bc.keep * jnp.where(bc.net, bc.at.vz_m_s, vz1)),
        spin_rad_s=jnp.where(hit, jnp.where(roll, u_t / r_new, imp.spin_rad_s),
                             bc.keep * state.spin_rad_s),
        seg=jnp.where(bc.net, bc.seg, seg),
        mode=mode,
        n_events=state.n_events + 1,
        n_impacts=state.n_impacts + impact.astype(jnp.int32),
        pending=impact & ~roll & into_slope,
        radius_m=r_new,
        fragmented=frag | brk,
        budget=state.budget,
        barrier=bc.crossing,
        breakup=state.breakup,
    )
    if settings.split_at_break:  # static: the break, for a caller that follows every fragment
        new = note_break(state, new, brk, vx, vz1, block, params, table.mass_frag_kg, settings)
    return new, passage


def _contact_event(state: State, params: Params, block: Block, profile: Profile,
                   table: SegmentTable, settings: Settings) -> tuple[State, Passage]:
    """A rolling move to the segment's end (and what happens at its vertex), to
    rest, or into the barrier's net. Longer than 80 lines for the reason of
    ``_flight_event``."""
    g = settings.g_m_s2
    n_seg = profile.x_m.shape[0] - 1
    seg = state.seg
    xa, xb = profile.x_m[seg], profile.x_m[seg + 1]
    za, zb = profile.z_m[seg], profile.z_m[seg + 1]
    beta, cb, sb = table.beta[seg], table.cos[seg], table.sin[seg]
    x = state.x_m
    r = state.radius_m
    k = block.inertia_ratio
    mu = table.mu[seg] + jnp.where(in_belt(x, params.belt_start_m, params.belt_end_m),
                                   params.belt_loss, 0.0)
    drag = jnp.where(state.fragmented, table.drag_frag[seg], table.drag[seg])
    u = state.vx_m_s * cb + state.vz_m_s * sb
    mv = contact_move(u, cb, sb, mu, jnp.maximum((xb - x) / cb, 0.0),
                      jnp.maximum((x - xa) / cb, 0.0), k, g, drag)
    # a move to the segment's end ends exactly on its vertex (no round-off)
    x_end = jnp.where(mv.direction > 0, xb, xa)
    x1 = jnp.where(mv.at_end, x_end, jnp.clip(x + mv.dist_m * cb, xa, xb))
    z1 = jnp.where(mv.at_end, jnp.where(mv.direction > 0, zb, za),
                   za + (zb - za) * (x1 - xa) / (xb - xa))

    # this move, for the stations it passes (_stations)
    m = jnp.where(state.fragmented, table.mass_frag_kg, block.mass_kg)
    zero = jnp.zeros_like(x)
    passage = Passage(x0_m=x, x_end_m=x1, flight=jnp.asarray(False), z0_m=zero, vx_m_s=zero,
                      vz_m_s=zero, spin_energy_m2_s2=zero, u2_m2_s2=u * u,
                      accel_m_s2=mv.accel_m_s2, drag_per_m=mv.drag_per_m, slope_cos=cb,
                      mass_kg=m, inertia_ratio=k)

    # the barrier (_barrier): a move into its net ends there, before the segment's end
    bc = NO_CUT
    if table.barrier is not None:  # static: without a barrier none of this is compiled
        site = table.barrier
        bc = cut(state.barrier, site, state.barrier.open & (mv.direction > 0) & (x < site.x_m)
                 & (x1 >= site.x_m), rolling_at(x, state.z_m, u * u, mv.accel_m_s2,
                                                 mv.drag_per_m, cb, sb, m, k, r, site), seg)

    # what happens at the segment's end
    step = mv.direction.astype(jnp.int32)
    nxt = seg + step
    off_end = (nxt < 0) | (nxt >= n_seg)
    nxt_c = jnp.clip(nxt, 0, n_seg - 1)
    c2, s2 = table.cos[nxt_c], table.sin[nxt_c]
    speed = jnp.abs(mv.u_end_m_s)
    vt = vertex_transition(speed, mv.direction, beta, table.beta[nxt_c], r, k,
                           params.rolling_threshold_m_s, g, table.length[nxt_c])
    at_end = mv.at_end
    switch = at_end & ~off_end & ~bc.net
    launch = switch & vt.launch
    impact = switch & vt.impact
    pit_rest = switch & vt.rest
    roll_on = switch & ~vt.launch & ~vt.impact & ~vt.rest
    mode = jnp.where(bc.net, jnp.where(bc.caught, STOPPED_BY_BARRIER, CONTACT),
                     jnp.where(mv.stopped | pit_rest, STOPPED,
                               jnp.where(at_end & off_end, LEFT_PROFILE,
                                         jnp.where(launch | impact, FLIGHT, CONTACT))
                               )).astype(jnp.int32)
    d = mv.direction
    u_next = d * vt.u_next_m_s
    v_launch_x = speed * d * jnp.cos(vt.launch_rad)
    v_launch_z = -speed * jnp.sin(vt.launch_rad)
    vx_new = jnp.where(roll_on, u_next * c2,
                       jnp.where(launch, v_launch_x, mv.u_end_m_s * cb))
    vz_new = jnp.where(roll_on, u_next * s2,
                       jnp.where(launch, v_launch_z, mv.u_end_m_s * sb))
    speed_along = jnp.where(roll_on, vt.u_next_m_s, speed)
    stopped = mode == STOPPED
    return State(
        x_m=jnp.where(bc.net, bc.x_m, x1),
        z_m=jnp.where(bc.net, bc.at.z_m, z1),
        vx_m_s=jnp.where(bc.net, bc.keep * bc.at.vx_m_s, jnp.where(stopped, 0.0, vx_new)),
        vz_m_s=jnp.where(bc.net, bc.keep * bc.at.vz_m_s, jnp.where(stopped, 0.0, vz_new)),
        spin_rad_s=jnp.where(bc.net, bc.keep * bc.at.spin_rad_s,
                             jnp.where(stopped, 0.0, d * speed_along / r)),
        seg=jnp.where(switch, nxt_c, seg).astype(jnp.int32),
        mode=mode,
        n_events=state.n_events + 1,
        n_impacts=state.n_impacts,
        pending=impact,
        radius_m=r,
        fragmented=state.fragmented,
        budget=state.budget,
        barrier=bc.crossing,
        breakup=state.breakup,
    ), passage


def _moving(mode) -> jax.Array:
    return (mode == FLIGHT) | (mode == CONTACT)


def running(state: State) -> jax.Array:
    """bool: the block's loop goes on: it is moving within its event budget."""
    return _moving(state.mode) & (state.n_events < state.budget)


def step(state: State, params: Params, block: Block, key: jax.Array, profile: Profile,
         table: SegmentTable, settings: Settings) -> tuple[State, Passage]:
    """One step of the event loop (pure): the next event (a flight to the next impact,
    or a contact move), and its ``_stations.Passage`` for the caller to write
    (``_stations.write``).

    The event happens only if the block is moving within its budget; a finished
    block is unchanged and its passage ends at -inf (it passes nothing). An
    event that crosses the barrier ends there when the block hits the net
    (``_barrier``). After
    an event the block must be on or above the ground of its segment
    (``z >= ground - GROUND_TOL_M``) with finite values, else its mode becomes
    ``INVALID``. ``key`` is the event key's two uint32 words
    (``solvers._rng.key_words``)."""
    go = running(state)
    fl, fl_pass = _flight_event(state, params, block, key, profile, table, settings)
    co, co_pass = _contact_event(state, params, block, profile, table, settings)
    in_flight = state.mode == FLIGHT
    new = jax.tree_util.tree_map(lambda a, b: jnp.where(in_flight, a, b), fl, co)
    passage = jax.tree_util.tree_map(lambda a, b: jnp.where(in_flight, a, b), fl_pass, co_pass)
    ground = _line_z(profile, new.seg, new.x_m)
    finite = (jnp.isfinite(new.x_m) & jnp.isfinite(new.z_m) & jnp.isfinite(new.vx_m_s)
              & jnp.isfinite(new.vz_m_s))
    bad = ~finite | (new.z_m < ground - GROUND_TOL_M)
    new = new._replace(mode=jnp.where(bad, INVALID, new.mode).astype(jnp.int32))
    new = jax.tree_util.tree_map(lambda a, b: jnp.where(go, a, b), new, state)
    return new, passage._replace(x_end_m=jnp.where(go, new.x_m, -jnp.inf))


def sorted_stations(profile: Profile, stations_x_m) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(ascending stations, ground under them, the argsort that sorts them)."""
    st = jnp.zeros((0,), jnp.float64) if stations_x_m is None else jnp.asarray(
        stations_x_m, jnp.float64).reshape(-1)
    order = jnp.argsort(st)
    xs = st[order]
    return xs, ground_z(profile, xs), order


def simulate(
    params: Params,
    block: Block,
    key: jax.Array,
    *,
    profile: Profile,
    stations_x_m: jax.Array | None = None,
    settings: Settings = Settings(),
) -> Result:
    """Simulate ONE block from release to rest (use ``jax.vmap`` for batches).

    Args:
        params: ``Params`` (see ``params_from_profile``).
        block: ``Block`` (see ``make_block``).
        key: PRNG key of this block.
        profile: the slope.
        stations_x_m: (n_stations,) analysis abscissae, m, or None.
        settings: static ``Settings``.

    Returns:
        ``Result``.
    """
    release_key, event_key = jax.random.split(key)
    state0 = init(params, block, release_key, profile, settings)
    return simulate_from(state0, params, block, event_key, profile=profile,
                         stations_x_m=stations_x_m, settings=settings)


def simulate_from(state0: State, params: Params, block: Block, event_key: jax.Array, *,
                  profile: Profile, stations_x_m: jax.Array | None = None,
                  settings: Settings = Settings()) -> Result:
    """``simulate`` from the state ``state0`` with the event key ``event_key`` (the
    i-th impact draws from its words and i): the event loop of every run, from a
    release (``simulate``) or from a break (``_break.simulate_fragment``). The
    runout is counted from ``state0.x_m``; stations at or behind it are not passed."""
    xs, zs, order = sorted_stations(profile, stations_x_m)
    body = functools.partial(step, params=params, block=block, key=key_words(event_key),
                             profile=profile, table=segment_table(profile, params, block),
                             settings=settings)
    first = first_beyond(xs, state0.x_m)
    row = jnp.zeros((1,), jnp.int32)

    def loop(carry):
        s, reached, values = carry
        s, passage = body(s)
        reached, values = write(values, row, reached[None],
                                jax.tree_util.tree_map(lambda a: a[None, None], passage),
                                xs, zs, order, settings.g_m_s2, settings.station_slots)
        return s, reached[0], values

    final, reached, values = jax.lax.while_loop(
        lambda c: running(c[0]), loop, (state0, first, empty_values((1,) + xs.shape)))
    return result_from_state(final, state0.x_m, first, reached,
                             tuple(v[0] for v in values), order)


def result_from_state(final: State, release_x_m: jax.Array, first: jax.Array,
                      reached: jax.Array, values: tuple, order: jax.Array) -> Result:
    """The ``Result`` of a block whose loop has ended in state ``final``; a block
    still moving (event budget spent) gets status ``BUDGET``. ``first``,
    ``reached`` and ``values``: the station bookkeeping and the stored
    passages (``_stations.write``); ``order``: the argsort of the caller's
    stations (``sorted_stations``)."""
    return raw_result(final, release_x_m)._replace(stations=station_record(
        first, reached, values, order))


def raw_result(final: State, release_x_m: jax.Array) -> Result:
    """``result_from_state`` without the station record (``stations=None``): a
    batch that stores the passages itself builds the record once at the end."""
    moving = _moving(final.mode)
    return Result(
        runout_m=final.x_m - release_x_m,
        stop_x_m=final.x_m,
        stop_z_m=final.z_m,
        stopped=(final.mode == STOPPED) | (final.mode == STOPPED_BY_BARRIER),
        status=jnp.where(moving, BUDGET, final.mode).astype(jnp.int32),
        n_events=final.n_events,
        n_impacts=final.n_impacts,
        release_x_m=release_x_m,
        stations=None,
        barrier=None if final.barrier is None else barrier_record(final.barrier),
        breakup=final.breakup,
    )
