"""Test-wide hygiene: figures a test drew are closed after it, so that the
whole suite in one process never holds more than one test's figures (matplotlib
warns past 20 open figures, and the test settings turn warnings into errors)."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import sys

    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")
