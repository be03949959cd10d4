"""Bounded-memory summaries of many simulated blocks at analysis stations.

A hazard run simulates up to millions of blocks per size; keeping every
block's energy at every station would take n_blocks x n_stations x 8 bytes per
quantity (0.5 GB for 1e6 blocks and 61 stations). Instead each chunk of blocks
is reduced, on the device and in integers, to

* counts per station: blocks whose final position lies beyond x (runout
  exceedance), blocks that passed x (reach), passers with E > 30 and > 300 kJ;
* log-binned histograms of energy, velocity and bounce height of the passers,
  at ``FINE`` (5) sub-bins per bin of ``BINS``: 1000 bins per decade;
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
ratio, 10^(1/BPD) - 1 = 1.16 % for BPD = 200 bins per decade (``BINS``: the
hazard tables), 0.23 % for the 1000 bins per decade of ``FINE_BINS``.

Why finer bins and not exact per-block quantiles (design values, ``calib.design``).
A barrier design reads the 95th and 99th percentiles of speed, passing height
and energy of each posterior draw at the barrier, with their Monte Carlo
error, whose target is 2 % of the value. A histogram error of 1.16 % would
eat most of that; one of 0.23 % is a tenth of it. Exact quantiles from a sort of
the per-block values of a chunk would need the whole draw in one chunk (a
default CRSP run splits 20,000 blocks per size into two chunks of 10,000, and
the DEM runs one size per unit), so they would hold only for some runs and
make the numbers depend on the chunking. Nested fine bins keep every count an
integer that adds up the same whatever the chunking or the device, and their
coarse sums are the ``BINS`` histograms bit for bit (a fine bin lies inside one
coarse bin by construction: ``Bins.index`` with ``sub`` computes both from one
y = BPD log10(v / v_min); a separate 1000-per-decade index would disagree with
the coarse one for values within rounding of a bin edge), so the hazard tables
do not change (checked byte for byte on a run). Both are computed under jit, as
the chunks are: jit and op-by-op evaluation of the logarithm may round a value
on a bin edge differently.

Monte Carlo error of a percentile (``percentile_interval``): the
distribution-free interval of order statistics. Among n independent values,
the number B below the true q-quantile is Binomial(n, q); with
j_lo = F^-1(0.025) and j_hi = F^-1(0.975) + 1 (F the binomial CDF),
P(X_(j_lo) <= xi_q <= X_(j_hi)) >= 95 % for any continuous distribution
(e.g. Hahn & Meeker 1991, Statistical Intervals, Sect. 5.2). This is the
interval a percentile bootstrap approximates (resampling the same data), but
it is exact, needs no random numbers and is read from the same histogram
at ranks j_lo and j_hi. Its half-width (X_(j_hi) - X_(j_lo)) / 2 shrinks as
1 / sqrt(n) (tested against repeated synthetic samples and a bootstrap,
``tests/test_hazard_results.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from solvers.status import INVALID, LEFT_PROFILE, finished

__all__ = ["BINS", "DRAW_BINS", "DRAW_SUB", "FINE", "FINE_BINS", "PERCENTILES", "Bins",
           "ChunkStats", "hist_exceedance", "hist_quantile", "percentile_interval",
           "percentile_table", "rebin", "reduce_chunk"]


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

    def index(self, v: jax.Array, sub: int = 1) -> jax.Array:
        """Bin of each value (any shape; NaN goes to bin 0 and must be masked).

        ``sub`` > 1: the bin of ``refined(sub)``, computed inside this one's bin
        (y = BPD log10(v / v_min), coarse k = floor(y), fine k sub + floor((y - k)
        sub)), so that every fine bin lies in exactly the coarse bin ``index``
        gives, rounding included."""
        safe = jnp.where(v >= self.v_min, v, self.v_min)
        y = jnp.log10(safe / self.v_min) * self.per_decade
        if sub == 1:
            k = 1 + jnp.floor(y).astype(jnp.int32)
            k = jnp.where(v >= self.v_min, k, 0)
            return jnp.clip(k, 0, self.n - 1)
        kc = jnp.floor(y)
        part = jnp.clip(jnp.floor((y - kc) * sub), 0, sub - 1).astype(jnp.int32)
        kc = kc.astype(jnp.int32)
        k = jnp.where(kc >= self.n_log, self.n_log * sub + 1, 1 + kc * sub + part)
        return jnp.where(v >= self.v_min, k, 0)

    def refined(self, sub: int) -> Bins:
        """The bins ``index(v, sub)`` counts in: ``sub`` per bin of these."""
        return Bins(self.v_min, self.v_max, self.per_decade * sub)

    def lower_edges(self) -> np.ndarray:
        """(n,) lower edge of every bin: 0 (underflow), the log edges, v_max (overflow)."""
        return np.concatenate([[0.0], self.edges()])

    def edges(self) -> np.ndarray:
        """(n_log + 1,) edges of the log bins 1 .. n_log."""
        return self.v_min * 10.0 ** (np.arange(self.n_log + 1) / self.per_decade)


# energy (kJ), velocity (m/s), bounce height (m): the hazard tables' bins
BINS = {
    "energy_kJ": Bins(1e-4, 1e6, 200),
    "velocity_m_s": Bins(1e-3, 1e3, 200),
    "bounce_height_m": Bins(1e-3, 1e3, 200),
}
# what a chunk counts in: FINE sub-bins per bin of BINS (1000 per decade, 0.23 %)
FINE = 5
FINE_BINS = {q: b.refined(FINE) for q, b in BINS.items()}
# per-draw histograms a run keeps for design probabilities (50 per decade, 4.7 %):
# DRAW_SUB fine bins each
DRAW_SUB = 20
DRAW_BINS = {q: Bins(b.v_min, b.v_max, b.per_decade // DRAW_SUB) for q, b in FINE_BINS.items()}
# percentiles every run records per draw, size and station (design values)
PERCENTILES = (50.0, 95.0, 99.0)


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
        hist_energy_kJ, hist_velocity_m_s, hist_bounce_height_m: (T, S, B) counts
            in ``FINE_BINS`` (``rebin(..., FINE)`` gives the ``BINS`` counts).
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


def _hist(values, mask, bins: Bins, sub: int = FINE):
    t, _, s = values.shape
    n = bins.refined(sub).n
    k = bins.index(values, sub)
    flat = (jnp.arange(t)[:, None, None] * s + jnp.arange(s)[None, None, :]) * n + k
    out = jnp.zeros((t * s * n,), jnp.int32).at[flat.reshape(-1)].add(
        mask.reshape(-1).astype(jnp.int32))
    return out.reshape(t, s, n)


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


def rebin(counts: np.ndarray, factor: int) -> np.ndarray:
    """Counts of bins ``factor`` times wider: (..., n_log f + 2) -> (..., n_log + 2),
    under- and overflow kept (the nesting of ``Bins.index`` with ``sub``)."""
    counts = np.asarray(counts)
    n_log = (counts.shape[-1] - 2) // factor
    mid = counts[..., 1:-1].reshape(counts.shape[:-1] + (n_log, factor)).sum(axis=-1)
    return np.concatenate([counts[..., :1], mid, counts[..., -1:]], axis=-1)


class _Ranks:
    """Histogram counts ready to be read at many ranks: the cumulative counts, and
    every row shifted above the previous one so that one binary search finds the
    bin of a rank in all rows at once."""

    def __init__(self, counts: np.ndarray):
        self.counts = np.asarray(counts, dtype=np.int64)
        self.cum = np.cumsum(self.counts, axis=-1)
        self.n = self.cum[..., -1]
        b = self.cum.shape[-1]
        flat = self.cum.reshape(-1, b).astype(np.float64)
        self.offset = np.arange(flat.shape[0], dtype=np.float64) * (
            flat[:, -1].max(initial=0.0) + 2.0)
        self.sorted = (flat + self.offset[:, None]).ravel()

    def value(self, rank, bins: Bins) -> np.ndarray:
        """The value of rank ``rank`` (the smallest v with count(<= v) >= rank),
        interpolated geometrically in its bin; 0 in the underflow, +inf in the
        overflow (NaN-free: callers mask empty rows)."""
        counts, cum = self.counts, self.cum
        shape, b = cum.shape[:-1], cum.shape[-1]
        rank = np.asarray(rank, dtype=np.float64)
        # first bin whose cumulative count reaches the rank and holds a count: for a
        # rank r > 0 the first k with cum[k] >= r (then counts[k] > 0), for r <= 0
        # the first k with cum[k] >= 1
        target = np.maximum(np.broadcast_to(rank, shape).reshape(-1), 1.0) + self.offset
        hit = np.searchsorted(self.sorted, target, side="left")
        k = np.minimum(hit - np.arange(target.size) * b, b - 1).reshape(shape)
        c_k = np.take_along_axis(counts, k[..., None], axis=-1)[..., 0]
        below = np.take_along_axis(cum, k[..., None], axis=-1)[..., 0] - c_k
        frac = np.clip((rank - below) / np.maximum(c_k, 1), 0.0, 1.0)
        edges = bins.edges()
        j = np.clip(k - 1, 0, bins.n_log - 1)
        lo, hi = edges[j], edges[j + 1]
        val = lo * (hi / lo) ** frac
        val = np.where(k == 0, 0.0, val)
        return np.where(k == bins.n - 1, np.inf, val)


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
    r = _Ranks(counts)
    return np.where(r.n > 0, r.value(q * r.n, bins), np.nan)


def percentile_interval(counts: np.ndarray, q: float, bins: Bins, level: float = 0.95
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quantile ``q`` and its distribution-free ``level`` interval (module docstring).

    With n the values counted and B ~ Binomial(n, q): j_lo = F^-1((1 - level) / 2),
    j_hi = F^-1((1 + level) / 2) + 1 (F^-1 the smallest k with F(k) >= p); the
    interval is [X_(j_lo), X_(j_hi)], the values of ranks j_lo and j_hi read as
    ``hist_quantile`` reads rank q n. Where j_lo < 1 or j_hi > n (too few values
    for the level) that end is NaN.

    Args:
        counts: (..., B) integer counts.
        q: quantile in (0, 1).
        bins: the ``Bins`` behind the counts.
        level: coverage of the interval.

    Returns:
        (value, lo, hi), each (...) float64; all NaN where no values.
    """
    return _interval(_Ranks(counts), q, bins, level)


