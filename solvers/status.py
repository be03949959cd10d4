"""One set of block status codes for both solvers and every consumer.

A block's run ends in exactly one of these (failures are values, never
exceptions inside jitted code):

* ``STOPPED``: at rest where rest is physically possible.
* ``STOPPED_BY_BARRIER``: caught by a protection barrier (CRSP's
  ``barrier_*`` parameters, ``solvers.crsp._barrier``); it rests at the
  barrier's abscissa, so its runout is ``barrier_x_m - release_x_m``. A
  finished block, like ``STOPPED``.
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
    "STOPPED_BY_BARRIER",
    "finished",
    "status_counts",
]

# code 1 is left free: CRSP's State.mode holds FLIGHT = 0 and CONTACT = 1 while a
# block moves and its final status once it ends, so no status may be 0 or 1
# except RUNNING
RUNNING, STOPPED, LEFT_PROFILE, BUDGET, INVALID, STOPPED_BY_BARRIER = 0, 2, 3, 4, 5, 6
STATUS_NAMES = {RUNNING: "running", STOPPED: "stopped", LEFT_PROFILE: "left_profile",
                BUDGET: "budget", INVALID: "invalid", STOPPED_BY_BARRIER: "stopped_by_barrier"}

# tolerance of the "never below the ground" invariant (z >= ground - 1 mm)
GROUND_TOL_M = 1e-3


def finished(status):
    """True where the block ended stopped (on the ground or by a barrier) or left
    the profile (its position is a result); False for ``RUNNING``, ``BUDGET`` and
    ``INVALID``. Works on NumPy and JAX arrays."""
    return (status == STOPPED) | (status == LEFT_PROFILE) | (status == STOPPED_BY_BARRIER)


def status_counts(status) -> dict[str, int]:
    """Counts of each status name in an array of status codes (NumPy)."""
    s = np.asarray(status).ravel()
    return {name: int(np.sum(s == code)) for code, name in STATUS_NAMES.items()}
