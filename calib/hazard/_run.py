"""The Monte Carlo loop: posterior draws x block sizes (or volume classes) x blocks,
in chunks.

``run_hazard`` turns a ``Calibration`` and its ``Draws`` into a ``HazardCounts``:
per-draw counts at each station (so that posterior bands can be formed),
histograms pooled over draws (the posterior predictive distribution of energy,
velocity and bounce height of the blocks that reach a station), and per draw
the percentiles of those three with their Monte Carlo intervals and coarser
histograms of energy and height (what a barrier design reads: ``calib.design``).

What is simulated. Without release conditions (``release=None``): blocks of each
size, all released at one abscissa with the solver's default release state,
sizes sharing their random numbers (``_units.crsp_chunk``). With a
``calib.model.release.Seeder``: per class (a volume class of a block-volume law,
or a fixed size) ``n_blocks`` blocks per draw, each with its own volume drawn
within the class, its own release abscissa, height and speed
(``_units.seeded_chunk``: why each block is a task of its own is said there).
Stratified, equal allocation: a class's counts are conditional on the class,
and its weight (``VolumeClass.probability``) enters only the annual
frequencies. The DEM takes release conditions of fixed sizes (a zone, heights
and speeds; ``_units.dem_chunk``), not a volume distribution: each side is
compiled with its own step bound. A protection barrier (``Barrier``) is a CRSP
parameter of every draw (``solvers.crsp._barrier``); the DEM has none.
Fragmentation (``_fragments``) turns each unit into its fragment twin, with or
without release conditions.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from calib.files.calibration_file import Calibration, CalibrationError, Draws
from calib.hazard._sharding import run_units
from calib.hazard._stats import (
    BINS,
    DRAW_SUB,
    FINE,
    FINE_BINS,
    PERCENTILES,
    hist_quantile,
    percentile_table,
    rebin,
)
from calib.hazard._units import crsp_chunk, dem_chunk, draw_key, seeded_chunk
from calib.model.alpha_law import alpha_of, check_law
from calib.model.dem_run import DEM_RUN, DemRun
from calib.model.effects import draw_overrides
from calib.model.entries import Entries, dem_side_m
from calib.model.forward import stack_trees
from calib.model.release import Seeder
from solvers import crsp, dem
from solvers.profile import Profile

# The hazard run's CRSP settings: at most 5000 flight and contact events per block
# (a block still moving then is counted unfinished, ``_stats``), the default of
# ``run_hazard`` and of the command's ``--max-events``, so that a run from the
# library and one from the command simulate the same program.
HAZARD_SETTINGS = crsp.Settings(max_events=5000)

__all__ = ["HAZARD_SETTINGS", "Barrier", "HazardCounts", "check_dem_draws",
           "default_release_x_m", "dem_alpha", "run_hazard"]


@dataclasses.dataclass(frozen=True)
class Barrier:
    """A protection barrier of a CRSP hazard run (``solvers.crsp._barrier``: a block
    whose lowest point passes below H is stopped where its energy is at most the
    capacity, else breaks through keeping E - E_cap; over H it flies over).

    Attributes:
        x_m: its abscissa, m.
        height_m: H, m (+inf: unlimited).
        capacity_kJ: E_cap, kJ (+inf: unlimited).
    """

    x_m: float
    height_m: float = float("inf")
    capacity_kJ: float = float("inf")

    def overrides(self) -> dict:
        """The ``solvers.crsp.Params`` fields it sets."""
        return {"barrier_x_m": self.x_m, "barrier_height_m": self.height_m,
                "barrier_capacity_kJ": self.capacity_kJ}


@dataclasses.dataclass
class HazardCounts:
    """Everything the tables need (NumPy arrays; D draws, T sizes, S stations).

    Attributes:
        model: "crsp" or "dem".
        sizes_m: (T,) block sizes (average diameter), m.
        stations_x_m: (S,) stations, m.
        release_x_m: release abscissa, m (stations at or above it are not
            "reached": blocks start there).
        n_blocks: blocks per draw and size.
        draws: the ``Draws``.
        exceed, reach, e30, e300: (D, T, S) counts per draw.
        n_unfinished: (D, T) blocks that did not finish (still moving at the
            budget, or invalid: ``solvers.status``).
        n_left_profile: (D, T) blocks that left the profile.
        hist: quantity -> (T, S, B) counts pooled over draws (``_stats.BINS``).
        energy_p95_per_draw_kJ: (D, T, S) E p95 of each draw's passers, read from
            its ``BINS`` histogram (the hazard table's band).
        percentiles: quantity -> (value, lo, hi), each (D, T, S, P): each draw's
            ``_stats.PERCENTILES`` of its passers and their 95 % intervals, read
            from ``FINE_BINS`` (``_stats.percentile_table``).
        pooled_percentiles: quantity -> (value, lo, hi), each (T, S, P): the same
            for the passers of all draws pooled.
        draw_hist: "energy_kJ" and "bounce_height_m" -> (D, T, S, B) per-draw counts
            in ``_stats.DRAW_BINS``.
        block_mass_kg: (T,) mass of the simulated block of each size, kg (the DEM:
            the cube of side D whose energy the tables report; a volume class: the
            sphere of its representative volume).
        release: the release conditions (``calib.model.release.Seeder``), or None
            (every block at ``release_x_m``, the solver's release state).
        barrier: the protection barrier, or None.
        fragments: a fragment run's per-fragment counts
            (``_fragments.FragmentCounts``; the other fields are then per parent
            block), or None.
        crsp_settings: the CRSP settings the run simulated with (None for the
            DEM): a later run that must simulate the same blocks (``calib.design``'s
            impact angles, a run with a barrier) uses the same event budget.
        shapes: (T,) the CRSP shape class of each size's (class's) blocks
            (``solvers.crsp.SHAPES``), or None: spheres (and every DEM run).
    """

    model: str
    sizes_m: np.ndarray
    stations_x_m: np.ndarray
    release_x_m: float
    n_blocks: int
    draws: Draws
    exceed: np.ndarray
    reach: np.ndarray
    e30: np.ndarray
    e300: np.ndarray
    n_unfinished: np.ndarray
    n_left_profile: np.ndarray
    hist: dict
    energy_p95_per_draw_kJ: np.ndarray
    percentiles: dict = dataclasses.field(default_factory=dict)
    pooled_percentiles: dict = dataclasses.field(default_factory=dict)
    draw_hist: dict = dataclasses.field(default_factory=dict)
    block_mass_kg: np.ndarray | None = None
    release: Seeder | None = None
    barrier: Barrier | None = None
    fragments: object = None
    crsp_settings: crsp.Settings | None = None
    shapes: tuple[str, ...] | None = None


def dem_alpha(cal: Calibration, values: np.ndarray, size_m: float) -> float:
    """Local damping of the DEM square of a block of size ``size_m`` (average
    diameter, m) for one draw: the calibration's law, clipped, exactly as the
    fit ran it (``calib.model.alpha_law.alpha_of`` at L = ``dem_side_m(size_m)``)."""
    side = dem_side_m(np.atleast_1d(size_m))
    return float(alpha_of(cal.alpha_form, np.asarray(values, np.float64), side)[0])


def check_dem_draws(cal: Calibration, draws: Draws, sizes_m) -> None:
    """The hazard run's acceptance check of DEM draws (``calib.model.alpha_law.check_law``,
    the check the fit applies before it writes a calibration).

    Raises:
        CalibrationError: naming the posterior CSV line (or the map) of the first
            draw that is refused.
    """
    bad = check_law(cal.alpha_form, draws.values, dem_side_m(sizes_m))
    if bad is not None:
        i, why = bad
        row = int(draws.rows[i])
        where = (f"{cal.posterior_csv}: line {row + 1}" if row > 0
                 else f"{cal.path}: dem.alpha_law (map)")
        raise CalibrationError(f"{where}: {why}")


def default_release_x_m(cal: Calibration, profile: Profile) -> float:
    """Where a hazard run releases its blocks when not told: the calibration's
    ``release_x_m`` (the median release of the rows it fitted), else the
    profile's first vertex (older files, data without release points)."""
    return float(profile.x_m[0] if cal.release_x_m is None else cal.release_x_m)


