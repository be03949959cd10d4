"""When a percentile of simulated blocks is rough: the fewer-than-20-blocks rule.

A percentile (p95 of the energy at a station, 5/95 % runouts of a fit's check,
the predictive band of a held-out row) rests on the finished blocks behind it.
With fewer than ``MIN_BLOCKS_FOR_PERCENTILE`` (20) of them the p95 lies between
the two largest values (its rank 0.95 (n - 1) exceeds n - 2), so one block more
or less moves it. ``few_blocks`` is the one copy of the rule: the solvers'
commands, the fit's check, the predictive check and the hazard tables all flag
through it (the warning line of the commands is ``solvers.cli.few_blocks_warning``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MIN_BLOCKS_FOR_PERCENTILE", "few_blocks"]

# a percentile of simulated blocks from fewer finished blocks than this is flagged
MIN_BLOCKS_FOR_PERCENTILE = 20


def few_blocks(n_blocks):
    """True where a percentile rests on fewer than ``MIN_BLOCKS_FOR_PERCENTILE``
    (20) blocks (module docstring).

    Args:
        n_blocks: count(s) of finished blocks behind the percentile (int or array).

    Returns:
        bool, or a bool array of the same shape.
    """
    out = np.asarray(n_blocks) < MIN_BLOCKS_FOR_PERCENTILE
    return bool(out) if out.ndim == 0 else out
