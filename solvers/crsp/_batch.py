"""Batched CRSP runs: vmap over blocks, chunked to bound memory, keyed per block.

Block i of a run with key K always uses ``fold_in(K, i)``, so results do not
depend on the chunk size or on how many blocks run together.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from solvers.crsp._model import Block, Params, Result, Settings, simulate
from solvers.profile import Profile

__all__ = ["block_keys", "run_blocks", "simulate_batch"]


def block_keys(key: jax.Array, start: int, count: int) -> jax.Array:
    """Keys of blocks ``start .. start + count - 1`` of a run keyed by ``key``."""
    idx = jnp.arange(start, start + count, dtype=jnp.uint32)
    return jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)


@functools.partial(jax.jit, static_argnames=("settings",))
def simulate_batch(params: Params, block: Block, keys: jax.Array, profile: Profile,
                   stations_x_m: jax.Array, settings: Settings = Settings()) -> Result:
    """``simulate`` vmapped over ``keys`` (shape (N, ...)); jitted entry point."""
    fn = functools.partial(simulate, profile=profile, stations_x_m=stations_x_m,
                           settings=settings)
    return jax.vmap(fn, in_axes=(None, None, 0))(params, block, keys)


def run_blocks(
    params: Params,
    block: Block,
    key: jax.Array,
    n_blocks: int,
    profile: Profile,
    stations_x_m=None,
    settings: Settings = Settings(),
    chunk_size: int = 16384,
    progress=None,
) -> Result:
    """Simulate ``n_blocks`` blocks in chunks and return NumPy arrays.

    Args:
        params, block, profile, settings: as for ``simulate``.
        key: PRNG key of the run.
        n_blocks: number of blocks (> 0).
        stations_x_m: analysis abscissae, m, or None.
        chunk_size: blocks per compiled call (memory grows linearly with it).
        progress: optional callable ``progress(n_done)`` called after each chunk.

    Returns:
        ``Result`` whose leaves are NumPy arrays with leading dimension n_blocks.
    """
    if n_blocks <= 0:
        raise ValueError(f"n_blocks must be positive, got {n_blocks}")
    st = jnp.zeros((0,), jnp.float64) if stations_x_m is None else jnp.asarray(
        stations_x_m, jnp.float64)
    chunk = min(chunk_size, n_blocks)
    parts = []
    for start in range(0, n_blocks, chunk):
        count = min(chunk, n_blocks - start)
        keys = block_keys(key, start, chunk)  # padded: one compiled shape
        res = simulate_batch(params, block, keys, profile, st, settings)
        parts.append(jax.tree_util.tree_map(lambda a, c=count: np.asarray(a)[:c], res))
        if progress is not None:
            progress(count)
    return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=0), *parts)
