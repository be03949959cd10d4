"""Unfinished blocks in calibration: excluded, counted, and warned about.

A simulated block ends with a status (``solvers.status``). Only a FINISHED
block (``STOPPED`` or ``LEFT_PROFILE``, ``solvers.status.finished``) has a
runout. A block still moving when the solver's budget ran out (``BUDGET``) or
whose state became invalid (``INVALID``: below the ground, non-finite) has
none: its position at the end is where the budget happened to stop it.

The mechanism, the same in every calibration and discovery path:

* forward models (``calib.model.forward``, ``calib.discovery.dem_candidates``) return NaN as the
  runout, and as the passage speeds, of an unfinished block (``mask_unfinished``);
* every consumer reads runouts NaN-aware, i.e. weights the blocks by the
  finished mask: the likelihood (``calib.inference.likelihood``: kernel density and
  Silverman width over the finished blocks, divided by their number), the
  emulator's quantiles (``calib.inference.emulator``), the fit check and the figures
  (``calib.inference.calibrate``, ``calib.plots.figures``), the predictive checks of the
  discrepancy workflow (``calib.discovery.discrepancy``, ``calib.discovery.residuals``) and the
  synthetic data (``calib.discovery.synthetic`` takes finished blocks only);
* every stage counts them (``UnfinishedTally``) and the counts go to the
  outputs (``calibration.json`` and ``discovery.json``: ``unfinished_blocks``);
* a fit warns once (``UnfinishedBlocksWarning``) when the unfinished fraction of
  any (parameter point, block size) exceeds ``UNFINISHED_WARN_FRACTION``.

A block that LEFT THE PROFILE is finished but censored: it travelled at least to
the profile's end and its runout is the one recorded there (the end of the
profile, minus the release abscissa). It is kept, at that value: the
simulated distribution then puts its mass at the censoring point, which for an
observation inside the profile (``calib.fit`` rejects any other) is the right
ordering, "further than anything observable". Dropping such blocks would
shorten the simulated runouts.

The threshold. Excluding a fraction f of the blocks changes the runout CDF at
any x by at most f: F(x) = (1 - f) F_fin(x) + f F_unf(x), so |F - F_fin| =
f |F_unf - F_fin| <= f. With f = 1 % that bound is at or below the Monte Carlo
standard error of an empirical CDF value, sqrt(F (1 - F) / n): at the median for
n <= 2500 blocks, every block count the fits use per (point, size)
(``calib.inference.budget.Budget``: 4 to 2000; ``calib.discovery.discrepancy``: 4 to 128), and at
the 5 and 95 % levels for n <= 475. Above 1 % the exclusion can move the fitted
distribution by more than its own sampling noise, and the warning says so.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from solvers.status import finished

__all__ = ["UNFINISHED_WARN_FRACTION", "UnfinishedBlocksWarning", "UnfinishedTally",
           "mask_unfinished", "nan_quantile", "unfinished_record", "warn_unfinished"]

UNFINISHED_WARN_FRACTION = 0.01


class UnfinishedBlocksWarning(UserWarning):
    """More than ``UNFINISHED_WARN_FRACTION`` of the blocks of some (parameter
    point, block size) did not finish; they were excluded from the fit."""


def mask_unfinished(values, status) -> np.ndarray:
    """``values`` with NaN where the block did not finish.

    Args:
        values: (..., n) or (..., n, k) per-block values (runouts, m; speeds, m/s).
        status: (..., n) status codes (``solvers.status``).

    Returns:
        float64 NumPy array of ``values``' shape.
    """
    values = np.asarray(values, np.float64)
    ok = np.asarray(finished(np.asarray(status)))
    ok = ok.reshape(ok.shape + (1,) * (values.ndim - ok.ndim))
    return np.where(ok, values, np.nan)


def nan_quantile(x, q, axis: int = -1) -> np.ndarray:
    """``np.nanquantile`` that returns NaN, without a RuntimeWarning, where a
    slice holds no finite value (every block unfinished)."""
    x = np.asarray(x, np.float64)
    empty = ~np.any(np.isfinite(x), axis=axis, keepdims=True)
    out = np.nanquantile(np.where(empty, 0.0, x), q, axis=axis)
    return np.where(np.squeeze(empty, axis=axis), np.nan, out)


@dataclasses.dataclass
class UnfinishedTally:
    """Counts of unfinished blocks over the simulations of one stage of a fit.

    ``add`` takes runouts (T, S, n) with NaN for unfinished blocks, for T
    parameter points and the block sizes ``sizes_m`` (S,).
    """

    sizes_m: tuple[float, ...]
    n_blocks: int = 0
    n_unfinished: int = 0
    n_points: int = 0
    n_over: int = 0
    max_fraction: float = 0.0
    worst: dict | None = None

    def add(self, runouts, theta=None, names: tuple[str, ...] | None = None) -> None:
        """Count the NaN runouts of (T, S, n) ``runouts`` at parameters ``theta`` (T, p)."""
        r = np.asarray(runouts, np.float64)
        r = r.reshape((-1,) + r.shape[-2:])
        frac = np.isnan(r).mean(axis=-1)  # (T, S)
        self.n_blocks += int(r.size)
        self.n_unfinished += int(np.isnan(r).sum())
        self.n_points += int(frac.size)
        self.n_over += int(np.sum(frac > UNFINISHED_WARN_FRACTION))
        t, s = np.unravel_index(int(np.argmax(frac)), frac.shape)
        if frac[t, s] > self.max_fraction:
            self.max_fraction = float(frac[t, s])
            self.worst = {"block_size_m": float(self.sizes_m[s]),
                          "fraction": float(frac[t, s])}
            if theta is not None:
                th = np.atleast_2d(np.asarray(theta, float))[t]
                keys = names or tuple(f"theta{i}" for i in range(th.size))
                self.worst["theta"] = dict(zip(keys, map(float, th)))

    def as_dict(self) -> dict:
        return {"n_blocks": self.n_blocks, "n_unfinished": self.n_unfinished,
                "fraction": self.n_unfinished / self.n_blocks if self.n_blocks else 0.0,
                "n_points": self.n_points, "n_points_over_threshold": self.n_over,
                "max_fraction": self.max_fraction, "worst": self.worst}


def _where(worst: dict | None) -> str:
    if worst is None:
        return ""
    at = f" at block size {worst['block_size_m']:g} m"
    if "theta" in worst:
        at += " and " + ", ".join(f"{k} = {v:.3g}" for k, v in worst["theta"].items())
    return at


def unfinished_record(tallies: dict[str, UnfinishedTally], label: str,
                      remedy: str = "raise the solver's budget (CRSP Settings.max_events, "
                                    "DEM max_time_s)") -> dict:
    """The JSON record of a fit's tallies, with its warning text (None if every
    (point, size) stays at or below ``UNFINISHED_WARN_FRACTION``); ``remedy``
    ends it (what the user of the fit can raise)."""
    stages = {k: t.as_dict() for k, t in tallies.items()}
    bad = {k: t for k, t in tallies.items() if t.n_over}
    message = None
    if bad:
        k, t = max(bad.items(), key=lambda kv: kv[1].max_fraction)
        total = sum(b.n_over for b in bad.values())
        points = sum(b.n_points for b in bad.values())
        message = (f"{label}: unfinished blocks (still moving at the solver's budget, or "
                   f"invalid) exceed {UNFINISHED_WARN_FRACTION:.0%} in {total} of {points} "
                   f"(parameter point, block size) pairs of stage(s) {', '.join(bad)}; up "
                   f"to {t.max_fraction:.1%} in stage {k}{_where(t.worst)}. They were "
                   f"excluded from the fit (never read as runouts), which can bias it by "
                   f"up to that fraction of probability; {remedy}")
    return {"threshold": UNFINISHED_WARN_FRACTION, "stages": stages, "warning": message}


def warn_unfinished(record: dict) -> None:
    """Emit the record's warning, if it has one, as an ``UnfinishedBlocksWarning``."""
    if record.get("warning"):
        warnings.warn(record["warning"], UnfinishedBlocksWarning, stacklevel=3)
