"""The run's shared JAX compilation cache (``tests/conftest.py``): processes
read and write it at once without a lock, so a read can find an entry half
written; such a read must cost a compilation, never a result or a test."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

from conftest import TORN_READ_WARNING

# a program small enough to compile in well under a second
_PROGRAM = ("import jax, jax.numpy as jnp; "
            "print(repr(float(jax.jit(lambda x: jnp.sin(x) * 3.0 + x ** 2)(0.5))))")


def _run(env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _PROGRAM], env=env, capture_output=True,
                          text=True, check=True, timeout=300)


def test_a_half_written_cache_entry_is_compiled_again(tmp_path):
    """Every entry of a fresh cache cut to half its bytes (what a reader sees
    while another process writes it): the program gives the same result, JAX
    warns that it could not read the entry, and the warning filter the run
    hands the processes it starts (``PYTHONWARNINGS``) keeps their output
    clean."""
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(tmp_path),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
               JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    run_filter = env.pop("PYTHONWARNINGS")
    assert TORN_READ_WARNING in run_filter
    first = _run(env)
    entries = sorted(tmp_path.glob("*-cache"))
    assert entries, os.listdir(tmp_path)
    for path in entries:
        data = path.read_bytes()
        path.write_bytes(data[:len(data) // 2])
    torn = _run(env)
    assert torn.stdout == first.stdout
    assert TORN_READ_WARNING in torn.stderr, torn.stderr
    quiet = _run(dict(env, PYTHONWARNINGS=run_filter))
    assert quiet.stdout == first.stdout
    assert TORN_READ_WARNING not in quiet.stderr, quiet.stderr


def test_the_test_processes_let_the_torn_read_warning_pass():
    """The test settings turn every warning into an error but this one (the
    text JAX writes, ``jax._src.compiler``); another stays an error."""
    warnings.warn(f"{TORN_READ_WARNING} for 'jit_f': ZstdError: truncated")
    try:
        warnings.warn("Error reading something else")
    except UserWarning:
        return
    raise AssertionError("a UserWarning passed the test settings")
