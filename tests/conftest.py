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
  the commands they start, a study's local cluster) and has no lock: JAX
  writes an entry in place, so a process can read an entry another is still
  writing. JAX then warns ("Error reading persistent compilation cache
  entry ...") and compiles the program itself, so a torn read costs one
  compilation and changes no result (``tests/test_compilation_cache.py``);
  the run lets that one warning pass (a ``filterwarnings`` line added to
  the test processes' settings, ``PYTHONWARNINGS`` for the processes they
  start). JAX locks its cache only when it has a size limit, and then
  rescans every entry at each write (``jax/_src/lru_cache.py``): over the
  run's ~1,400 entries that cost more than the compilations it shared
  (docs/testing.md).
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
_OWN_CACHE = pytest.StashKey[str]()
# the warning of a torn cache read (``jax._src.compiler``): the program is compiled instead
TORN_READ_WARNING = "Error reading persistent compilation cache entry"


def pytest_configure(config):
    """Before any test module imports JAX (and before test workers start, which
    inherit the environment): the run's compilation cache."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    rule = f"ignore:{TORN_READ_WARNING}:UserWarning"
    config.addinivalue_line("filterwarnings", rule)  # after "error": this one wins
    kept = os.environ.get("PYTHONWARNINGS", "")
    if rule not in kept.split(","):
        os.environ["PYTHONWARNINGS"] = ",".join(filter(None, (kept, rule)))
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
