"""The fit's check of itself: the point estimate re-simulated with fresh blocks,
each row against the blocks of its entry (stage 3 of ``calib.inference.calibrate``).

* ``check_estimate``: the check of one fit (``FitCheck``).
* ``check_entries``: what the check simulates (the figure's sizes at the rows'
  median release, and every entry of the rows that is not one of them).
* ``fit_quality``: per row, the simulated 5/50/95 % runouts, its PIT and
  log-likelihood at the point estimate.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import ndtr

from calib.files.observations import Observations
from calib.inference.likelihood import RowLikelihood
from calib.model.entries import Entries
from solvers.percentiles import few_blocks

__all__ = ["FitCheck", "check_entries", "check_estimate", "fit_quality"]


class FitCheck(NamedTuple):
    """The check of one fit (``check_estimate``).

    Attributes:
        sizes_m: (K,) the sizes simulated at the rows' median release, m.
        runouts: (K, n) their runouts at the point estimate, m.
        at_rows: (G, n) the runouts of each entry of the rows, m.
        quality: per row, ``fit_quality``.
    """

    sizes_m: np.ndarray
    runouts: np.ndarray
    at_rows: np.ndarray
    quality: list[dict]


def check_estimate(forward, entries: Entries, obs: Observations, rows: RowLikelihood,
              estimate: np.ndarray, sizes_m: np.ndarray, n_blocks: int, key: jax.Array,
              tally) -> FitCheck:
    """Re-simulate the point estimate with ``n_blocks`` fresh blocks per entry of
    ``check_entries`` (the sizes ``sizes_m`` at the rows' median release, and
    every entry of the rows, ``entries``, that is not one of them) and score
    every row against its entry's blocks (``fit_quality``); ``tally`` records
    the unfinished blocks (stage "check")."""
    checked, entry = check_entries(entries, sizes_m)
    runs = dataclasses.replace(forward, entries=checked, n_blocks=n_blocks,
                               key=key).runouts(estimate[None])[0]
    tally("check", runs[None], estimate[None], checked.sizes_m)
    at_rows = runs[entry]
    return FitCheck(sizes_m, runs[:len(sizes_m)], at_rows, fit_quality(obs, at_rows, rows))


def fit_quality(obs: Observations, runouts: np.ndarray, rows: RowLikelihood) -> list[dict]:
    """Per-observation fit: simulated 5/50/95 % runouts, PIT and log-likelihood.

    Args:
        obs: the rows.
        runouts: (S, n) runouts per simulated entry, m; NaN for an unfinished
            block (left out).
        rows: the fit's likelihood of ``obs`` (``RowLikelihood``: row i reads
            entry ``rows.index[i]``).

    PIT = P(R + e <= y), e ~ N(0, sd^2), for a point (the predictive CDF of the
    OBSERVED value, tolerance included) (about uniform on [0, 1] if the model is right;
    below 0.05 or above 0.95 means the observation lies outside the simulated
    90 % band) and P(a <= R <= b) for an interval; all over the finished blocks
    (``sim_n_finished`` of them). With none, the simulated values are None;
    ``sim_few_blocks`` is True where 1 to 19 blocks finished, too few for the
    5/95 % values (``solvers.percentiles.few_blocks``).
    """
    index = rows.index
    ll = np.asarray(rows.pointwise(jnp.asarray(runouts)[None]))[0]
    out = []
    for i in range(obs.n_obs):
        r = runouts[index[i]]
        r = r[np.isfinite(r)]
        some = r.size > 0
        q05, q50, q95 = (map(float, np.quantile(r, [0.05, 0.5, 0.95])) if some
                         else (None,) * 3)
        row = {"row": i + 1, "block_size_m": float(obs.block_size_m[i]),
               "sim_q05_m": q05, "sim_median_m": q50, "sim_q95_m": q95,
               "sim_n_finished": int(r.size), "sim_few_blocks": bool(some and few_blocks(r.size)),
               "loglik": float(ll[i]) if np.isfinite(ll[i]) else None}
        if obs.is_interval[i]:
            a, b = obs.runout_min_m[i], obs.runout_max_m[i]
            row.update(observed_min_m=float(a), observed_max_m=float(b),
                       p_in_interval=float(np.mean((r >= a) & (r <= b))) if some else None)
        else:
            y, sd = obs.runout_m[i], obs.runout_sd_m[i]
            pit = float(np.mean(ndtr((y - r) / sd))) if some else None
            row.update(observed_m=float(y), observed_sd_m=float(obs.runout_sd_m[i]), pit=pit,
                       in_90_band=bool(some and 0.05 <= pit <= 0.95))
        out.append(row)
    return out


def check_entries(entries: Entries, sizes_m: np.ndarray) -> tuple[Entries, np.ndarray]:
    """What the check simulates: first the figure's sizes ``sizes_m`` at the
    median of the rows' releases, on the command's profile, with the solver's
    release speed and height, then every entry of the rows that is not one of
    these.

    Returns:
        the check's entries (E,), and the check entry of each of ``entries`` (G,).
    """
    median = float(np.median(entries.release_x_m[entries.index]))
    figure = Entries.at_sizes(sizes_m, median, density_kg_m3=entries.density_kg_m3)
    at = np.empty(entries.n, int)
    own = []
    for g in range(entries.n):
        if (entries.release_x_m[g] == median and np.isnan(entries.release_speed_m_s[g])
                and np.isnan(entries.release_height_m[g]) and entries.profiles[g] is None):
            at[g] = int(np.searchsorted(sizes_m, entries.sizes_m[g]))
        else:
            at[g] = len(sizes_m) + len(own)
            own.append(g)
    return (figure.concat(entries.take(own)) if own else figure), at
