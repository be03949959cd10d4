"""CRSP rockfall model for ONE block: parameters, state, events, simulate.

The rock is a lumped mass with a radius (for roughness and rotational inertia)
moving along a 2D height-field profile. Its history is a sequence of events,
each solved in closed form:

* FLIGHT: exact parabola to the next impact (``_flight.next_impact``), then the
  CRSP impact law on a roughness-tilted facet (``_impact.crsp_impact``). If the
  rebound's normal speed relative to the mean segment is below
  ``rolling_threshold_m_s`` the rock stays on the ground (CONTACT).
* CONTACT: rolling/sliding with Coulomb resistance along the segment to its end,
  to rest, or to the next roughness asperity one radius further (where a CRSP
  impact on a new random facet follows, as a pending impact) (``_contact``);
  launch into flight at convex breaks.
* STOPPED: at rest where rest is possible (``tan|beta| <= mu``).
* LEFT_PROFILE: passed either end of the profile (not a stop).

The loop is a ``lax.while_loop`` bounded by ``Settings.max_events``: event-
driven motion has no fixed step count, and a vmapped while_loop stops when the
slowest lane of the batch is done. A block still moving at the bound is flagged
(status ``MAX_EVENTS``), never counted as stopped. This forward model is not
reverse-differentiated (calibration uses common-random-number objectives; see
``calib``).

Randomness: ``key`` is split into a release key (release jitter) and an event
key; the i-th event draws its roughness from a counter-based hash of the event
key's words and i (``solvers._rng``; threefry per event dominated run time). A block's
history depends only on its own key, whatever the batch it runs in.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from solvers._rng import key_words, uniform_from_counter
from solvers.crsp._contact import contact_move
from solvers.crsp._effects import breaks, in_belt, size_scaled
from solvers.crsp._flight import next_impact
from solvers.crsp._impact import crsp_impact, roughness_tilt
from solvers.profile import Profile, ground_z, segment_index
from solvers.stations import StationRecord, empty_record, record_passage

__all__ = [
    "CONTACT",
    "FLIGHT",
    "LEFT_PROFILE",
    "MAX_EVENTS",
    "STOPPED",
    "Block",
    "Params",
    "Result",
    "Settings",
    "State",
    "make_block",
    "params_from_profile",
    "result_from_state",
    "simulate",
]

# modes (State.mode) and final status (Result.status)
FLIGHT, CONTACT, STOPPED, LEFT_PROFILE = 0, 1, 2, 3
MAX_EVENTS = 4  # status only: still moving when the event budget ran out

_INERTIA_RATIO = {"sphere": 0.4, "cylinder": 0.5, "disc": 0.5}


class Block(NamedTuple):
    """A rock (pytree of scalars, vmappable).

    Attributes:
        radius_m: radius r, m.
        mass_kg: mass m, kg.
        inertia_ratio: k = I / (m r^2) about the rolling axis.
    """

    radius_m: jax.Array
    mass_kg: jax.Array
    inertia_ratio: jax.Array


def make_block(
    radius_m: float,
    shape: str = "sphere",
    density_kg_m3: float = 2350.0,
    length_m: float | None = None,
) -> Block:
    """CRSP block of a given shape.

    Shapes (CRSP 4.0): sphere (I = 2/5 m r^2); cylinder rolling on its curved
    face, of axial length ``length_m`` (default 2 r), I = 1/2 m r^2; disc on its
    rim, thickness ``length_m`` (default r / 2), I = 1/2 m r^2. The density
    default is the paper's rho = 2350 kg/m^3 (Sect. 4.1).

    Raises:
        ValueError: unknown shape or non-positive sizes.
    """
    if shape not in _INERTIA_RATIO:
        raise ValueError(f"unknown block shape {shape!r}; expected one of "
                         f"{', '.join(_INERTIA_RATIO)}")
    if not (radius_m > 0 and np.isfinite(radius_m)):
        raise ValueError(f"block radius must be a positive number of metres, got {radius_m}")
    if not (density_kg_m3 > 0 and np.isfinite(density_kg_m3)):
        raise ValueError(f"density must be positive, got {density_kg_m3}")
    if shape == "sphere":
        volume = 4.0 / 3.0 * np.pi * radius_m**3
    else:
        default = 2.0 * radius_m if shape == "cylinder" else 0.5 * radius_m
        length = default if length_m is None else length_m
        if not (length > 0 and np.isfinite(length)):
            raise ValueError(f"block length must be positive, got {length}")
        volume = np.pi * radius_m**2 * length
    return Block(jnp.asarray(float(radius_m)), jnp.asarray(float(volume * density_kg_m3)),
                 jnp.asarray(_INERTIA_RATIO[shape]))


class Params(NamedTuple):
    """CRSP parameters (a pytree; all leaves may be traced).

    Attributes:
        Kn, Kt: (Z,) restitution coefficients per zone.
        roughness_m: (Z,) slope roughness S per zone, m.
        rolling_friction_deg: (Z,) rolling-resistance angle per zone, degrees.
        rolling_threshold_m_s: rebound normal speed (w.r.t. the mean slope) below
            which the rock stays in ground contact, m/s.
        release_x_m: release abscissa, m.
        release_x_spread_m: release abscissa drawn uniformly in
            ``[release_x_m, release_x_m + spread]``, m.
        release_height_m: height of the release point above the ground, m.
        release_vx_m_s, release_vz_m_s: initial velocity, m/s.
        restitution_size_exponent: gamma of the size-dependent restitution
            ``K (2 r / 1 m)^gamma`` (0: off). See ``_effects``.
        frag_energy_kJ: normal impact energy above which the block breaks, kJ
            (inf: off).
        frag_radius_ratio: fragment radius / block radius.
        frag_speed_ratio: fragment speed / rebound speed at the break.
        rolling_resistance: extra rolling-resistance coefficient added to
            ``tan(phi_r)`` in every zone (0: off).
        belt_start_m, belt_end_m: abscissae of the vegetation belt, m.
        belt_loss: fraction of the rebound energy lost at an impact in the belt,
            and extra rolling resistance there (0: off).
    """

    Kn: jax.Array
    Kt: jax.Array
    roughness_m: jax.Array
    rolling_friction_deg: jax.Array
    rolling_threshold_m_s: jax.Array
    release_x_m: jax.Array
    release_x_spread_m: jax.Array
    release_height_m: jax.Array
    release_vx_m_s: jax.Array
    release_vz_m_s: jax.Array
    restitution_size_exponent: jax.Array
    frag_energy_kJ: jax.Array
    frag_radius_ratio: jax.Array
    frag_speed_ratio: jax.Array
    rolling_resistance: jax.Array
    belt_start_m: jax.Array
    belt_end_m: jax.Array
    belt_loss: jax.Array


def params_from_profile(profile: Profile, **overrides) -> Params:
    """Parameters from the profile's material table, with optional overrides.

    Zone arrays (Kn, Kt, roughness_m, rolling_friction_deg) accept a scalar that
    applies to every zone. Defaults: rolling threshold 0.5 m/s (a rebound of
    about 1.3 cm), release at the profile's first vertex, on the ground, with
    1 m/s horizontal velocity (the block is pushed over the crest). The optional
    effects of ``_effects`` are off (fragment size and speed ratios 0.5 and 0.7,
    assumptions, matter only once ``frag_energy_kJ`` is finite).
    """
    n_zones = len(profile.zone_names)
    values = dict(
        Kn=profile.Kn, Kt=profile.Kt, roughness_m=profile.roughness_m,
        rolling_friction_deg=profile.rolling_friction_deg,
        rolling_threshold_m_s=0.5, release_x_m=float(profile.x_m[0]),
        release_x_spread_m=0.0, release_height_m=0.0, release_vx_m_s=1.0,
        release_vz_m_s=0.0, restitution_size_exponent=0.0, frag_energy_kJ=float("inf"),
        frag_radius_ratio=0.5, frag_speed_ratio=0.7, rolling_resistance=0.0,
        belt_start_m=0.0, belt_end_m=0.0, belt_loss=0.0,
    )
    unknown = set(overrides) - set(values)
    if unknown:
        raise TypeError(f"unknown CRSP parameter(s): {', '.join(sorted(unknown))}")
    values.update(overrides)
    zone_fields = ("Kn", "Kt", "roughness_m", "rolling_friction_deg")
    out = {}
    for name, v in values.items():
        arr = jnp.asarray(v, dtype=jnp.float64)
        if name in zone_fields:
            arr = jnp.broadcast_to(arr, (n_zones,))
        out[name] = arr
    return Params(**out)


@dataclasses.dataclass(frozen=True)
class Settings:
    """Static solver settings (hashable; changing them recompiles).

    Attributes:
        g_m_s2: gravitational acceleration, m/s^2.
        max_events: bound on flight + contact events per block.
        window: segments tested per flight event (local search).
    """

    g_m_s2: float = 9.81
    max_events: int = 5000
    window: int = 4


class State(NamedTuple):
    """State of one block between events.

    Attributes:
        x_m, z_m: position of the lumped mass, m.
        vx_m_s, vz_m_s: velocity, m/s.
        spin_rad_s: rolling-positive spin, rad/s.
        seg: segment under the block.
        mode: FLIGHT, CONTACT, STOPPED or LEFT_PROFILE.
        n_events: events so far.
        n_impacts: impacts so far.
        pending: bool, the last rebound points into the mean slope: the next
            event is an immediate new impact (no flight).
        stations: first-passage records, fields of shape (n_stations,).
        radius_m: current radius (the fragment's after a break), m.
        fragmented: bool, the block has broken (``_effects``).
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
    stations: StationRecord
    radius_m: jax.Array
    fragmented: jax.Array


class Result(NamedTuple):
    """Outcome for one block.

    Attributes:
        runout_m: horizontal distance from the release point to the final
            position, m (for blocks not stopped: to where they were at the end).
        stop_x_m, stop_z_m: final position, m.
        stopped: bool, at rest where rest is possible.
        status: STOPPED, LEFT_PROFILE or MAX_EVENTS.
        n_events, n_impacts: counts.
        release_x_m: the release abscissa actually used, m.
        stations: ``StationRecord`` with fields of shape (n_stations,).
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


def _segment_geometry(profile: Profile, seg):
    xa, xb = profile.x_m[seg], profile.x_m[seg + 1]
    za, zb = profile.z_m[seg], profile.z_m[seg + 1]
    beta = jnp.arctan2(zb - za, xb - xa)
    return xa, xb, za, zb, beta


class SegmentTable(NamedTuple):
    """Per-segment constants, computed once per block outside the event loop
    (transcendentals inside the loop dominated its cost on CPU). Shapes (S,).
    The ``*_frag`` fields are those of a fragment (``_effects``)."""

    beta: jax.Array
    cos: jax.Array
    sin: jax.Array
    mu: jax.Array
    theta_max: jax.Array
    Kn: jax.Array
    Kt: jax.Array
    theta_max_frag: jax.Array
    Kn_frag: jax.Array
    Kt_frag: jax.Array
    mass_frag_kg: jax.Array
    belt_keep: jax.Array


def segment_table(profile: Profile, params: Params, block: Block) -> SegmentTable:
    """Angles, their cos/sin, rolling resistance ``tan(phi_r) + Delta-mu``, the
    roughness angle ``theta_max = arctan(S / R)`` (see ``_impact.roughness_tilt``)
    and the (size-scaled, ``_effects``) restitution per segment, for the block and
    for a fragment of it."""
    dx = jnp.diff(profile.x_m)
    dz = jnp.diff(profile.z_m)
    beta = jnp.arctan2(dz, dx)
    zone = profile.zone_id
    r_frag = block.radius_m * params.frag_radius_ratio
    gamma = params.restitution_size_exponent
    Kn, Kt = params.Kn[zone], params.Kt[zone]
    return SegmentTable(
        beta=beta, cos=jnp.cos(beta), sin=jnp.sin(beta),
        mu=jnp.tan(jnp.deg2rad(params.rolling_friction_deg[zone])) + params.rolling_resistance,
        theta_max=roughness_tilt(1.0, params.roughness_m[zone], block.radius_m),
        Kn=size_scaled(Kn, block.radius_m, gamma), Kt=size_scaled(Kt, block.radius_m, gamma),
        theta_max_frag=roughness_tilt(1.0, params.roughness_m[zone], r_frag),
        Kn_frag=size_scaled(Kn, r_frag, gamma), Kt_frag=size_scaled(Kt, r_frag, gamma),
        mass_frag_kg=block.mass_kg * params.frag_radius_ratio**3,
        belt_keep=jnp.sqrt(1.0 - params.belt_loss),
    )


def init(params: Params, block: Block, key: jax.Array, profile: Profile,
         n_stations: int) -> State:
    """Initial state at the release point (``key``: release key).

    The block starts in flight, or in ground contact when it is released on the
    ground (height 0) with a velocity that does not leave the slope (normal
    component below the rolling threshold)."""
    u = jax.random.uniform(key, dtype=jnp.float64)
    x0 = params.release_x_m + u * params.release_x_spread_m
    x0 = jnp.clip(x0, profile.x_m[0], profile.x_m[-1])
    z0 = ground_z(profile, x0) + params.release_height_m
    zero = jnp.zeros((), jnp.float64)
    seg = segment_index(profile, x0)
    *_, beta = _segment_geometry(profile, seg)
    vx0, vz0 = zero + params.release_vx_m_s, zero + params.release_vz_m_s
    # released on the ground without leaving it: start rolling along the segment
    on_ground = (params.release_height_m <= 0.0) & (
        -vx0 * jnp.sin(beta) + vz0 * jnp.cos(beta) < params.rolling_threshold_m_s)
    u0 = vx0 * jnp.cos(beta) + vz0 * jnp.sin(beta)
    return State(
        x_m=x0, z_m=z0, vx_m_s=jnp.where(on_ground, u0 * jnp.cos(beta), vx0),
        vz_m_s=jnp.where(on_ground, u0 * jnp.sin(beta), vz0), spin_rad_s=zero,
        seg=seg, mode=jnp.where(on_ground, CONTACT, FLIGHT).astype(jnp.int32),
        n_events=jnp.asarray(0, jnp.int32), n_impacts=jnp.asarray(0, jnp.int32),
        pending=jnp.asarray(False), stations=empty_record(n_stations),
        radius_m=zero + block.radius_m, fragmented=jnp.asarray(False),
    )


def _flight_event(state: State, params: Params, block: Block, key, profile: Profile,
                  table: SegmentTable, stations_x_m, stations_z_m,
                  settings: Settings) -> State:
    g = settings.g_m_s2
    x, z, vx, vz = state.x_m, state.z_m, state.vx_m_s, state.vz_m_s
    fh = next_impact(profile, state.seg, x, z, vx, vz, g, settings.window)
    # a rebound into the mean slope hits the rough surface again at once
    fh = fh._replace(t_s=jnp.where(state.pending, 0.0, fh.t_s),
                     hit=fh.hit | state.pending,
                     seg=jnp.where(state.pending, state.seg, fh.seg),
                     left_profile=fh.left_profile & ~state.pending)
    t = fh.t_s
    x1 = x + vx * t
    z1 = z + vz * t - 0.5 * g * t * t
    vz1 = vz - g * t

    # first passages during this flight
    r, k = state.radius_m, block.inertia_ratio
    m = jnp.where(state.fragmented, table.mass_frag_kg, block.mass_kg)
    safe_vx = jnp.where(vx > 0.0, vx, 1.0)
    ts = (stations_x_m - x) / safe_vx
    crossed = (vx > 0.0) & (stations_x_m > x) & (stations_x_m <= x1)
    vzs = vz - g * ts
    speed2 = vx * vx + vzs * vzs
    zs = z + vz * ts - 0.5 * g * ts * ts
    energy = 0.5 * m * (speed2 + k * (r * state.spin_rad_s) ** 2) / 1000.0
    rec = record_passage(state.stations, crossed, energy, jnp.sqrt(speed2), zs - stations_z_m)

    # impact on the hit segment (used only if fh.hit)
    seg = fh.seg
    xa, xb = profile.x_m[seg], profile.x_m[seg + 1]
    za, zb = profile.z_m[seg], profile.z_m[seg + 1]
    beta, cb, sb = table.beta[seg], table.cos[seg], table.sin[seg]
    frag = state.fragmented
    theta_max = jnp.where(frag, table.theta_max_frag[seg], table.theta_max[seg])
    tilt = uniform_from_counter(key, state.n_events) * theta_max
    imp = crsp_impact(vx, vz1, state.spin_rad_s, beta, tilt,
                      jnp.where(frag, table.Kn_frag[seg], table.Kn[seg]),
                      jnp.where(frag, table.Kt_frag[seg], table.Kt[seg]),
                      r, k, slope_cos=cb, slope_sin=sb)
    # optional effects (_effects): a break on a hard impact, a vegetation belt
    brk = fh.hit & breaks(m, vx * sb - vz1 * cb, params.frag_energy_kJ, frag)
    r_new = jnp.where(brk, r * params.frag_radius_ratio, r)
    f = jnp.where(in_belt(x1, params.belt_start_m, params.belt_end_m), table.belt_keep, 1.0)
    f_spin = f * jnp.where(brk, params.frag_speed_ratio / params.frag_radius_ratio, 1.0)
    f = f * jnp.where(brk, params.frag_speed_ratio, 1.0)
    imp = imp._replace(vx_m_s=f * imp.vx_m_s, vz_m_s=f * imp.vz_m_s,
                       spin_rad_s=f_spin * imp.spin_rad_s)
    vn_mean = -imp.vx_m_s * sb + imp.vz_m_s * cb
    roll = jnp.abs(vn_mean) < params.rolling_threshold_m_s
    into_slope = vn_mean <= -params.rolling_threshold_m_s
    u_t = imp.vx_m_s * cb + imp.vz_m_s * sb
    z_line = za + (zb - za) * (x1 - xa) / (xb - xa)

    hit = fh.hit
    mode = jnp.where(hit, jnp.where(roll, CONTACT, FLIGHT),
                     jnp.where(fh.left_profile, LEFT_PROFILE, FLIGHT)).astype(jnp.int32)
    return State(
        x_m=x1,
        z_m=jnp.where(hit, z_line, z1),
        vx_m_s=jnp.where(hit, jnp.where(roll, u_t * cb, imp.vx_m_s), vx),
        vz_m_s=jnp.where(hit, jnp.where(roll, u_t * sb, imp.vz_m_s), vz1),
        spin_rad_s=jnp.where(hit, jnp.where(roll, u_t / r_new, imp.spin_rad_s),
                             state.spin_rad_s),
        seg=seg,
        mode=mode,
        n_events=state.n_events + 1,
        n_impacts=state.n_impacts + hit.astype(jnp.int32),
        pending=hit & into_slope,
        stations=rec,
        radius_m=r_new,
        fragmented=frag | brk,
    )


def _contact_event(state: State, params: Params, block: Block, profile: Profile,
                   table: SegmentTable, stations_x_m, settings: Settings) -> State:
    g = settings.g_m_s2
    n_seg = profile.x_m.shape[0] - 1
    seg = state.seg
    xa, xb = profile.x_m[seg], profile.x_m[seg + 1]
    za, zb = profile.z_m[seg], profile.z_m[seg + 1]
    beta, cb, sb = table.beta[seg], table.cos[seg], table.sin[seg]
    x = state.x_m
    r = state.radius_m
    mu = table.mu[seg] + jnp.where(in_belt(x, params.belt_start_m, params.belt_end_m),
                                   params.belt_loss, 0.0)
    u = state.vx_m_s * cb + state.vz_m_s * sb
    rough = table.theta_max[seg] > 0.0
    mv = contact_move(u, cb, sb, mu, jnp.maximum((xb - x) / cb, 0.0),
                      jnp.maximum((x - xa) / cb, 0.0), block.inertia_ratio, g,
                      dist_kick_m=jnp.where(rough, r, jnp.inf))
    x1 = jnp.clip(x + mv.dist_m * cb, xa, xb)
    z1 = za + (zb - za) * (x1 - xa) / (xb - xa)

    # first passages while rolling downslope
    k = block.inertia_ratio
    m = jnp.where(state.fragmented, table.mass_frag_kg, block.mass_kg)
    crossed = (mv.direction > 0) & (stations_x_m > x) & (stations_x_m <= x1)
    d_s = (stations_x_m - x) / cb
    v2 = jnp.maximum(u * u + 2.0 * mv.accel_m_s2 * mv.direction * d_s, 0.0)
    energy = 0.5 * m * (1.0 + k) * v2 / 1000.0
    rec = record_passage(state.stations, crossed, energy, jnp.sqrt(v2), jnp.zeros_like(v2))

    # transition at the segment's end
    step = mv.direction.astype(jnp.int32)
    nxt = seg + step
    off_end = (nxt < 0) | (nxt >= n_seg)
    nxt_c = jnp.clip(nxt, 0, n_seg - 1)
    beta2, c2, s2 = table.beta[nxt_c], table.cos[nxt_c], table.sin[nxt_c]
    convex = jnp.where(step > 0, beta2 < beta, beta2 > beta)
    u_end = mv.u_end_m_s
    u2 = u_end * (c2 * cb + s2 * sb)  # u cos(beta2 - beta)

    at_end = mv.at_end
    mode = jnp.where(mv.stopped, STOPPED,
                     jnp.where(at_end & off_end, LEFT_PROFILE,
                               jnp.where((at_end & convex) | mv.kicked, FLIGHT,
                                         CONTACT))).astype(jnp.int32)
    switch = at_end & ~off_end
    vx_new = jnp.where(switch & ~convex, u2 * c2, u_end * cb)
    vz_new = jnp.where(switch & ~convex, u2 * s2, u_end * sb)
    speed_along = jnp.where(switch & ~convex, u2, u_end)
    stopped = mode == STOPPED
    return State(
        x_m=x1,
        z_m=z1,
        vx_m_s=jnp.where(stopped, 0.0, vx_new),
        vz_m_s=jnp.where(stopped, 0.0, vz_new),
        spin_rad_s=jnp.where(stopped, 0.0, speed_along / r),
        seg=jnp.where(switch, nxt_c, seg).astype(jnp.int32),
        mode=mode,
        n_events=state.n_events + 1,
        n_impacts=state.n_impacts,
        pending=mv.kicked,
        stations=rec,
        radius_m=r,
        fragmented=state.fragmented,
    )


def step(state: State, params: Params, block: Block, key: jax.Array, profile: Profile,
         table: SegmentTable, stations_x_m: jax.Array, stations_z_m: jax.Array,
         settings: Settings) -> State:
    """One event: a flight to the next impact, or a contact move (pure).

    ``key`` is the event key's two uint32 words (``solvers._rng.key_words``)."""
    fl = _flight_event(state, params, block, key, profile, table, stations_x_m, stations_z_m,
                       settings)
    co = _contact_event(state, params, block, profile, table, stations_x_m, settings)
    in_flight = state.mode == FLIGHT
    return jax.tree_util.tree_map(lambda a, b: jnp.where(in_flight, a, b), fl, co)


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
    if stations_x_m is None:
        stations_x_m = jnp.zeros((0,), jnp.float64)
    stations_x_m = jnp.asarray(stations_x_m, jnp.float64)
    stations_z_m = ground_z(profile, stations_x_m)
    release_key, event_key = jax.random.split(key)
    state0 = init(params, block, release_key, profile, stations_x_m.shape[0])

    def cond(s: State):
        return ((s.mode == FLIGHT) | (s.mode == CONTACT)) & (s.n_events < settings.max_events)

    body = functools.partial(step, params=params, block=block, key=key_words(event_key),
                             profile=profile, table=segment_table(profile, params, block),
                             stations_x_m=stations_x_m, stations_z_m=stations_z_m,
                             settings=settings)
    final = jax.lax.while_loop(cond, lambda s: body(s), state0)
    return result_from_state(final, state0.x_m)


def result_from_state(final: State, release_x_m: jax.Array) -> Result:
    """The ``Result`` of a block whose loop has ended in state ``final``; a block
    still moving (event budget spent) gets status ``MAX_EVENTS``."""
    moving = (final.mode == FLIGHT) | (final.mode == CONTACT)
    return Result(
        runout_m=final.x_m - release_x_m,
        stop_x_m=final.x_m,
        stop_z_m=final.z_m,
        stopped=final.mode == STOPPED,
        status=jnp.where(moving, MAX_EVENTS, final.mode).astype(jnp.int32),
        n_events=final.n_events,
        n_impacts=final.n_impacts,
        release_x_m=release_x_m,
        stations=final.stations,
    )
