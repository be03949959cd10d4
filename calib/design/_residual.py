"""Residual hazard behind a barrier: the exceedance of a run with the barrier beside
the run without it.

A run with a barrier element in the solver writes a hazard results file of the
same schema (``calib.files.hazard_results``), on the same stations and block
sizes; ``residual_exceedance`` puts its exceedance curves next to those of the
run without the barrier, and ``python -m calib.design --with-barrier FILE``
draws and reports them. Without such a file the table holds the run without
the barrier only.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from calib.files.hazard_results import HazardResultsError
from calib.hazard import exceedance_table

__all__ = ["check_compatible", "residual_exceedance"]


def check_compatible(without, with_barrier, where: str = "--with-barrier") -> None:
    """Raise ``HazardResultsError`` where the run with the barrier differs from the
    run without it in stations, block sizes or model."""
    for coord in ("x_m", "block_size_m"):
        a, b = without[coord].values, with_barrier[coord].values
        if a.shape != b.shape or not np.allclose(a, b):
            raise HazardResultsError(f"{where}: its {coord} differ from the run without the "
                                     "barrier: rerun it on the same stations and block sizes")
    if with_barrier.attrs.get("model") != without.attrs.get("model"):
        raise HazardResultsError(f"{where}: model {with_barrier.attrs.get('model')!r}, the run "
                                 f"without the barrier is {without.attrs.get('model')!r}")


def residual_exceedance(without, with_barrier=None, where: str = "--with-barrier"
                        ) -> pd.DataFrame:
    """Exceedance curves without and with the barrier, one row per size and station.

    Args:
        without: results Dataset of the run without the barrier.
        with_barrier: results Dataset of the run with it, or None.
        where: how to name the with-barrier file in an error.

    Returns:
        ``calib.hazard.exceedance_table`` of ``without``, plus the columns
        ``p_exceed_mean_with_barrier``, ``p_exceed_q05_with_barrier`` and
        ``p_exceed_q95_with_barrier`` (NaN without a with-barrier run).

    Raises:
        HazardResultsError: the two runs differ in stations, sizes or model.
    """
    table = exceedance_table(without)
    cols = ("p_exceed_mean", "p_exceed_q05", "p_exceed_q95")
    if with_barrier is None:
        for c in cols:
            table[f"{c}_with_barrier"] = np.nan
        return table
    check_compatible(without, with_barrier, where)
    other = exceedance_table(with_barrier)
    for c in cols:
        table[f"{c}_with_barrier"] = other[c].to_numpy()
    return table