def percentile_table(counts: np.ndarray, bins: Bins, percentiles=PERCENTILES,
                     level: float = 0.95) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``percentile_interval`` at each of ``percentiles`` (in %), the cumulative
    counts formed once: (value, lo, hi), each (..., P)."""
    r = _Ranks(counts)
    parts = [_interval(r, p / 100.0, bins, level) for p in percentiles]
    return tuple(np.stack([part[i] for part in parts], axis=-1) for i in range(3))


def _interval(r: _Ranks, q: float, bins: Bins, level: float):
    from scipy.stats import binom

    n = r.n
    value = np.where(n > 0, r.value(q * n, bins), np.nan)
    nn = np.maximum(n, 1)
    j_lo = binom.ppf((1.0 - level) / 2.0, nn, q)
    j_hi = binom.ppf((1.0 + level) / 2.0, nn, q) + 1.0
    lo = np.where((n > 0) & (j_lo >= 1), r.value(j_lo, bins), np.nan)
    hi = np.where((n > 0) & (j_hi <= n), r.value(np.minimum(j_hi, nn), bins), np.nan)
    return value, lo, hi


def hist_exceedance(counts: np.ndarray, threshold, bins: Bins) -> np.ndarray:
    """Fraction of the values behind ``counts`` above ``threshold``.

    Inside the bin [lo, hi) holding the threshold the values are taken as spread
    evenly in log v (the interpolation of ``hist_quantile``): a fraction
    log(hi / t) / log(hi / lo) of its count lies above t. Values of the underflow
    bin are taken as 0 (below any positive threshold), those of the overflow bin
    as above any threshold (conservative). No values give NaN.

    Args:
        counts: (..., B) integer counts.
        threshold: (...) or scalar threshold, in the unit of the bins (> 0).
        bins: the ``Bins`` behind the counts.

    Returns:
        (...) float64 fractions in [0, 1].
    """
    counts = np.asarray(counts, dtype=np.float64)
    t = np.broadcast_to(np.asarray(threshold, dtype=np.float64), counts.shape[:-1])
    n = counts.sum(axis=-1)
    edges = bins.edges()
    # bin of the threshold: 0 below v_min, n - 1 at or above v_max
    j = np.clip(np.searchsorted(edges, t, side="right"), 0, bins.n - 1)
    above = np.flip(np.cumsum(np.flip(counts, -1), -1), -1)  # above[k] = sum(counts[k:])
    strictly = np.where(j + 1 < bins.n, np.take_along_axis(
        above, np.minimum(j + 1, bins.n - 1)[..., None], -1)[..., 0], 0.0)
    c_j = np.take_along_axis(counts, j[..., None], -1)[..., 0]
    inner = (j >= 1) & (j <= bins.n_log)
    lo = edges[np.clip(j - 1, 0, bins.n_log)]
    hi = edges[np.clip(j, 0, bins.n_log)]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(inner, np.log(hi / np.maximum(t, lo)) / np.log(hi / lo), 0.0)
    frac = np.where(j == bins.n - 1, 1.0, frac)  # overflow: counted as above
    out = (strictly + c_j * np.clip(frac, 0.0, 1.0)) / np.maximum(n, 1.0)
    return np.where(n > 0, out, np.nan)
