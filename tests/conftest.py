"""Test-wide settings.

* Figures a test drew are closed after it, so that the whole suite in one
  process never holds more than one test's figures (matplotlib warns past 20
  open figures, and the test settings turn warnings into errors).
* One JAX compilation cache for the whole run (``JAX_COMPILATION_CACHE_DIR``,
  a fresh temporary folder removed at the end; left alone when the caller
  set one): most of the suite's time is XLA compiling the same solver
  programs again in test after test and in the commands the tests start as
  subprocesses (they inherit the variable). A cached program is the same
  program: results do not change. Every run starts cold, so its time is that
  of a fresh machine.
* The cache is shared by processes that run at once (the two test workers,
  the commands they start, a study's local cluster), and JAX's cache writes
  an entry in place: without a lock a process can read an entry another is
  still writing ("Error reading persistent compilation cache entry ...
  truncated stream", a warning the test settings make an error). JAX takes a
  file lock (the ``filelock`` package, in the test extra) around every read
  and write of its cache only when the cache has a size limit
  (``jax/_src/lru_cache.py``), so the run sets one
  (``JAX_COMPILATION_CACHE_MAX_SIZE``, 1 TiB: nothing is evicted), also
  where the caller chose the folder.
* The default run spreads its test files over two worker processes
  (pytest-xdist, ``-n 2 --dist loadfile`` in ``pyproject.toml``): one per
  core of a 2-core machine; a file's tests share one worker and its fixtures.
  On a GPU the workers share the device, so JAX does not preallocate its
  memory (``XLA_PYTHON_CLIENT_PREALLOCATE``, unless the caller set it).
"""

from __future__ import annotations

import os
import shutil
import tempfile

import pytest

_CACHE_VARIABLE = "JAX_COMPILATION_CACHE_DIR"
# a size limit turns on JAX's file lock around cache reads and writes; 1 TiB evicts nothing
_CACHE_LIMIT_VARIABLE = "JAX_COMPILATION_CACHE_MAX_SIZE"
_CACHE_LIMIT_BYTES = 2**40
_OWN_CACHE = pytest.StashKey[str]()


def pytest_configure(config):
    """Before any test module imports JAX (and before test workers start, which
    inherit the environment): the run's compilation cache."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    try:
        import filelock  # noqa: F401  (JAX's cache lock)
    except ImportError as e:
        raise pytest.UsageError(
            "the tests share one JAX compilation cache between processes and need the "
            "`filelock` package to lock it: pip install -e \".[test]\"") from e
    os.environ.setdefault(_CACHE_LIMIT_VARIABLE, str(_CACHE_LIMIT_BYTES))
    if os.environ.get(_CACHE_VARIABLE):
        return
    folder = tempfile.mkdtemp(prefix="rockfall-tests-jax-cache-")
    config.stash[_OWN_CACHE] = folder
    os.environ[_CACHE_VARIABLE] = folder
    # cache every program, however quick to compile or small
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"


def pytest_unconfigure(config):
    folder = config.stash.get(_OWN_CACHE, None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(_CACHE_VARIABLE, None)



@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import sys

    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")
