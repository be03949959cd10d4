"""Values as JSON can hold them, for every file the toolkit writes as JSON or
stores as JSON text (the commands' outputs, ``hazard.nc``'s attributes, the
design record): NumPy scalars become Python ones, non-finite floats ``null``
(``json.dumps(..., allow_nan=False)`` refuses NaN), tuples lists."""

from __future__ import annotations

import numpy as np

__all__ = ["json_ready"]


def json_ready(v):
    """A copy of ``v`` that ``json.dumps(..., allow_nan=False)`` accepts: NumPy
    scalars become Python ones, non-finite floats None, tuples lists."""
    if isinstance(v, dict):
        return {k: json_ready(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [json_ready(x) for x in v]
    if isinstance(v, (np.bool_, bool)):
        return bool(v)
    if isinstance(v, (np.integer, int)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v) if np.isfinite(v) else None
    return v
