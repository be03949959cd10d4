"""What a CRSP run of ONE block is given: the block, its parameters, the settings.

``Block`` and ``make_block`` (the rock's shape classes, CRSP 4.0), ``Params``
and ``params_from_profile`` (restitution, roughness and rolling resistance per
zone, the release, the optional effects of ``_effects``, the protection barrier
of ``_barrier``) and the static ``Settings``. The model that uses them is
``solvers.crsp._model``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from solvers.material import ROCK_DENSITY_KG_M3
from solvers.profile import Profile

__all__ = ["ROLLING_THRESHOLD_M_S", "ROLLING_THRESHOLD_RANGE_M_S", "Block", "Params", "Settings",
           "make_block", "params_from_profile", "shape_constants", "SHAPES"]

# The default rolling threshold, m/s: a rebound (or a landing, or a release on the
# ground) whose normal speed relative to the mean segment is below it keeps the
# rock on the ground (``_model``), where it rolls against the rolling resistance;
# at the profile's vertices it also decides which kinks are impacts (``_vertex``).
# Our choice (a rebound of about 1.3 cm). It is a numerical cutoff that ends a
# Zeno sequence of ever smaller hops, and not converged everywhere: on the
# Tschamut east spot's profile at a parameter set fitted on the main line, the
# runouts of a slow release change by up to 79 m when it is halved and settle
# only from about 0.05 m/s down (docs/studies.md, "The rolling threshold";
# the strict xfail ``tests/test_crsp_invariants.py::
# test_runouts_do_not_depend_on_the_rolling_threshold_below_the_default``).
ROLLING_THRESHOLD_M_S = 0.5

# The rolling thresholds a site or a calibration file may state, m/s (closed
# interval). Our choice: the cutoff must stay positive, or nothing ends the
# sequence of ever smaller hops; 1e-4 m/s (a rebound of about half a micrometre)
# lies far below where runouts settle (about 0.05 m/s, above); at 10 m/s nearly
# every landing of a rockfall would already roll.
ROLLING_THRESHOLD_RANGE_M_S = (1e-4, 10.0)

_INERTIA_RATIO = {"sphere": 0.4, "cylinder": 0.5, "disc": 0.5}
# V = c pi r^3 of each shape at its default length (``make_block``): sphere 4/3,
# cylinder of length 2 r: 2, disc of thickness r / 2: 1/2
_VOLUME_FACTOR = {"sphere": 4.0 / 3.0, "cylinder": 2.0, "disc": 0.5}
SHAPES = tuple(_INERTIA_RATIO)


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
    density_kg_m3: float = ROCK_DENSITY_KG_M3,
    length_m: float | None = None,
) -> Block:
    """CRSP block of a given shape.

    Shapes (CRSP 4.0): sphere (I = 2/5 m r^2); cylinder rolling on its curved
    face, of axial length ``length_m`` (default 2 r), I = 1/2 m r^2; disc on its
    rim, thickness ``length_m`` (default r / 2), I = 1/2 m r^2. The density
    default is ``solvers.material.ROCK_DENSITY_KG_M3``, the paper's 2350 kg/m^3.

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


