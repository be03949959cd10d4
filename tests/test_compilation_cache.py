"""The run's shared JAX compilation cache (``tests/conftest.py``) under
processes that read and write it at once."""

from __future__ import annotations

import os
import threading

import jax
import pytest


def test_a_cache_entry_being_written_is_never_read_half_written(tmp_path):
    """One writer puts a large entry while a reader polls for it, through JAX's
    own cache class with the run's settings: every read finds either nothing or
    the whole entry. JAX writes an entry in place and locks it only when the
    cache has a size limit; without the lock this reader sees truncated
    entries (the error "Error -5 while decompressing data: incomplete or
    truncated stream" that stopped a test run at collection)."""
    try:
        from jax._src.lru_cache import LRUCache
    except ImportError:  # JAX moved its private cache class; the run's settings stay
        pytest.skip("this JAX has no jax._src.lru_cache.LRUCache")
    cache = LRUCache(str(tmp_path), max_size=jax.config.jax_compilation_cache_max_size)
    value = os.urandom(128 * 2**20)
    writer = threading.Thread(target=cache.put, args=("entry", value))
    partial, whole = 0, 0
    writer.start()
    while writer.is_alive():
        got = cache.get("entry")
        if got is not None:
            partial += len(got) != len(value)
            whole += got == value
    writer.join()
    assert cache.get("entry") == value
    assert partial == 0, f"{partial} reads found the entry half-written ({whole} whole)"
