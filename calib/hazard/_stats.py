"""Bounded-memory summaries of many simulated blocks at analysis stations.

A hazard run simulates up to millions of blocks per size; keeping every
block's energy at every station would take n_blocks x n_stations x 8 bytes per
quantity (0.5 GB for 1e6 blocks and 61 stations). Instead each chunk of blocks
is reduced, on the device and in integers, to

* counts per station: blocks whose final position lies beyond x (runout
  exceedance), blocks that passed x (reach), passers with E > 30 and > 300 kJ;
* log-binned histograms of energy, velocity and bounce height of the passers;
* counts per size of the blocks that left the profile and of the unfinished ones.

Block status (``solvers.status``). Only a finished block (stopped, or left the
profile) has a final position, so only finished blocks count towards the
exceedance; an unfinished one (still moving at the budget, or invalid) is
counted as unfinished instead. A block that left the profile counts as beyond
every station it passed (its final abscissa is the profile's end). Passages
count towards reach and the histograms for every block except an INVALID one:
a block stopped by the budget really passed the stations it passed, while an
invalid state (below the ground, non-finite) makes its records meaningless.

Counts add up exactly whatever the chunking or device, so tables are
bit-for-bit reproducible. Quantiles are read from the histograms: a value
v >= v_min falls in bin k = 1 + floor(BPD log10(v / v_min)); bin 0 holds
0 <= v < v_min (reported as 0) and the last bin v >= v_max. Within a bin the
quantile is interpolated geometrically, so its relative error is below one bin
ratio, 10^(1/BPD) - 1 = 1.16 % for BPD = 200 bins per decade.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from solvers.status import INVALID, LEFT_PROFILE, finished

__all__ = ["BINS", "Bins", "ChunkStats", "hist_quantile", "reduce_chunk"]


class Bins(NamedTuple):
    """Log-spaced histogram bins: ``per_decade`` bins from ``v_min`` to ``v_max``
    plus an underflow bin (values below v_min, zero included) and an overflow bin."""

    v_min: float
    v_max: float
    per_decade: int

    @property
    def n_log(self) -> int:
        return int(round(np.log10(self.v_max / self.v_min) * self.per_decade))

    @property
    def n(self) -> int:
        return self.n_log + 2

    def index(self, v: jax.Array) -> jax.Array:
        """Bin of each value (any shape; NaN goes to bin 0 and must be masked)."""
        safe = jnp.where(v >= self.v_min, v, self.v_min)
        k = 1 + jnp.floor(jnp.log10(safe / self.v_min) * self.per_decade).astype(jnp.int32)
        k = jnp.where(v >= self.v_min, k, 0)
        return jnp.clip(k, 0, self.n - 1)

    def edges(self) -> np.ndarray:
        """(n_log + 1,) edges of the log bins 1 .. n_log."""
        return self.v_min * 10.0 ** (np.arange(self.n_log + 1) / self.per_decade)


# energy (kJ), velocity (m/s), bounce height (m)
BINS = {
    "energy_kJ": Bins(1e-4, 1e6, 200),
    "velocity_m_s": Bins(1e-3, 1e3, 200),
    "bounce_height_m": Bins(1e-3, 1e3, 200),
}


class ChunkStats(NamedTuple):
    """Integer summaries of a chunk of blocks for T tasks and S stations.

    Attributes:
        n_blocks: () blocks counted per task.
        n_unfinished: (T,) blocks that did not finish: still moving when the
            event/step budget ran out, or invalid (``solvers.status``).
        n_left_profile: (T,) blocks that left the profile still moving.
        exceed: (T, S) finished blocks whose final abscissa is beyond the station.
        reach: (T, S) blocks that passed the station moving downslope (invalid
            blocks excluded).
        e30, e300: (T, S) passers with E > 30 kJ / E > 300 kJ.
        hist_energy_kJ, hist_velocity_m_s, hist_bounce_height_m: (T, S, B) counts.
    """

    n_blocks: jax.Array
    n_unfinished: jax.Array
    n_left_profile: jax.Array
    exceed: jax.Array
    reach: jax.Array
    e30: jax.Array
    e300: jax.Array
    hist_energy_kJ: jax.Array
    hist_velocity_m_s: jax.Array
    hist_bounce_height_m: jax.Array


def _hist(values, mask, bins: Bins):
    t, _, s = values.shape
    k = bins.index(values)
    flat = (jnp.arange(t)[:, None, None] * s + jnp.arange(s)[None, None, :]) * bins.n + k
    out = jnp.zeros((t * s * bins.n,), jnp.int32).at[flat.reshape(-1)].add(
        mask.reshape(-1).astype(jnp.int32))
    return out.reshape(t, s, bins.n)


def reduce_chunk(stop_x_m, status, passed, energy_kJ, velocity_m_s, bounce_height_m,
                 valid, stations_x_m) -> ChunkStats:
    """Reduce per-block results of one chunk to ``ChunkStats`` (pure, jit-able).

    Args:
        stop_x_m: (T, n) final abscissa of each block, m.
        status: (T, n) final status of each block (``solvers.status`` codes).
        passed: (T, n, S) bool, the block passed the station.
        energy_kJ, velocity_m_s, bounce_height_m: (T, n, S) values at first
            passage (NaN where not passed).
        valid: (n,) bool, the block belongs to the run (chunks are padded).
        stations_x_m: (S,) station abscissae, m.

    Returns:
        ``ChunkStats``; every count is an int32 sum over the valid blocks.
    """
    v = valid[None, :]
    vs = valid[None, :, None]
    done = finished(status)  # (T, n): the final abscissa is a result
    ok = passed & vs & (status != INVALID)[..., None]
    i32 = jnp.int32
    return ChunkStats(
        n_blocks=jnp.sum(valid.astype(i32)),
        n_unfinished=jnp.sum((~done & v).astype(i32), axis=1),
        n_left_profile=jnp.sum(((status == LEFT_PROFILE) & v).astype(i32), axis=1),
        exceed=jnp.sum(((stop_x_m[..., None] > stations_x_m) & (done & v)[..., None]
                        ).astype(i32), axis=1),
        reach=jnp.sum(ok.astype(i32), axis=1),
        e30=jnp.sum((ok & (energy_kJ > 30.0)).astype(i32), axis=1),
        e300=jnp.sum((ok & (energy_kJ > 300.0)).astype(i32), axis=1),
        hist_energy_kJ=_hist(energy_kJ, ok, BINS["energy_kJ"]),
        hist_velocity_m_s=_hist(velocity_m_s, ok, BINS["velocity_m_s"]),
        hist_bounce_height_m=_hist(bounce_height_m, ok, BINS["bounce_height_m"]),
    )


def hist_quantile(counts: np.ndarray, q: float, bins: Bins) -> np.ndarray:
    """Quantile ``q`` in [0, 1] of the values behind histogram ``counts``.

    The sample quantile is the smallest value v with F(v) >= q (NumPy's
    ``method="inverted_cdf"``): rank r = q n is located in the cumulative
    counts, which gives the bin [lo, hi) of that value; within it the value is
    lo (hi / lo)^f with f the fraction of the bin's count below r, so the result
    lies in the same bin as the exact sample quantile. Underflow gives 0,
    overflow gives +inf, no values give NaN.

    Args:
        counts: (..., B) integer counts.
        q: quantile in [0, 1].
        bins: the ``Bins`` behind the counts.

    Returns:
        (...) float64 quantiles.
    """
    counts = np.asarray(counts, dtype=np.int64)
    cum = np.cumsum(counts, axis=-1)
    n = cum[..., -1]
    rank = q * n
    # first bin whose cumulative count reaches the rank (at least one count in it)
    k = np.argmax((cum >= rank[..., None]) & (counts > 0), axis=-1)
    c_k = np.take_along_axis(counts, k[..., None], axis=-1)[..., 0]
    below = np.take_along_axis(cum, k[..., None], axis=-1)[..., 0] - c_k
    frac = np.clip((rank - below) / np.maximum(c_k, 1), 0.0, 1.0)
    edges = bins.edges()
    j = np.clip(k - 1, 0, bins.n_log - 1)
    lo, hi = edges[j], edges[j + 1]
    val = lo * (hi / lo) ** frac
    val = np.where(k == 0, 0.0, val)
    val = np.where(k == bins.n - 1, np.inf, val)
    return np.where(n > 0, val, np.nan)
