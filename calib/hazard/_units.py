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
DEM: one size per unit, ``jax.vmap`` of ``solvers.dem.simulate``. The 2D DEM
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
from solvers.crsp import Settings, simulate_tasks
from solvers.dem import simulate as dem_simulate

__all__ = ["crsp_chunk", "dem_chunk", "draw_key"]


def draw_key(seed: int, draw: int) -> jax.Array:
    """Key of draw ``draw`` of the run seeded ``seed``: fold_in(key(seed), draw)."""
    return jax.random.fold_in(jax.random.key(seed), draw)


@functools.partial(jax.jit, static_argnames=("n_chunk", "pool", "settings"))
def crsp_chunk(params, blocks, key, profile, stations_x_m, offset, n_valid, *, n_chunk: int,
               pool: int, settings: Settings = Settings()) -> ChunkStats:
    """Blocks ``offset .. offset + n_chunk - 1`` of every task, reduced.

    Args:
        params, blocks: CRSP ``Params`` / ``Block`` with a leading task axis T.
        key: the draw's key (block j uses fold_in(key, j)).
        profile: the slope.
        stations_x_m: (S,) stations, m.
        offset: index of the chunk's first block (traced: no recompilation).
        n_valid: blocks of the chunk that belong to the run (the rest pad the
            last chunk to the compiled size and are not counted).
        n_chunk, pool, settings: static sizes and solver settings.

    Returns:
        ``ChunkStats`` with T tasks.
    """
    res = simulate_tasks(params, blocks, key, profile, stations_x_m, n_per_task=n_chunk,
                         pool=pool, settings=settings, offset=offset)
    st = res.stations
    valid = jnp.arange(n_chunk) < n_valid
    return reduce_chunk(res.stop_x_m, res.status, st.passed, st.energy_kJ,
                        st.velocity_m_s, st.bounce_height_m, valid, stations_x_m)


@functools.partial(jax.jit, static_argnames=("n_chunk", "options"))
def dem_chunk(params, block, key, offset, n_valid, *, n_chunk: int, options) -> ChunkStats:
    """DEM blocks ``offset .. offset + n_chunk - 1`` of one size, reduced (T = 1).

    Args:
        params: DEM ``Params``.
        block: DEM ``Block`` (one un-fragmented square; stations inside).
        key: the draw's key (block j uses fold_in(key, j)).
        offset, n_valid: as for ``crsp_chunk``.
        n_chunk: static chunk size.
        options: static DEM ``Options``.

    Returns:
        ``ChunkStats`` with T = 1.
    """
    idx = (offset + jnp.arange(n_chunk)).astype(jnp.uint32)
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)
    res = jax.vmap(lambda k: dem_simulate(params, block, k, options))(keys)
    st = res.stations  # fields (n, 1, S): one fragment
    valid = jnp.arange(n_chunk) < n_valid
    energy_kJ = st.energy_kJ[None, :, 0] * block.size_m  # per metre -> per block (cube)
    return reduce_chunk(res.stop_x_m[None, :, 0], res.status[None], st.passed[None, :, 0],
                        energy_kJ, st.velocity_m_s[None, :, 0],
                        st.bounce_height_m[None, :, 0], valid, block.stations_x_m)
