"""When a percentile of simulated blocks is rough: the fewer-than-20-blocks rule.

A percentile (p95 of the energy at a station, 5/95 % runouts of a fit's check,
the predictive band of a held-out row) rests on the finished blocks behind it.
With fewer than ``MIN_BLOCKS_FOR_PERCENTILE`` (20) of them the p95 lies between
the two largest values (its rank 0.95 (n - 1) exceeds n - 2), so one block more
or less moves it. ``few_blocks`` is the one copy of the rule: the solvers'
commands, the fit's check, the predictive check and the hazard tables all flag
through it, and ``few_blocks_warning`` words the one warning line they print.
"""

from __future__ import annotations

import numpy as np

__all__ = ["MIN_BLOCKS_FOR_PERCENTILE", "few_blocks", "few_blocks_warning"]

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


def few_blocks_warning(rows, what: str = "percentiles", max_named: int = 8) -> str | None:
    """One warning line naming the rows whose percentiles rest on too few blocks
    (``solvers.percentiles.few_blocks``).

    Args:
        rows: iterable of ``(label, n_blocks)``, e.g. ``("D = 0.5 m, x = 110 m", 7)``.
        what: what rests on the blocks, for the message.
        max_named: rows named before "and k more".

    Returns:
        ``"warning: <what> rest on fewer than 20 blocks in N row(s): label (n blocks);
        ..."``, or None where no row is below the threshold.
    """
    bad = [(label, int(n)) for label, n in rows if few_blocks(n)]
    if not bad:
        return None
    named = "; ".join(f"{label} ({n} block{'s' if n != 1 else ''})"
                      for label, n in bad[:max_named])
    more = f"; and {len(bad) - max_named} more" if len(bad) > max_named else ""
    return (f"warning: {what} rest on fewer than {MIN_BLOCKS_FOR_PERCENTILE} blocks in "
            f"{len(bad)} row(s), treat them as rough: {named}{more}")
