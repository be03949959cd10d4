"""One set of block status codes for both solvers and every consumer.

A block's run ends in exactly one of these (failures are values, never
exceptions inside jitted code):

* ``STOPPED``: at rest where rest is physically possible.
* ``LEFT_PROFILE``: passed either end of the profile, still moving (not a stop;
  its runout is censored at the profile end).
* ``BUDGET``: still moving when the event (CRSP) or step (DEM) budget ran out.
* ``INVALID``: the state became invalid: a block below the ground (CRSP checks
  ``z >= ground - GROUND_TOL_M`` after every event) or a non-finite value.

``RUNNING`` is the state of a block whose run has not ended; it is never a
final status. Consumers must never read the runout of an unfinished block
(``BUDGET``, ``INVALID``) as a runout: use ``finished`` to exclude and count
them.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "BUDGET",
    "GROUND_TOL_M",
    "INVALID",
    "LEFT_PROFILE",
    "RUNNING",
    "STATUS_NAMES",
    "STOPPED",
    "finished",
    "status_counts",
]

RUNNING, STOPPED, LEFT_PROFILE, BUDGET, INVALID = 0, 2, 3, 4, 5
STATUS_NAMES = {RUNNING: "running", STOPPED: "stopped", LEFT_PROFILE: "left_profile",
                BUDGET: "budget", INVALID: "invalid"}

# tolerance of the "never below the ground" invariant (z >= ground - 1 mm)
GROUND_TOL_M = 1e-3


def finished(status):
    """True where the block ended stopped or left the profile (its position is a
    result); False for ``RUNNING``, ``BUDGET`` and ``INVALID``. Works on NumPy and
    JAX arrays."""
    return (status == STOPPED) | (status == LEFT_PROFILE)


def status_counts(status) -> dict[str, int]:
    """Counts of each status name in an array of status codes (NumPy)."""
    s = np.asarray(status).ravel()
    return {name: int(np.sum(s == code)) for code, name in STATUS_NAMES.items()}
