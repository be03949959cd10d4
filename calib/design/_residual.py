"""Residual hazard behind a barrier: the exceedance and the reach probability of a run
with the barrier beside the run without it.

A run with the barrier element in the solver (``python -m calib.hazard
--barrier-x-m X ...``, ``solvers/crsp/_barrier.py``) writes a hazard results file
of the same schema (``calib.files.hazard_results``) with the barrier's attributes
(``barrier_x_m``, ``barrier_height_m``, ``barrier_capacity_kJ``), on the same
stations and block sizes; ``residual_exceedance`` puts its exceedance curves and
reach probabilities, with their 5-95 % bands over posterior draws, next to those
of the run without the barrier, and ``python -m calib.design --with-barrier FILE``
draws and reports them at the station of interest. Run both with the same seed
and draws: block j of draw d then has the same random numbers in both (common
random numbers, ``calib.hazard._units``), the blocks the barrier does not touch
are the same blocks, and the difference is the barrier's, not Monte Carlo
noise. Without such a file the table holds the run without the barrier only.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from calib.files.hazard_results import (
    HazardResultsError,
    crsp_event_budget,
    json_attr,
    optional_attr,
)
from calib.hazard import exceedance_table

__all__ = ["BANDED", "barrier_of", "check_compatible", "residual_exceedance"]

# the columns given without and with the barrier
BANDED = ("p_exceed_mean", "p_exceed_q05", "p_exceed_q95", "reach_prob_mean", "reach_prob_q05",
          "reach_prob_q95")


def barrier_of(ds) -> tuple[float, float, float] | None:
    """(x, height, capacity) of a run's barrier, or None for a run without one."""
    if optional_attr(ds, "barrier_x_m") is None:
        return None
    return tuple(float(ds.attrs[k]) for k in ("barrier_x_m", "barrier_height_m",
                                              "barrier_capacity_kJ"))


def check_compatible(without, with_barrier, where: str = "--with-barrier") -> list[str]:
    """Refuse (``HazardResultsError``) a run with the barrier that is not one (no
    barrier attributes), a run "without" that has a barrier, or runs that differ in
    stations, block sizes or model; return warnings where they differ in what makes
    the comparison one of common random numbers (seed, posterior draws, blocks per
    draw, release conditions, the CRSP event budget)."""
    for coord in ("x_m", "block_size_m"):
        a, b = without[coord].values, with_barrier[coord].values
        if a.shape != b.shape or not np.allclose(a, b):
            raise HazardResultsError(f"{where}: its {coord} differ from the run without the "
                                     "barrier: rerun it on the same stations and block sizes")
    if with_barrier.attrs.get("model") != without.attrs.get("model"):
        raise HazardResultsError(f"{where}: model {with_barrier.attrs.get('model')!r}, the run "
                                 f"without the barrier is {without.attrs.get('model')!r}")
    if barrier_of(with_barrier) is None:
        raise HazardResultsError(f"{where}: not a run with a barrier (no attribute "
                                 "barrier_x_m): rerun python -m calib.hazard with --barrier-x-m")
    if barrier_of(without) is not None:
        raise HazardResultsError(f"{where}: the run it is compared with has a barrier too (at "
                                 f"x = {barrier_of(without)[0]:g} m); give the run without one")
    warnings = []
    same = [("seed", without.attrs.get("seed") == with_barrier.attrs.get("seed")),
            ("blocks per draw", without.attrs.get("n_blocks_per_draw")
             == with_barrier.attrs.get("n_blocks_per_draw")),
            ("posterior draws", np.array_equal(without["posterior_row"].values,
                                               with_barrier["posterior_row"].values)),
            ("release conditions", json_attr(without, "release_json")
             == json_attr(with_barrier, "release_json")
             and without.attrs.get("release_x_m") == with_barrier.attrs.get("release_x_m")),
            ("event budget", crsp_event_budget(without) == crsp_event_budget(with_barrier))]
    differ = [name for name, ok in same if not ok]
    if differ:
        warnings.append(f"warning: {where} differs from the run without the barrier in "
                        f"{', '.join(differ)}: the residual hazard is not compared with "
                        "common random numbers, and its difference holds Monte Carlo noise")
    return warnings


def _reach(ds) -> np.ndarray:
    """(D, T, S) reach probability per draw (NaN at or above the release)."""
    n = float(ds.attrs["n_blocks_per_draw"])
    downslope = ds["x_m"].values > float(ds.attrs["release_x_m"])
    return np.where(downslope, ds["n_reach"].values / n, np.nan)


def _reach_columns(ds) -> dict:
    p = _reach(ds)
    with np.errstate(invalid="ignore"):
        mean = p.mean(axis=0)
        q = np.quantile(p, [0.05, 0.95], axis=0)
    return {"reach_prob_mean": mean.ravel(), "reach_prob_q05": q[0].ravel(),
            "reach_prob_q95": q[1].ravel()}


def residual_exceedance(without, with_barrier=None, where: str = "--with-barrier"
                        ) -> pd.DataFrame:
    """Exceedance and reach without and with the barrier, one row per size and station.

    Args:
        without: results Dataset of the run without the barrier.
        with_barrier: results Dataset of the run with it, or None.
        where: how to name the with-barrier file in an error.

    Returns:
        ``calib.hazard.exceedance_table`` of ``without`` with ``reach_prob_mean``,
        ``reach_prob_q05``, ``reach_prob_q95`` (5-95 % over draws; NaN at or above
        the release), plus each of ``BANDED`` again with the suffix
        ``_with_barrier`` (NaN without a with-barrier run).

    Raises:
        HazardResultsError: the two runs cannot be compared (``check_compatible``).
    """
    table = exceedance_table(without)
    for k, v in _reach_columns(without).items():
        table[k] = v
    if with_barrier is None:
        for c in BANDED:
            table[f"{c}_with_barrier"] = np.nan
        return table
    check_compatible(without, with_barrier, where)
    other = exceedance_table(with_barrier)
    for k, v in _reach_columns(with_barrier).items():
        other[k] = v
    for c in BANDED:
        table[f"{c}_with_barrier"] = other[c].to_numpy()
    return table
