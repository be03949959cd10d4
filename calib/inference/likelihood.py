"""The observation model: an observed runout against a simulated runout distribution.

Each observed row i (block size d_i) is taken as ONE draw from the runout
distribution of blocks of that size, seen with a measurement tolerance. The
simulated distribution is represented by samples r_1..r_n (the runouts of n
blocks of size d_i, or the K quantiles of an emulated distribution).

Point observation y_i with tolerance s_i (Gaussian kernel density of the
simulated runouts, the kernel being the measurement error):

    p(y_i | theta) = (1/n) sum_j N(y_i ; r_j(theta), s_i^2 + v_j),

Interval observation [a_i, b_i] (the runout was seen to lie in it):

    P_i(theta) = (1/n) sum_j [Phi((b_i - r_j)/w_j) - Phi((a_i - r_j)/w_j)],
    w_j^2 = h^2 + v_j,

with h a kernel width (Silverman's rule on the samples, at least 0.5 m) that
turns the empirical distribution into a smooth one, and v_j an extra variance
per sample (the emulator's predictive variance; 0 for raw simulations).

Both are mixed with a small defensive uniform component over [0, R_MAX]
(Hesterberg 1995, Technometrics 37, 185-194; the same device as the speeds'
model below), so that a row the model cannot produce at all costs a bounded
amount instead of hundreds of nats:

    p_i = (1 - eps) p_i^KDE + eps / R_MAX          (point rows),
    P_i = (1 - eps) P_i^KDE + eps (b_i - a_i) / R_MAX   (interval rows),

with eps = 1e-3 and R_MAX = 1000 m (longer than the runout of a single block on
any 2D profile this toolkit is meant for; our choice): a point row's log
density never falls below log(1e-6 / m) = -13.8. Why (measured 2026-11-25 on
the Tschamut seed-1 hold-out split of notebooks/04_tschamut.py): without it
three runs that stopped after 27-36 m,
which few simulated blocks of their groups reached, could cost tens to
hundreds of nats each (at phi_r 20 deg, 95 % of their groups' blocks stop
23-47 m beyond them; a 2 m kernel gives a block 23-47 m away a log weight of
about -70 to -270, against about -190 for all 43 rows at the fit's optimum). They
dominated the summed log-likelihood and pushed the rolling resistance to 36 deg, where the blocks
of other groups stalled at their release: held-out CRPS 12.7 m, skill -0.24.
With it: 10.6 m, skill -0.03 (+0.11 against the per-size climatology), and
the fit passes every check. A row that the model explains is changed by
log(1 - eps) = -0.001 nats.

Unfinished blocks (``calib.model.unfinished``) come as NaN samples and are left out:
the sums run over the n finished samples of the row, the kernel width comes
from them, and a row with no finished sample keeps only the defensive
component (the parameters produce no runout of that size at all).

Passage velocity v_i of a block of size d_i seen at station x_s (``calib.
observations.Velocities``): the kernel density of the simulated speeds of the
blocks of that size that passed x_s, i.e. the distribution CONDITIONAL on
passing (a speed is only recorded for blocks that got there), mixed with a
small defensive uniform component (Hesterberg 1995, Technometrics 37, 185-194)
so that a parameter set under which no simulated block reaches the station
gets a finite, very low density instead of minus infinity:

    p(v_i | theta) = (1 - eps) (1/m) sum_{j passed} N(v_i ; u_j, s_i^2 + h_v^2)
                     + eps / V_MAX,

with m the number of passing samples, h_v = 0.9 sd m^(-1/5) from the sd of
their speeds (Silverman's rule without its IQR branch, which would need a
percentile over a varying subset; at least 0.1 m/s), eps = 1e-3 and
V_MAX = 100 m/s (faster than any rockfall on record); with m = 0 only the
uniform term is left (log p = -11.5).

Assumptions: rows are independent given theta (distinct blocks); every
observed block is a random draw from the release conditions the solver uses;
the tolerance is Gaussian. With few rows per size the likelihood says where
the distribution must put mass, not its full shape.

This is the one observation model of the project (``docs/calibration.md``,
"Observation model"): ``calib.fit`` (``calib.inference.calibrate``) and ``calib.discover``
(``calib.discovery.discrepancy``) both score runout rows with ``log_likelihood`` on the
rows of ``observed_rows``, with v_j = 0 for simulated runouts (the kernel of a
point row is the tolerance alone, that of an interval row the width h alone)
and v_j the inflated emulator variance for emulated quantiles.

Tolerance rule (ours): a point row needs a finite tolerance s_i > 0, in the file
(``calib.files.observations.load_observations`` refuses the row otherwise) and in
observations built in memory (``observed_rows`` refuses them); no default is
filled in. An interval row has no tolerance: the interval is what was seen.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import log_ndtr, logsumexp

__all__ = ["RUNOUT_EPS", "R_MAX_M", "ObservedRows", "RowLikelihood", "VelocityRows",
           "log_likelihood", "observed_rows", "silverman_width_m", "velocity_log_likelihood",
           "velocity_rows_loglik"]

_LOG_2PI = 1.8378770664093453
RUNOUT_EPS = 1e-3  # weight of the runouts' defensive uniform component
R_MAX_M = 1000.0  # its upper end, m


class ObservedRows(NamedTuple):
    """Runout rows as ``log_likelihood`` takes them (``log_likelihood(samples, *rows)``).

    Attributes:
        y_m, sd_m: (n_obs,) point value and tolerance, m (0 and 1 on interval rows,
            where they are not used).
        lo_m, hi_m: (n_obs,) interval ends, m (0 on point rows, not used).
        is_interval: (n_obs,) bool.
    """

    y_m: jax.Array
    sd_m: jax.Array
    lo_m: jax.Array
    hi_m: jax.Array
    is_interval: jax.Array


def observed_rows(obs) -> ObservedRows:
    """The rows of ``obs`` (``calib.files.observations.Observations``) for ``log_likelihood``.

    Raises:
        ValueError: a point row without a finite tolerance > 0 (the tolerance
            rule of the module docstring), naming the file and line.
    """
    is_int = np.asarray(obs.is_interval, bool)
    sd = np.asarray(obs.runout_sd_m, float)
    bad = np.flatnonzero(~is_int & ~(np.isfinite(sd) & (sd > 0)))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{obs.path}: line {i + 2}, column 'runout_sd_m': a point "
                         f"observation needs a positive tolerance in metres, got {sd[i]:g}")
    y = np.where(is_int, 0.0, np.asarray(obs.runout_m, float))
    lo = np.where(is_int, np.asarray(obs.runout_min_m, float), 0.0)
    hi = np.where(is_int, np.asarray(obs.runout_max_m, float), 0.0)
    return ObservedRows(jnp.asarray(y), jnp.asarray(np.where(is_int, 1.0, sd)),
                        jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(is_int))


def silverman_width_m(samples: jax.Array, floor_m: float = 0.5) -> jax.Array:
    """Kernel width h = 0.9 min(sd, IQR/1.34) n^(-1/5) (Silverman 1986), >= floor_m,
    over the finite samples (n of them; ``floor_m`` where n < 2)."""
    n = jnp.isfinite(samples).sum(axis=-1)
    sd = jnp.nanstd(samples, axis=-1)
    q75, q25 = jnp.nanpercentile(samples, jnp.array([75.0, 25.0]), axis=-1)
    spread = jnp.minimum(sd, (q75 - q25) / 1.34)
    h = jnp.maximum(0.9 * spread * jnp.maximum(n, 1) ** (-0.2), floor_m)
    return jnp.where(n >= 2, h, floor_m)


def _log_diff_ndtr(hi: jax.Array, lo: jax.Array) -> jax.Array:
    """log(Phi(hi) - Phi(lo)) for hi >= lo, stable in both tails."""
    upper = lo > 0  # both in the upper tail: use symmetry Phi(x) = 1 - Phi(-x)
    a = jnp.where(upper, -lo, hi)
    b = jnp.where(upper, -hi, lo)
    la, lb = log_ndtr(a), log_ndtr(b)
    return la + jnp.log1p(-jnp.exp(jnp.minimum(lb - la, -1e-12)))


def log_likelihood(samples: jax.Array, y_m: jax.Array, sd_m: jax.Array, lo_m: jax.Array,
                   hi_m: jax.Array, is_interval: jax.Array,
                   extra_var_m2: jax.Array | float = 0.0) -> jax.Array:
    """Pointwise log-likelihood of observations given simulated runout samples.

    Args:
        samples: (n_obs, n) simulated runouts for each row's block size, m; NaN
            for an unfinished block (left out).
        y_m, sd_m: (n_obs,) point value and tolerance (ignored for intervals).
        lo_m, hi_m: (n_obs,) interval ends (ignored for points).
        is_interval: (n_obs,) bool.
        extra_var_m2: per-sample extra variance, broadcastable to ``samples``.

    Returns:
        (n_obs,) log p(y_i | theta) (points, a density in 1/m) or log P_i(theta)
        (intervals, a probability), following the module docstring.
    """
    ok = jnp.isfinite(samples)  # finished blocks (NaN: unfinished, left out)
    log_n = jnp.log(jnp.maximum(ok.sum(axis=-1), 1))
    h = silverman_width_m(samples)[:, None]
    r = jnp.where(ok, samples, 0.0)
    extra = jnp.broadcast_to(jnp.asarray(extra_var_m2, samples.dtype), samples.shape)
    # points: Gaussian kernel with the measurement tolerance
    y = jnp.where(is_interval, 0.0, y_m)[:, None]
    var = jnp.where(is_interval, 1.0, sd_m)[:, None] ** 2 + extra
    lp = -0.5 * ((y - r) ** 2 / var + jnp.log(var) + _LOG_2PI)
    point = logsumexp(jnp.where(ok, lp, -jnp.inf), axis=-1) - log_n
    # intervals: probability mass of the kernel-smoothed distribution
    w = jnp.sqrt(h**2 + extra)
    lo = jnp.where(is_interval, lo_m, 0.0)[:, None]
    hi = jnp.where(is_interval, hi_m, 1.0)[:, None]
    li = _log_diff_ndtr((hi - r) / w, (lo - r) / w)
    interval = logsumexp(jnp.where(ok, li, -jnp.inf), axis=-1) - log_n
    # the defensive uniform component (module docstring): density eps / R_MAX
    # for a point row, probability eps (b - a) / R_MAX for an interval row
    floor = jnp.log(RUNOUT_EPS / R_MAX_M) + jnp.where(
        is_interval, jnp.log(jnp.maximum(hi_m - lo_m, 1e-9)), 0.0)
    return jnp.logaddexp(jnp.log1p(-RUNOUT_EPS) + jnp.where(is_interval, interval, point),
                         floor)


log_likelihood_jit = jax.jit(log_likelihood)


@dataclasses.dataclass(frozen=True)
class VelocityRows:
    """Passage-velocity rows prepared for a fit (``calib.files.observations.Velocities``).

    Attributes:
        stations_m: (K,) distinct station abscissae, m (the solver records a
            passage speed at each: ``CrspForward.stations_x_m``).
        station: (n_v,) station index of each row.
        entry: (n_v,) the simulated entry whose blocks each row reads (a size
            class where the entries are the size classes).
        v_m_s, sd_m_s: (n_v,) observed speed and tolerance, m/s.
    """

    stations_m: np.ndarray
    station: np.ndarray
    entry: np.ndarray
    v_m_s: np.ndarray
    sd_m_s: np.ndarray

    @classmethod
    def of(cls, velocities, entry) -> VelocityRows:
        """The rows of ``velocities`` (``calib.files.observations.Velocities``),
        row i reading the blocks of simulated entry ``entry[i]``."""
        return cls(velocities.stations_m, velocities.station_index, np.asarray(entry),
                   velocities.velocity_m_s, velocities.velocity_sd_m_s)

    @property
    def n_obs(self) -> int:
        return int(self.v_m_s.shape[0])

    @property
    def stations_x_m(self) -> tuple[float, ...]:
        """The stations as a forward model records them (``CrspForward.stations_x_m``)."""
        return tuple(map(float, self.stations_m))


@jax.jit
def _velocity_rows_loglik(speeds, entry, station, v, sd):
    return jax.vmap(lambda u: velocity_log_likelihood(u[entry, station], v, sd))(speeds)


def velocity_rows_loglik(speeds_m_s, vel: VelocityRows) -> jax.Array:
    """(T, n_v) log-likelihood of every velocity row at each of T points, from the
    simulated passage speeds (T, E, K, n) (``CrspForward.simulate``; NaN where a
    block did not pass): row i against the speeds of its entry at its station."""
    return _velocity_rows_loglik(jnp.asarray(speeds_m_s), *(jnp.asarray(a) for a in (
        vel.entry, vel.station, vel.v_m_s, vel.sd_m_s)))


class RowLikelihood:
    """The rows of one fit scored against simulated runouts: row i reads the
    blocks of simulated entry ``index[i]`` (``log_likelihood`` of each row);
    with passage-velocity rows (``VelocityRows``), each also against the
    simulated passage speeds of its entry at its station
    (``velocity_log_likelihood``). The summed log-likelihood is over both.

    Built once per fit from the observations; every stage of
    ``calib.inference.calibrate`` scores its simulations through it
    (``simulate``: what a point's simulation must record for the rows).

    Attributes:
        rows: the runout rows as ``log_likelihood`` takes them (``observed_rows``).
        index: (n_runout,) int, the simulated entry of each runout row (default
            ``obs.size_index``: one entry per distinct size).
        velocities: the passage-velocity rows, or None.
        n_runout: the number of runout rows.
        n_rows: the number of rows scored: runout rows plus velocity rows.
        kernel_var_m2: the median over runout rows of the kernel variance one
            simulated sample gets: the tolerance sd^2 of a point row, the
            smallest kernel width h^2 (0.5 m) of an interval row, m^2.
        pointwise: runouts (T, S, n) -> (T, n_runout) pointwise log-likelihood
            of the runout rows (jitted).
    """

    def __init__(self, obs, index=None, velocities: VelocityRows | None = None):
        self.rows = observed_rows(obs)
        self.index = np.asarray(obs.size_index if index is None else index)
        self.velocities = velocities if velocities is not None and velocities.n_obs else None
        self.n_runout = int(obs.n_obs)
        self.n_rows = self.n_runout + (0 if self.velocities is None else self.velocities.n_obs)
        self.kernel_var_m2 = float(np.median(np.where(
            obs.is_interval, 0.5**2, np.nan_to_num(obs.runout_sd_m)**2)))
        rows, idx = self.rows, jnp.asarray(self.index)

        @jax.jit
        def pointwise(runouts):
            return jax.vmap(lambda r: log_likelihood(r[idx], *rows))(runouts)

        self.pointwise = pointwise

    @property
    def stations_m(self) -> tuple[float, ...]:
        """The abscissae at which the forward model must record passage speeds, m."""
        return () if self.velocities is None else self.velocities.stations_x_m

    def simulate(self, forward, theta) -> tuple[np.ndarray, np.ndarray | None]:
        """(runouts (T, S, n), passage speeds (T, S, K, n) or None without
        velocity rows) of ``forward`` at theta (T, d): what ``summed`` scores.
        The forward records the speeds at ``stations_m``."""
        if self.velocities is None:
            return forward.runouts(theta), None
        return forward.simulate(theta)

    def all_rows(self, runouts, speeds=None) -> np.ndarray:
        """(T, n_rows) pointwise log-likelihood: the runout rows, then the
        velocity rows (which need the passage ``speeds``)."""
        ll = np.asarray(self.pointwise(jnp.asarray(runouts)))
        if self.velocities is None:
            return ll
        if speeds is None:
            raise ValueError("the fit has passage-velocity rows: their speeds are needed")
        return np.concatenate([ll, np.asarray(velocity_rows_loglik(speeds, self.velocities))],
                              axis=1)

    def summed(self, runouts, speeds=None) -> np.ndarray:
        """(D,) summed log-likelihood of all rows at each of D points (runouts
        (D, S, n), speeds (D, S, K, n) with velocity rows); -inf where a runout
        row gets no finished block."""
        ll = self.all_rows(runouts, speeds).sum(1)
        return np.where(np.isnan(ll), -np.inf, ll)

    def noise_var(self, runouts: np.ndarray, speeds=None, *, n_boot: int = 16,
                  seed: int = 0) -> np.ndarray:
        """(D,) Monte Carlo variance of the summed log-likelihood at each of D
        points: bootstrap over each point's blocks (runouts (D, S, n), and
        the same blocks' speeds with velocity rows; Efron 1979); 0 where it is
        not finite."""
        rng = np.random.default_rng(seed)
        n = runouts.shape[-1]
        boot = []
        for _ in range(n_boot):
            pick = rng.integers(0, n, n)
            boot.append(self.all_rows(runouts[..., pick],
                                      None if speeds is None else speeds[..., pick]).sum(1))
        boot = np.stack(boot)
        var = np.var(np.where(np.isfinite(boot), boot, np.nan), axis=0)
        return np.where(np.isfinite(var), var, 0.0)

    def emulated(self, emu, emulator_inputs, inflation: float):
        """theta (d,) -> pointwise log-likelihood (n_runout,) of the runout rows
        from an emulator of the runout quantiles (``calib.inference.emulator``):
        each row's entry's predicted quantiles are its samples, with
        ``inflation`` times their predictive variance as the samples' extra
        variance v_j. Velocity rows are not emulated: they enter through the
        log-likelihood GP of the summed log-likelihood
        (``calib.inference.loglik_emulator``)."""
        idx = jnp.asarray(self.index)

        def f(theta):
            mean, var = emu.predict(emulator_inputs(theta))
            return log_likelihood(mean[idx], *self.rows, inflation * var[idx])

        return f


VELOCITY_EPS = 1e-3  # weight of the defensive uniform component
V_MAX_M_S = 100.0  # its upper end, m/s
H_V_FLOOR_M_S = 0.1  # smallest kernel width of the speeds, m/s


def velocity_log_likelihood(speeds_m_s: jax.Array, v_m_s: jax.Array,
                            sd_m_s: jax.Array) -> jax.Array:
    """Pointwise log-likelihood of observed passage speeds (module docstring).

    Args:
        speeds_m_s: (n_obs, n) simulated speeds at each row's station for blocks
            of the row's size; NaN where the simulated block did not pass.
        v_m_s, sd_m_s: (n_obs,) observed speed and its tolerance, m/s.

    Returns:
        (n_obs,) log p(v_i | theta), a density in s/m.
    """
    passed = jnp.isfinite(speeds_m_s)
    m = passed.sum(axis=-1)
    u = jnp.where(passed, speeds_m_s, 0.0)
    mean = u.sum(axis=-1) / jnp.maximum(m, 1)
    var = jnp.where(passed, (u - mean[:, None]) ** 2, 0.0).sum(axis=-1) / jnp.maximum(m - 1, 1)
    h = jnp.maximum(0.9 * jnp.sqrt(var) * jnp.maximum(m, 1) ** (-0.2), H_V_FLOOR_M_S)
    s2 = (sd_m_s**2 + h**2)[:, None]
    lp = -0.5 * ((v_m_s[:, None] - u) ** 2 / s2 + jnp.log(s2) + _LOG_2PI)
    kde = logsumexp(jnp.where(passed, lp, -jnp.inf), axis=-1) - jnp.log(jnp.maximum(m, 1))
    kde = jnp.where(m > 0, kde, -jnp.inf)
    return jnp.logaddexp(jnp.log1p(-VELOCITY_EPS) + kde, jnp.log(VELOCITY_EPS / V_MAX_M_S))
