"""Work units of a hazard run: one chunk of blocks, simulated and reduced in one
jitted call, so that only integer summaries (``_stats.ChunkStats``) leave the
device and memory stays bounded by the chunk size.

Random numbers. Draw d of a run with seed s uses the key K_d = fold_in(key(s), d);
block j (0-based within the draw) uses fold_in(K_d, j) in every size: sizes
share their random numbers within a draw (common random numbers: differences
between sizes come from the size, not from the draws), draws are independent.
A block's key does not depend on the chunk it runs in or on the device, so the
tables do not depend on chunking or on the number of devices.

Both solvers report a block's end as a ``solvers.status`` code; ``_stats``
reads it (finished, left the profile, unfinished).

CRSP: all sizes of a draw run as tasks of one lane pool
(``solvers.crsp.simulate_tasks``, with the chunk's block offset).
CRSP with release conditions drawn per block (``seeded_chunk``,
``calib.model.release``): one class (a volume class, or a fixed size) per unit,
every block its own task of one block keyed as above, so that each block has its
own volume, sphere, release abscissa, height and speed.
DEM: one size per unit, ``jax.vmap`` of ``solvers.dem.simulate``; with release
conditions (a fixed size's zone, height and speed) each block's drawn as for
CRSP (``dem_chunk``). The 2D DEM
gives kinetic energy per metre of thickness; it is multiplied by the square's
side L, i.e. the block is taken as a prism of thickness L (a cube of side D for
a block of average diameter D). This makes the energies kJ per block, as the
CRSP's and as the intensity classes need. It is an assumption of this module
(the paper's 2D runs have no thickness); a cube is about twice as heavy as the
CRSP sphere of the same diameter.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from calib.hazard._stats import ChunkStats, reduce_chunk
from calib.model.release import SeedArrays, sample_release
from solvers.crsp import Block, Settings, block_keys, simulate_tasks, task_slots
from solvers.dem import simulate as dem_simulate

__all__ = ["crsp_chunk", "dem_chunk", "draw_key", "seeded_chunk", "seeded_dem_block",
           "seeded_tasks"]


def draw_key(seed: int, draw: int) -> jax.Array:
    """Key of draw ``draw`` of the run seeded ``seed``: fold_in(key(seed), draw)."""
    return jax.random.fold_in(jax.random.key(seed), draw)


def crsp_chunk(params, blocks, key, profile, stations_x_m, offset, n_valid, *, n_chunk: int,
               pool: int | None, settings: Settings = Settings()) -> ChunkStats:
    """Blocks ``offset .. offset + n_valid - 1`` of every task, reduced.

    Compiled once per ``solvers.crsp.task_slots(n_chunk)`` (``_slotted_chunk``):
    runs whose chunk sizes share a slot count share one program, and only the
    chunk's ``n_valid`` blocks are simulated (a block's result does not depend
    on how many run with it: ``solvers.crsp.simulate_tasks``).

    Args:
        params, blocks: CRSP ``Params`` / ``Block`` with a leading task axis T.
        key: the draw's key (block j uses fold_in(key, j)).
        profile: the slope.
        stations_x_m: (S,) stations, m.
        offset: index of the chunk's first block (traced: no recompilation).
        n_valid: blocks of the chunk that belong to the run (at most ``n_chunk``;
            traced).
        n_chunk, pool, settings: the run's chunk size, the solver's lanes (None:
            ``solvers.crsp.default_pool()``) and its settings (static).

    Returns:
        ``ChunkStats`` with T tasks.
    """
    return _slotted_chunk(params, blocks, key, profile, stations_x_m, offset, n_valid,
                          n_slots=task_slots(n_chunk), pool=pool, settings=settings)


@functools.partial(jax.jit, static_argnames=("n_slots", "pool", "settings"))
def _slotted_chunk(params, blocks, key, profile, stations_x_m, offset, n_valid, *,
                   n_slots: int, pool: int | None, settings: Settings) -> ChunkStats:
    """``crsp_chunk`` compiled for ``n_slots`` rows per task."""
    res = simulate_tasks(params, blocks, key, profile, stations_x_m, n_per_task=n_valid,
                         pool=pool, settings=settings, offset=offset, n_slots=n_slots)
    st = res.stations
    valid = jnp.arange(n_slots) < n_valid
    return reduce_chunk(res.stop_x_m, res.status, st.passed, st.energy_kJ,
                        st.velocity_m_s, st.bounce_height_m, valid, stations_x_m)


@functools.partial(jax.jit, static_argnames=("n_chunk", "options", "kinds"))
def dem_chunk(params, block, key, offset, n_valid, seeds: SeedArrays | None = None, *,
              n_chunk: int, options, kinds: tuple[str, str] | None = None) -> ChunkStats:
    """DEM blocks ``offset .. offset + n_chunk - 1`` of one size, reduced (T = 1).

    With ``seeds`` each block's release abscissa, height and speed are drawn from
    its key by ``calib.model.release.sample_release`` (the CRSP run's draws, the
    same numbers for block j) and replace the block's; the DEM draws its
    orientation, offset and (a NaN speed) speed as without them
    (``solvers.dem``'s release). Drawn here, the height and speed reach the
    DEM as exact values (sds 0): a program without ``Options.release_errors``
    runs them. With the zone a point and the state the solver's default (NaN),
    every block is the block of the run without ``seeds``, to the bit.

    Args:
        params: DEM ``Params``.
        block: DEM ``Block`` (one un-fragmented square; stations inside).
        key: the draw's key (block j uses fold_in(key, j)).
        offset, n_valid: as for ``crsp_chunk``.
        seeds: the size's ``SeedArrays`` (a fixed size), or None: every block
            at ``block``'s release.
        n_chunk: static chunk size.
        options: static DEM ``Options``.
        kinds: with ``seeds``, (law kind, zone kind), static (``Seeder.kinds``).

    Returns:
        ``ChunkStats`` with T = 1.
    """
    keys = block_keys(key, offset, n_chunk)
    res = jax.vmap(lambda k: dem_simulate(params, seeded_dem_block(block, seeds, kinds, k),
                                          k, options))(keys)
    st = res.stations  # fields (n, 1, S): one fragment
    valid = jnp.arange(n_chunk) < n_valid
    energy_kJ = st.energy_kJ[None, :, 0] * block.size_m  # per metre -> per block (cube)
    return reduce_chunk(res.stop_x_m[None, :, 0], res.status[None], st.passed[None, :, 0],
                        energy_kJ, st.velocity_m_s[None, :, 0],
                        st.bounce_height_m[None, :, 0], valid, block.stations_x_m)


def seeded_dem_block(block, seeds: SeedArrays | None, kinds, key):
    """ONE DEM block (``solvers.dem.Block``, whole or in bonded fragments) released
    as ``seeds`` draw it from ``key`` (``calib.model.release.sample_release``: its
    abscissa, height and speed replace the block's, as exact values), or
    ``block`` itself where ``seeds`` is None."""
    if seeds is None:
        return block
    _, _, x, h, v = sample_release(seeds, kinds, key)
    return block._replace(release_x_m=x, release_height_m=h, release_speed_m_s=v)


@functools.partial(jax.jit, static_argnames=("n_chunk", "pool", "settings", "kinds"))
def seeded_chunk(params, seeds: SeedArrays, density_kg_m3, key, profile, stations_x_m, offset,
                 n_valid, *, n_chunk: int, pool: int, kinds: tuple[str, str],
                 settings: Settings = Settings()) -> ChunkStats:
    """Blocks ``offset .. offset + n_chunk - 1`` of one class, each drawn by
    ``calib.model.release.sample_release`` from its key, reduced (T = 1).

    Why one task per block. A CRSP task runs its blocks with one ``Params`` and ONE
    ``Block``, and its per-segment constants (roughness angle arctan(S / r), the
    rolling loss per metre) depend on the radius; blocks of different volumes
    therefore need tasks of their own. Groups of blocks sharing a drawn volume
    would make the blocks of a class dependent (a percentile's Monte Carlo
    interval, ``_stats``, assumes independent blocks), so every block is a task,
    keyed as block ``offset + t`` of the draw (``simulate_tasks``' ``task_offsets``):
    the solver's pool still schedules the lanes, and the segment constants are
    computed once per block (the memory of a chunk grows with the profile's
    segments: ``calib.hazard._run`` bounds it).

    Args:
        params: the draw's CRSP ``Params`` (one set; the release fields are
            replaced block by block).
        seeds: the class's ``SeedArrays``.
        density_kg_m3: rho: a block of volume V weighs rho V.
        key: the draw's key (block j uses fold_in(key, j)).
        profile, stations_x_m, offset, n_valid: as for ``crsp_chunk``.
        n_chunk, pool, settings: static sizes and solver settings.
        kinds: (law kind, zone kind), static (``Seeder.kinds``).

    Returns:
        ``ChunkStats`` with T = 1.
    """
    tasks, blocks = seeded_tasks(params, seeds, density_kg_m3, key, offset, n_chunk=n_chunk,
                                 kinds=kinds)
    res = simulate_tasks(tasks, blocks, key, profile, stations_x_m, n_per_task=1, pool=pool,
                         settings=settings, offset=offset,
                         task_offsets=jnp.arange(n_chunk, dtype=jnp.int32))
    st = res.stations  # fields (n_chunk, 1, S)
    valid = jnp.arange(n_chunk) < n_valid
    return reduce_chunk(res.stop_x_m[None, :, 0], res.status[None, :, 0],
                        st.passed[None, :, 0], st.energy_kJ[None, :, 0],
                        st.velocity_m_s[None, :, 0], st.bounce_height_m[None, :, 0], valid,
                        stations_x_m)



def seeded_tasks(params, seeds: SeedArrays, density_kg_m3, key, offset, *, n_chunk: int,
                 kinds: tuple[str, str]):
    """Blocks ``offset .. offset + n_chunk - 1`` of one class as CRSP tasks of one
    block each (``seeded_chunk``; traced, not jitted).

    Block j draws its volume V, diameter d, release abscissa, height and speed from
    fold_in(key, offset + j) (``calib.model.release.sample_release``); its task is
    ``params`` with that release (a NaN height or speed keeps ``params``' own, the
    solver's release state; no abscissa spread) and its block the class's CRSP
    shape (``SeedArrays.shape``) of mass rho V and radius s d / 2, d the diameter of
    the sphere of volume V (a fixed size, or a volume drawn from a law) and s the
    shape's radius scale (a sphere's s is 1: ``calib.model.entries``).

    Returns:
        (tasks, blocks): CRSP ``Params`` and ``Block`` with a leading axis
        ``n_chunk``, for ``solvers.crsp.simulate_tasks`` with ``n_per_task=1`` and
        ``task_offsets=arange(n_chunk)``.
    """
    keys = block_keys(key, offset, n_chunk)
    volume, diameter, x, h, v = jax.vmap(lambda k: sample_release(seeds, kinds, k))(keys)
    tasks = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n_chunk,) + a.shape), params)
    tasks = tasks._replace(
        release_x_m=x, release_x_spread_m=jnp.zeros(n_chunk),
        release_height_m=jnp.where(jnp.isnan(h), params.release_height_m, h),
        release_vx_m_s=jnp.where(jnp.isnan(v), params.release_vx_m_s, v))
    scale, inertia_ratio = seeds.shape[0], seeds.shape[1]
    radius = 0.5 * diameter * scale
    blocks = Block(radius_m=radius, mass_kg=density_kg_m3 * volume,
                   inertia_ratio=jnp.broadcast_to(inertia_ratio, (n_chunk,)))
    return tasks, blocks