def _chunks(n_blocks: int, max_chunk: int) -> tuple[int, list[int]]:
    """Equal chunk size and the chunk offsets covering ``n_blocks``."""
    n_chunks = -(-n_blocks // max_chunk)
    size = -(-n_blocks // n_chunks)
    return size, [i * size for i in range(n_chunks)]


def run_hazard(cal: Calibration, draws: Draws, profile: Profile, sizes_m, stations_x_m,
               n_blocks: int, seed: int, *, chunk_blocks: int = 16384, pool: int | None = None,
               settings: crsp.Settings = HAZARD_SETTINGS, dem_run: DemRun = DEM_RUN,
               release_x_m: float | None = None, release: Seeder | None = None,
               barrier: Barrier | None = None,
               progress: Callable[[int], None] | None = None, devices=None,
               fragments=None, shapes: tuple[str, ...] | None = None) -> HazardCounts:
    """Simulate ``n_blocks`` blocks per draw and size (or class); reduce at the stations.

    Args:
        cal: the calibration (model and parameter names).
        draws: parameter sets (``draw_parameters``).
        profile: the slope (materials from its materials file; the calibrated
            CRSP parameters override Kn, Kt, roughness in every zone).
        sizes_m: (T,) block sizes (average diameter), m: CRSP sphere radius
            D/2, DEM square side D.
        stations_x_m: (S,) stations, m.
        n_blocks: blocks per draw and size.
        seed: random seed (see ``_units`` for the key of each block).
        chunk_blocks: most blocks per size in one work unit (memory bound).
        pool: CRSP lanes per unit (None: ``solvers.crsp.default_pool()``).
        settings: CRSP settings (``HAZARD_SETTINGS``: the command's defaults).
        dem_run: DEM numerics (``calib.model.dem_run``; default: the fit's).
        release_x_m: release abscissa of every block, m (None:
            ``default_release_x_m``); with ``release``: the zone's downslope end.
        release: release conditions drawn per block (the DEM: fixed sizes
            only, ``Seeder.fixed_sizes``); its classes replace ``sizes_m``
            (pass None).
        barrier: a protection barrier (CRSP only), or None.
        progress: called with the number of blocks finished after each unit.
        devices: JAX devices (default all).
        fragments: a ``_fragment_options.Fragmentation``: every block broken and every
            fragment run as its own block (None: unbroken blocks).
        shapes: (T,) the CRSP shape class of each size's blocks
            (a size is the diameter of the sphere of the block's volume, radius s d
            / 2: ``calib.model.entries``), or None: spheres. With ``release``, its
            ``shapes`` (pass None).

    Returns:
        ``HazardCounts``.
    """
    if release is not None:
        shapes = release.shapes
    _check_options(cal, release, barrier, shapes)
    if release is not None:
        sizes_m = release.sizes_m
        if cal.model == "crsp":  # every block a CRSP task of its own
            chunk_blocks = min(chunk_blocks, _seeded_chunk_cap(profile))
    sizes_m = np.asarray(sizes_m, dtype=np.float64)
    stations = np.asarray(stations_x_m, dtype=np.float64)
    chunk, offsets = _chunks(n_blocks, chunk_blocks)
    release_x = (default_release_x_m(cal, profile) if release_x_m is None
                 else float(release_x_m))
    if release is not None:
        release_x = release.zone.span_m[1]
    tally = _Tally(len(draws.values), len(sizes_m), len(stations), n_blocks, progress)

    # what is simulated: each size at the release, in its shape, at the calibration's
    # rock density
    entries = Entries.at_sizes(sizes_m, release_x, density_kg_m3=cal.rock_density_kg_m3,
                               shapes=shapes)
    units = _work_units(cal, draws, profile, entries, release, barrier, sizes_m, stations,
                        n_blocks, seed, chunk, offsets, pool, settings, dem_run)
    on_result, frag = tally.on_result, None
    if fragments is not None:  # every fragment its own block (_fragments)
        units, on_result, frag = fragments.plan(units, on_result, cal, draws, sizes_m,
                                                stations, dem_run)
    run_units(units, on_result, devices=devices)
    fine = tally.fine
    pooled = {q: percentile_table(f, FINE_BINS[q]) for q, f in fine.items()}
    return HazardCounts(model=cal.model, sizes_m=sizes_m, stations_x_m=stations,
                        release_x_m=release_x, n_blocks=n_blocks, draws=draws,
                        n_unfinished=tally.n_unfinished, n_left_profile=tally.n_left_profile,
                        hist={q: rebin(f, FINE) for q, f in fine.items()},
                        energy_p95_per_draw_kJ=tally.e95,
                        percentiles={q: tuple(v) for q, v in tally.pct.items()},
                        pooled_percentiles=pooled, draw_hist=tally.kept,
                        block_mass_kg=_block_mass_kg(cal.model, entries),
                        release=release, barrier=barrier, fragments=frag,
                        crsp_settings=settings if cal.model == "crsp" else None,
                        shapes=None if shapes is None else tuple(entries.shapes), **tally.acc)


def _check_options(cal: Calibration, release, barrier, shapes) -> None:
    """Refuse the combinations ``run_hazard`` cannot run: a volume distribution, a
    barrier or a CRSP shape other than the sphere without the CRSP model (the DEM
    takes fixed sizes, each in a program of its own step bound, its blocks are
    squares, and it has no barrier element)."""
    if cal.model != "crsp" and (barrier is not None or (release is not None
                                                        and release.law is not None)
                                or any(f != "sphere" for f in shapes or ())):
        raise ValueError("volume distributions, barriers and block shapes need the CRSP "
                         "model")


def _work_units(cal, draws, profile, entries: Entries, release, barrier, sizes_m, stations,
                n_blocks, seed, chunk, offsets, pool, settings, dem_run):
    """The run's work units: seeded CRSP units with release conditions, else
    CRSP units of the sizes, else DEM units (after checking the DEM draws; with
    release conditions, each block's drawn in its unit);
    a barrier and the calibration's rolling threshold enter every CRSP draw as
    parameter overrides."""
    st_dev = jnp.asarray(stations)
    extra = {"rolling_threshold_m_s": cal.rolling_threshold_m_s,
             **({} if barrier is None else barrier.overrides())}
    if release is not None and cal.model == "crsp":
        return _seeded_units(draws, profile, release, entries.density_kg_m3, st_dev, n_blocks,
                             seed, chunk, offsets, pool, settings, extra, cal.effects)
    if cal.model == "crsp":
        return _crsp_units(draws, profile, entries, st_dev, n_blocks, seed, chunk, offsets,
                           pool, settings, extra, cal.effects)
    check_dem_draws(cal, draws, sizes_m)
    return _dem_units(cal, draws, profile, entries, stations, n_blocks, seed, chunk,
                      offsets, dem_run, release)


class _Tally:
    """What ``run_hazard`` adds up as the work units finish (``on_result``), in
    the arrays of ``HazardCounts``: per draw, size and station the counts
    (``acc``: exceed, reach, e30, e300), per draw and size the unfinished and
    left-profile blocks, per size the fine histograms pooled over draws
    (``fine``), and, once a draw's every block is in, its energy p95, percentiles
    and kept histograms (``_draw_done``)."""

    def __init__(self, n_draws: int, n_sizes: int, n_st: int, n_blocks: int,
                 progress: Callable[[int], None] | None):
        shape = (n_draws, n_sizes, n_st)
        self.n_sizes, self.n_blocks, self.progress = n_sizes, n_blocks, progress
        self.acc = {k: np.zeros(shape, np.int64) for k in ("exceed", "reach", "e30", "e300")}
        self.n_unfinished = np.zeros((n_draws, n_sizes), np.int64)
        self.n_left_profile = np.zeros((n_draws, n_sizes), np.int64)
        self.fine = {q: np.zeros((n_sizes, n_st, b.n), np.int64) for q, b in FINE_BINS.items()}
        self.draw_hist = {}
        self.draw_left = {}
        self.e95 = np.full(shape, np.nan)
        self.pct = {q: np.full((3,) + shape + (len(PERCENTILES),), np.nan) for q in FINE_BINS}
        self.kept = {q: np.zeros(shape + ((b.n - 2) // DRAW_SUB + 2,), np.int32)
                     for q, b in FINE_BINS.items() if q != "velocity_m_s"}

    def on_result(self, tag, out) -> None:
        """Add one unit's reduced output ``out`` for draw ``d`` and sizes ``t_sl``
        (``tag``); reduce the draw when its last unit is in; report progress."""
        d, t_sl = tag
        acc, fine = self.acc, self.fine
        for k in acc:
            acc[k][d, t_sl] += getattr(out, k)
        self.n_unfinished[d, t_sl] += out.n_unfinished
        self.n_left_profile[d, t_sl] += out.n_left_profile
        dh = self.draw_hist.setdefault(d, {q: np.zeros_like(f) for q, f in fine.items()})
        for q in fine:
            fine[q][t_sl] += getattr(out, f"hist_{q}")
            dh[q][t_sl] += getattr(out, f"hist_{q}")
        self.draw_left[d] = self.draw_left.get(d, self.n_sizes * self.n_blocks) - int(
            out.n_blocks) * (t_sl.stop - t_sl.start)
        if self.draw_left[d] == 0:
            _draw_done(d, self.draw_hist.pop(d), self.e95, self.pct, self.kept)
        if self.progress is not None:
            self.progress(int(out.n_blocks) * (t_sl.stop - t_sl.start))


def _draw_done(d: int, dh: dict, e95: np.ndarray, pct: dict, kept: dict) -> None:
    """Reduce the finished draw ``d``'s fine histograms (``dh``: quantity -> (T, S, B))
    into its rows of ``e95``, ``pct`` and ``kept`` (``HazardCounts``)."""
    e95[d] = hist_quantile(rebin(dh["energy_kJ"], FINE), 0.95, BINS["energy_kJ"])
    for q, counts in dh.items():
        for j, v in enumerate(percentile_table(counts, FINE_BINS[q])):
            pct[q][j, d] = v
        if q in kept:
            kept[q][d] = rebin(counts, DRAW_SUB)


def _block_mass_kg(model: str, entries: Entries) -> np.ndarray:
    """(T,) mass of the simulated block of each size, kg: the CRSP block of the
    entry's shape that ``_crsp_units`` simulates (``Entries.crsp_blocks``; over
    volume classes, the block of the class's representative volume); the DEM
    square's mass per metre times its side (the cube whose energy ``_units``
    reports)."""
    if model == "crsp":
        return np.array([float(b.mass_kg) for b in entries.crsp_blocks()])
    return float(entries.density_kg_m3) * np.asarray(entries.dem_side_m, np.float64) ** 3


def _crsp_units(draws, profile, entries: Entries, stations, n_blocks, seed, chunk, offsets,
                pool, settings, extra=None, effects=()):
    """Per draw, the chunks of ``_units.crsp_chunk`` for every size at once, each
    size's block its entry's (``Entries.crsp_blocks``: its shape); ``extra``: more
    solver parameters (a barrier's), ``effects``: the fitted model's effects
    (``Calibration.effects``)."""
    extra = {} if extra is None else extra
    n_sizes, release_x = entries.n, float(entries.release_x_m[0])
    blocks = stack_trees(entries.crsp_blocks())
    fn = functools.partial(crsp_chunk, n_chunk=chunk, pool=pool, settings=settings)
    for d, values in enumerate(draws.values):
        # the fitted model: the baseline's parameters and the effects' (Calibration.effects)
        p = crsp.params_from_profile(profile, release_x_m=release_x, **extra,
                                     **draw_overrides(effects, draws.names, values, profile))
        params = stack_trees([p] * n_sizes)
        key = draw_key(seed, d)
        for off in offsets:
            n_valid = min(chunk, n_blocks - off)

            def make_args(params=params, key=key, off=off, n_valid=n_valid):
                return (params, blocks, key, profile, stations, jnp.asarray(off, jnp.int32),
                        jnp.asarray(n_valid, jnp.int32))

            yield (d, slice(0, n_sizes)), make_args, fn


# memory of a seeded chunk's per-block segment constants (``_units.seeded_chunk``):
# about 16 float64 per segment and block; the chunk is kept under this many bytes
_SEEDED_TABLE_BYTES = 64 * 2**20


def _seeded_chunk_cap(profile: Profile) -> int:
    """Most blocks of a seeded chunk on ``profile``: its per-block segment tables
    under ``_SEEDED_TABLE_BYTES`` (Postignano, 4 segments: 65,536 blocks; Tschamut,
    179: 2,928), a multiple of 16 and at least 256."""
    n_seg = len(profile.x_m) - 1
    cap = _SEEDED_TABLE_BYTES // (16 * 8 * n_seg)
    return max(256, cap // 16 * 16)


def _seeded_units(draws, profile, release: Seeder, density, stations, n_blocks, seed, chunk,
                  offsets, pool, settings, extra, effects=()):
    """Per draw and class, the chunks of ``_units.seeded_chunk``."""
    pool = crsp.default_pool() if pool is None else pool
    fn = functools.partial(seeded_chunk, n_chunk=chunk, pool=min(pool, chunk),
                           kinds=release.kinds, settings=settings)
    seeds = [release.arrays(t) for t in range(len(release.classes))]
    rho = jnp.asarray(density, jnp.float64)
    for d, values in enumerate(draws.values):
        p = crsp.params_from_profile(profile, **extra,
                                     **draw_overrides(effects, draws.names, values, profile))
        key = draw_key(seed, d)
        for t, s in enumerate(seeds):
            for off in offsets:
                n_valid = min(chunk, n_blocks - off)

                def make_args(s=s, key=key, off=off, n_valid=n_valid, p=p):
                    return (p, s, rho, key, profile, stations, jnp.asarray(off, jnp.int32),
                            jnp.asarray(n_valid, jnp.int32))

                yield (d, slice(t, t + 1)), make_args, fn


def _dem_units(cal, draws, profile, entries: Entries, stations, n_blocks, seed, chunk,
               offsets, run: DemRun, seeder: Seeder | None = None):
    """DEM units, one size each; with ``seeder`` (fixed sizes) its zone, heights
    and speeds drawn per block (``_units.dem_chunk``)."""
    params = run.params(profile, rho=entries.density_kg_m3)
    sides, release = entries.dem_side_m, float(entries.release_x_m[0])
    # one static step bound for every size (one compilation; calib.model.dem_run)
    fn = functools.partial(dem_chunk, n_chunk=chunk, options=run.options(params, sides),
                           kinds=None if seeder is None else seeder.kinds)
    seeds = [None if seeder is None else seeder.arrays(t) for t in range(len(sides))]
    alphas = np.asarray(alpha_of(cal.alpha_form, draws.values, sides))  # (D, T)
    for d in range(len(draws.values)):
        key = draw_key(seed, d)
        for t, side in enumerate(sides):
            block = dem.make_block(float(side), alpha=float(alphas[d, t]),
                                   release_x_m=release, stations=stations)
            for off in offsets:
                n_valid = min(chunk, n_blocks - off)

                def make_args(block=block, key=key, off=off, n_valid=n_valid, s=seeds[t]):
                    return (params, block, key, jnp.asarray(off, jnp.int32),
                            jnp.asarray(n_valid, jnp.int32), s)

                yield (d, slice(t, t + 1)), make_args, fn