def shape_constants(shape: str) -> tuple[float, float]:
    """(s, k) of a CRSP shape class at its default length (``make_block``).

    s: the radius of the block of that shape with the volume of a sphere of
    radius 1, (4/3 / c)^(1/3), where V = c pi r^3 (sphere c = 4/3, cylinder of
    length 2 r c = 2, disc of thickness r / 2 c = 1/2): a block of volume V has
    radius s (3 V / (4 pi))^(1/3). k = I / (m r^2) about the rolling axis.

    Raises:
        ValueError: unknown shape.
    """
    if shape not in _VOLUME_FACTOR:
        raise ValueError(f"unknown block shape {shape!r}; expected one of {', '.join(SHAPES)}")
    return (4.0 / 3.0 / _VOLUME_FACTOR[shape]) ** (1.0 / 3.0), _INERTIA_RATIO[shape]


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
        release_height_m: height of the release point above the ground, m; may
            be negative (a tracked release below a raster's ground, see
            ``release_height_sd_m``).
        release_vx_m_s, release_vz_m_s: initial velocity, m/s.
        release_height_sd_m: sd of the release height's error, m: each block
            starts at a height drawn from N(release_height_m, sd^2) truncated
            to >= 0 (``_model.init``; 0: the point release, clipped to the
            ground).
        release_speed_sd_m_s: sd of the release speed's error, m/s: each block
            starts at a speed drawn from N(|v|, sd^2) truncated to >= 0, in the
            direction of (vx, vz) (0: the given velocity).
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
        barrier_x_m: abscissa of a protection barrier, m, or None: no barrier
            (+inf: none either, but the run carries the barrier's code). See
            ``_barrier``.
        barrier_height_m: its height H above the ground there, m (a block whose
            lowest point passes at H or higher flies over it); None with
            ``barrier_x_m``.
        barrier_capacity_kJ: the energy E_cap it absorbs, kJ (+inf: unlimited):
            a block hitting it with more breaks through keeping E - E_cap; None
            with ``barrier_x_m``.

    The barrier's three fields are None together or arrays together; tasks of
    one batch (``_batch``) share that structure (a batch of runs with and
    without a barrier gives the latter ``barrier_x_m = +inf``).
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
    release_height_sd_m: jax.Array
    release_speed_sd_m_s: jax.Array
    restitution_size_exponent: jax.Array
    frag_energy_kJ: jax.Array
    frag_radius_ratio: jax.Array
    frag_speed_ratio: jax.Array
    rolling_resistance: jax.Array
    belt_start_m: jax.Array
    belt_end_m: jax.Array
    belt_loss: jax.Array
    barrier_x_m: jax.Array | None
    barrier_height_m: jax.Array | None
    barrier_capacity_kJ: jax.Array | None


def params_from_profile(profile: Profile, **overrides) -> Params:
    """Parameters from the profile's material table, with optional overrides.

    Zone arrays (Kn, Kt, roughness_m, rolling_friction_deg) accept a scalar that
    applies to every zone. Defaults: rolling threshold ``ROLLING_THRESHOLD_M_S``
    (0.5 m/s; see its comment), release at the profile's first vertex, on the ground, with
    1 m/s horizontal velocity (the block is pushed over the crest), release
    height and speed known exactly (their sds 0). The optional
    effects of ``_effects`` are off (fragment size and speed ratios 0.5 and 0.7,
    assumptions, matter only once ``frag_energy_kJ`` is finite). There is no
    barrier (its fields None); given an abscissa only, the barrier is unlimited
    (height and capacity +inf: it stops every block that reaches it).

    Raises:
        TypeError: an unknown parameter name.
        ValueError: a barrier height or capacity that is negative or NaN, or
            given without the barrier's abscissa.
    """
    n_zones = len(profile.zone_names)
    values = dict(
        Kn=profile.Kn, Kt=profile.Kt, roughness_m=profile.roughness_m,
        rolling_friction_deg=profile.rolling_friction_deg,
        rolling_threshold_m_s=ROLLING_THRESHOLD_M_S, release_x_m=float(profile.x_m[0]),
        release_x_spread_m=0.0, release_height_m=0.0, release_vx_m_s=1.0,
        release_vz_m_s=0.0, restitution_size_exponent=0.0, frag_energy_kJ=float("inf"),
        release_height_sd_m=0.0, release_speed_sd_m_s=0.0,
        frag_radius_ratio=0.5, frag_speed_ratio=0.7, rolling_resistance=0.0,
        belt_start_m=0.0, belt_end_m=0.0, belt_loss=0.0, barrier_x_m=None,
        barrier_height_m=None, barrier_capacity_kJ=None,
    )
    unknown = set(overrides) - set(values)
    if unknown:
        raise TypeError(f"unknown CRSP parameter(s): {', '.join(sorted(unknown))}")
    values.update(overrides)
    _check_barrier(values)
    if values["barrier_x_m"] is not None:
        for name in ("barrier_height_m", "barrier_capacity_kJ"):
            values[name] = float("inf") if values[name] is None else values[name]
    zone_fields = ("Kn", "Kt", "roughness_m", "rolling_friction_deg")
    out = {}
    for name, v in values.items():
        if v is None:  # no barrier
            out[name] = None
            continue
        arr = jnp.asarray(v, dtype=jnp.float64)
        if name in zone_fields:
            arr = jnp.broadcast_to(arr, (n_zones,))
        out[name] = arr
    return Params(**out)


def _check_barrier(values: dict) -> None:
    """Refuse a negative or NaN barrier height or capacity, a NaN abscissa, and
    a height or capacity without an abscissa (traced values are not checked)."""
    if values["barrier_x_m"] is None:
        given = [n for n in ("barrier_height_m", "barrier_capacity_kJ") if values[n] is not None]
        if given:
            raise ValueError(f"{', '.join(given)} given without barrier_x_m (the barrier's "
                             "abscissa)")
        return
    for name in ("barrier_x_m", "barrier_height_m", "barrier_capacity_kJ"):
        if values[name] is None or isinstance(values[name], jax.core.Tracer):
            continue
        v = np.asarray(values[name], dtype=float)
        if np.any(np.isnan(v)) or (name != "barrier_x_m" and np.any(v < 0.0)):
            raise ValueError(f"{name} must be a number"
                             f"{'' if name == 'barrier_x_m' else ' >= 0'}, got {values[name]}")


@dataclasses.dataclass(frozen=True)
class Settings:
    """Static solver settings (hashable; changing them recompiles).

    Attributes:
        g_m_s2: gravitational acceleration, m/s^2.
        max_events: a fixed bound on flight + contact events per block, or None
            (default) for the per-block budget of ``event_budget``.
        window: segments tested per flight event (local search).
        station_slots: station passages evaluated per lane in one pass of
            ``_stations.write`` (the pooled loop evaluates ``station_slots x
            lanes`` at a time after every few events; ``simulate``, this many
            after every event); more passages take further passes. Speed only:
            results do not depend on it.
        split_at_break: a block that breaks (``_effects``) ends its run at the
            break (status BUDGET, ``Result.breakup`` says it broke) so that the
            caller can run every fragment on (``_break``); False (default): the
            model follows one fragment.
    """

    g_m_s2: float = 9.81
    max_events: int | None = None
    window: int = 4
    station_slots: int = 4
    split_at_break: bool = False
