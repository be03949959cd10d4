"""Cheap counter-based uniforms for per-event draws inside solver loops.

Calling ``jax.random`` (threefry, 20 rounds) once per event and per block
dominated the CRSP event loop on CPU (measured: ``python -m solvers.bench``).
Inside loops we instead hash the block's key words with the event counter using
MurmurHash3's 32-bit finaliser (Appleby, public domain), applied twice. The key
itself still comes from ``jax.random`` (explicit, splittable), so a block's draws
depend only on its own key and the event index, never on the batch.
Resolution is 2^-24, ample for sampling an impact angle.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["key_words", "uniform_from_counter"]


def _fmix32(x: jax.Array) -> jax.Array:
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x85EBCA6B)
    x = x ^ (x >> 13)
    x = x * jnp.uint32(0xC2B2AE35)
    return x ^ (x >> 16)


def key_words(key: jax.Array) -> jax.Array:
    """Two uint32 words derived from a JAX PRNG key (shape (2,))."""
    return jax.random.bits(key, (2,), dtype=jnp.uint32)


def uniform_from_counter(words: jax.Array, counter: jax.Array) -> jax.Array:
    """Uniform in [0, 1) from key words (2,) and an integer counter (float64)."""
    c = counter.astype(jnp.uint32)
    x = _fmix32(c * jnp.uint32(0x9E3779B9) + words[0])
    x = _fmix32(x ^ words[1])
    return (x >> 8).astype(jnp.float64) * (1.0 / 16777216.0)
