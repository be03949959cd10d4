"""Can the model fit these data? Two checks a calibration reports about itself.

A posterior can pass every sampler diagnostic (R-hat, ESS, divergences) and
still describe a model that cannot reproduce what was observed: the likelihood
pushes the parameters against the edges of their prior box, and the rows the
model was calibrated on fall outside their own predictive bands. Both are
reported per fit (``calib.inference.calibrate``; ``calibration.json`` under
``"adequacy"``) and printed loudly by ``python -m calib.fit``.

1. **Mass at the prior bounds.** For each parameter, the fraction of posterior
   draws within ``BOUND_BAND`` (2 %) of the box width of its lower and of its
   upper bound. A uniform prior puts 2 % there; a posterior that puts more
   than ``BOUND_FLAG`` (10 %, five times the prior's) there says the data want
   a value outside the box: either the box is too narrow or the model lacks
   something, provided the posterior reaches the bound (``bound_mass``). The
   2 % band is the project's specification; the factor of five and the reach
   condition are our own choices.

2. **Posterior predictive coverage of the calibration rows.** Each row's
   predictive distribution is that of the OBSERVED value: the runout of a
   block of the row's size, simulated at posterior draws (fresh blocks, not the
   fit's common random numbers), plus the row's measurement error
   ``e ~ N(0, sd^2)`` for a point row (the observation model of
   ``calib.inference.likelihood``). A point row is covered at level p when its value
   lies inside the central p interval of that distribution; an interval row
   when its interval overlaps the central p interval of the runout. For a
   model that fits, about a fraction p of rows is covered, and rows used in
   the fit are, if anything, covered more often. So coverage is flagged when it
   is too LOW: when a one-sided binomial test of "covered with probability p"
   against "less often" rejects at 5 % (our own choice of test; with few rows
   nothing is flagged unless the miss is gross). Coverage above nominal is
   reported, not flagged.

3. **Blocks that stall at their release.** Per simulated entry (a size, or a
   (size, release) group), the fraction of the predictive's finished blocks
   that stop within ``STALL_M`` (1 m) of where they were released, against
   the fraction of the entry's observed rows that did. An entry is flagged when
   the simulated fraction exceeds the observed one by ``STALL_FLAG`` (0.5) or
   more: most simulated blocks never get going where the observed ones did.
   On a profile this happens where the blocks start slowly on ground flatter
   than the rolling resistance angle (e.g. hand-released blocks projected
   onto a shoulder of a mean fall line), and a posterior then splits into modes
   that do and do not let them start. Threshold and flag level are our own
   choice.

4. **A better point that the fit did not find.** The emulator's design
   simulates the rows at many points of the prior box (CRSP). Where one of
   those points fits the rows better than the calibration's estimate, by more
   than ``BETTER_NATS_PER_ROW`` (1 nat) per row and by more than half the
   99.9 % point of chi-square with as many degrees of freedom as parameters
   (a likelihood-ratio bar: 9.2 nats for 4 parameters) in simulated
   log-likelihood
   (the design's blocks against the check's; against the posterior's mode
   simulated with the design's own blocks), the fit missed a better region
   and does not describe the best fit found. Seen on a likelihood that is
   flat in most of the box and peaked in a thin slab of it (Tschamut: a
   roughness near 0.05 m). Thresholds our own choice: the second keeps a fit
   of few rows (Postignano's two) from being flagged for the ordinary
   distance between an emulated posterior's mode and the simulated best
   (measured there: 2.1 nats), the first scales the bar with the rows. The
   gradient fit starts once from that best design point too
   (``calib.inference.calibrate``).

5. **Rows that stall at their release.** Per calibration row, whether at
   least half of its predictive runouts end within 5 m of the release while
   the row's observed runout exceeds 20 m, with why: the slope below the
   release against the rolling-resistance angle of the draws (the fraction
   of draws with phi_r above the slope). A safety net, the rule and its
   thresholds shared with ``calib.validate``
   (``calib.inference.predictive_check.stalled_rows``): a release that sits
   a tracked block on ground flatter than phi_r, e.g. a tracked release that
   a raster put below its ground and that is taken as exact (no
   ``release_height_sd_m``), stalls every simulated block.

6. **The rolling threshold converged** (CRSP). The solver's rolling threshold
   (a landing or rebound slower than it, normal to the slope, rolls on,
   ``solvers.crsp.Params.rolling_threshold_m_s``) is a numerical cutoff; its
   value must not decide the runouts. At the point estimate, every simulated
   entry is run with the fit's threshold and with ``THRESHOLD_FACTOR`` (a
   tenth) of it, with the same blocks (common random numbers), and an entry
   is flagged when its runout distribution moves by more than
   ``THRESHOLD_SHIFT_M`` (5 m) and ``THRESHOLD_SHIFT_FRACTION`` (10 %) of
   its median, the move measured as the Wasserstein-1 distance between the
   two runout distributions, W1 = integral over u in (0, 1) of
   |F^-1(u) - G^-1(u)| (the mean distance between their quantiles). W1
   bounds what the cutoff can do to a prediction's score: a row's CRPS,
   E|X - y| - E|X - X'| / 2, changes by at most 2 W1 (each term is
   1-Lipschitz in W1). A single quantile is not the measure: where a few
   percent of an entry's blocks stall at the release (an atom at 0 m), its
   5 % quantile jumps between 0 m and the runouts of the others when one
   block in a hundred changes side, with W1 under a metre (measured at the
   Tschamut main job's seed-2 mode, docs/studies.md, "Divergences repaired
   with a smaller step"). The 5/50/95 % runouts are reported beside it. A
   tenth, not a half: at Tschamut the default's stalls survive a halving and
   vanish from about a tenth (docs/studies.md, "The rolling threshold"); the
   thresholds are our own choice. A flag names the site file's
   ``rolling_threshold_m_s`` (``calib.files.site``) as the fix.

Without a posterior (gradient-only fits) the predictive distribution is that
of the point estimate (plug-in), and the record says so.

``fit_adequacy`` makes the record of one fit (``calib.inference.calibrate``,
stage 4): it simulates the posterior predictive and the fit's points for
check 4, and hands them to ``adequacy_record``.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
from scipy.stats import binomtest, chi2

from calib.files.observations import Observations
from calib.inference.predictive_check import (
    in_band,
    observed_ensemble,
    pool_draws,
    stall_message,
    stalled_rows,
)
from calib.model.forward import CrspForward, release_rolling_deg, release_slopes_deg
from calib.model.priors import Box

__all__ = ["BETTER_NATS_PER_ROW", "BOUND_BAND", "BOUND_FLAG", "COVERAGE_ALPHA", "LEVELS",
           "REACH_BAND", "REACH_QUANTILE",
           "STALL_FLAG", "STALL_M", "adequacy_record", "better_design_point", "bound_mass",
           "fit_adequacy", "loglik_gap_nats", "predictive_coverage", "stalled_releases"]

BOUND_BAND = 0.02  # width of the band at each bound, as a fraction of the box width
BOUND_FLAG = 0.10  # posterior mass in that band above which a parameter is flagged
REACH_QUANTILE = 0.01  # ... when this quantile of the posterior on that side
REACH_BAND = 0.005  # lies within this fraction of the box width of the bound
COVERAGE_ALPHA = 0.05  # level of the one-sided binomial test of coverage
LEVELS = (0.5, 0.9)
STALL_M = 1.0  # a block that stops within this distance of its release stalled, m
STALL_FLAG = 0.5  # simulated minus observed stalled fraction above which an entry is flagged
BETTER_NATS_PER_ROW = 1.0  # a design point this much better per row is flagged (check 4)


def bound_mass(samples: np.ndarray, box: Box) -> dict:
    """Posterior mass near each prior bound, per parameter.

    A side is flagged when more than ``BOUND_FLAG`` of the draws lie within
    ``BOUND_BAND`` of the box width of the bound AND the posterior reaches the
    bound: its ``REACH_QUANTILE`` quantile on that side lies within
    ``REACH_BAND`` of the box width of it. The second condition is our own:
    a parameter whose box spans decades (roughness S, 0.01-4 m) can hold a
    posterior that is narrow and well inside the box (S 0.077-0.086 m on the
    Tschamut rows) yet inside the 2 % band (0.01-0.09 m); that posterior does
    not want a value outside the box.

    Args:
        samples: (n_draws, d) posterior draws.
        box: the prior box.

    Returns:
        {name: {"lower": fraction, "upper": fraction, "lower_flagged": bool,
        "upper_flagged": bool, "flagged": bool}}.
    """
    s = np.asarray(samples, float)
    width = box.hi - box.lo
    band, reach = BOUND_BAND * width, REACH_BAND * width
    q_lo, q_hi = np.quantile(s, [REACH_QUANTILE, 1 - REACH_QUANTILE], axis=0)
    out = {}
    for i, name in enumerate(box.names):
        lower = float(np.mean(s[:, i] <= box.lo[i] + band[i]))
        upper = float(np.mean(s[:, i] >= box.hi[i] - band[i]))
        lo_flag = bool(lower > BOUND_FLAG and q_lo[i] <= box.lo[i] + reach[i])
        hi_flag = bool(upper > BOUND_FLAG and q_hi[i] >= box.hi[i] - reach[i])
        out[name] = {"lower": lower, "upper": upper, "lower_flagged": lo_flag,
                     "upper_flagged": hi_flag, "flagged": lo_flag or hi_flag}
    return out


def predictive_coverage(obs: Observations, runouts: np.ndarray, key_seed: int = 0,
                        index=None) -> dict:
    """Posterior predictive coverage of the rows at the 50 and 90 % levels.

    Args:
        obs: the calibration rows.
        runouts: (S, n) simulated runouts per entry (a distinct size,
            ``obs.sizes_m``, or a (size, release) group), pooled over the
            posterior draws, m; NaN for unfinished blocks.
        key_seed: seed of the measurement-error draws (NumPy generator).
        index: (n_obs,) entry of each row (default ``obs.size_index``).

    Returns:
        {"levels": {"0.5": {...}, "0.9": {...}}, "rows": [...]}: per level the
        number of rows, the number covered, the fraction, the one-sided binomial
        test's p-value and ``flagged`` (too few covered); per row whether each
        band covers it (None for a row whose size has no finished block, left
        out of the counts).
    """
    rng = np.random.default_rng(key_seed)
    index = obs.size_index if index is None else np.asarray(index)
    rows, covered = [], {p: [] for p in LEVELS}
    for i in range(obs.n_obs):
        ens = observed_ensemble(obs, i, runouts[index[i]], rng)
        row = {"row": i + 1, "block_size_m": float(obs.block_size_m[i])}
        for p in LEVELS:
            inside = in_band(obs, i, ens, p) if ens.size else None
            row[f"in_{round(100 * p)}"] = inside
            if inside is not None:
                covered[p].append(inside)
        rows.append(row)
    levels = {}
    for p in LEVELS:
        n, k = len(covered[p]), int(np.sum(covered[p]))
        pval = float(binomtest(k, n, p, alternative="less").pvalue) if n else None
        levels[f"{p:g}"] = {"n_rows": n, "n_covered": k, "fraction": k / n if n else None,
                            "p_value": pval,
                            "flagged": bool(pval is not None and pval < COVERAGE_ALPHA)}
    return {"levels": levels, "rows": rows}


def stalled_releases(obs: Observations, runouts: np.ndarray, index=None,
                     release_x_m=None, release_slope_deg=None) -> dict:
    """Entries whose simulated blocks stall at their release (module docstring, 3).

    Args:
        obs: the calibration rows.
        runouts: (S, n) predictive runouts per entry, m; NaN for unfinished blocks.
        index: (n_obs,) entry of each row (default ``obs.size_index``).
        release_x_m, release_slope_deg: (S,) each entry's release abscissa, m,
            and the profile's slope just below it, deg, for the report (optional).

    Returns:
        {"stall_m", "flag_fraction", "entries": [per entry with rows: size,
        release, slope, simulated and observed stalled fractions, rows, flagged],
        "flagged": [the flagged ones]}.
    """
    index = obs.size_index if index is None else np.asarray(index)
    lo = np.where(obs.is_interval, obs.runout_min_m, obs.runout_m)
    entries = []
    for e in np.unique(index):
        r = np.asarray(runouts[e], float)
        r = r[np.isfinite(r)]
        rows = np.flatnonzero(index == e)
        sim = float(np.mean(r < STALL_M)) if r.size else None
        seen = float(np.mean(lo[rows] < STALL_M))
        entries.append({
            "entry": int(e), "block_size_m": float(obs.block_size_m[rows[0]]),
            "release_x_m": None if release_x_m is None else float(release_x_m[e]),
            "release_slope_deg": (None if release_slope_deg is None
                                  else float(release_slope_deg[e])),
            "simulated_stalled": sim, "observed_stalled": seen,
            "rows": [int(i) + 1 for i in rows],
            "flagged": bool(sim is not None and sim - seen >= STALL_FLAG)})
    return {"stall_m": STALL_M, "flag_fraction": STALL_FLAG, "entries": entries,
            "flagged": [x for x in entries if x["flagged"]]}


def _remedy(bound_flagged: bool) -> str:
    """What a user can do about the problems found. Where posterior mass piles on a
    bound of a box set from published ranges before fitting (``calib.model.priors``),
    widening the box only moves the cut: the remedy is a source for another range, a
    measurement that separates the parameters the runouts leave free together (passage
    speeds, ``calib.fit --velocities``), or the physics the model misses."""
    if not bound_flagged:
        return "Add the missing physics or check the data before using this calibration"
    return ("The prior boxes are set before fitting (their sources and assumptions: "
            "calib/model/priors.py), and widening one until the mass leaves its bound only "
            "moves the cut: a measurement that separates the parameters (passage speeds, "
            "calib.fit --velocities), a source for another range, the missing physics or a "
            "check of the data is what settles it, before this calibration is used")


def _stall_problem(stalls: dict) -> str | None:
    bad = stalls["flagged"]
    if not bad:
        return None
    where = "; ".join(
        f"{x['block_size_m']:g} m blocks"
        + ("" if x["release_x_m"] is None else f" released at x = {x['release_x_m']:.1f} m")
        + ("" if x["release_slope_deg"] is None else
           f" (slope below it {x['release_slope_deg']:.0f} deg)")
        + f": {x['simulated_stalled']:.0%} of the simulated blocks stop within "
          f"{stalls['stall_m']:g} m, {x['observed_stalled']:.0%} of its "
          f"{len(x['rows'])} rows did" for x in bad[:4])
    more = f" and {len(bad) - 4} more entries" if len(bad) > 4 else ""
    return (f"simulated blocks stall at their release where the observed ones did not "
            f"({where}{more}); check the profile's slope at these releases against the "
            f"rolling resistance angle, and how the blocks were released (release_x_m, "
            f"release_speed_m_s, release_height_m)")


def loglik_gap_nats(n_rows: int, n_params: int) -> float:
    """The gap in summed simulated log-likelihood beyond which one parameter point
    fits the rows worse than another, not merely differently: more than
    ``BETTER_NATS_PER_ROW`` per row and more than half the 99.9 % point of
    chi-square with one degree of freedom per parameter (a likelihood-ratio bar;
    9.2 nats for 4 parameters). Our choice; used by check 4 and by the chain
    screening of ``calib.inference.calibrate``."""
    return max(BETTER_NATS_PER_ROW * n_rows, 0.5 * float(chi2.ppf(0.999, n_params)))


def better_design_point(names, design_theta: np.ndarray, design_loglik: np.ndarray,
                        fitted_loglik: dict[str, float], n_rows: int) -> dict:
    """Check 4 of the module docstring: the design point with the highest
    simulated log-likelihood against the fit's own points.

    Args:
        names: parameter names.
        design_theta: (D, p) design points; design_loglik: (D,) their summed
            simulated log-likelihoods of the rows (-inf or NaN: none).
        fitted_loglik: the summed simulated log-likelihood of each of the fit's
            points by name (e.g. "estimate", "posterior mode").
        n_rows: number of calibration rows.
    """
    ll = np.where(np.isfinite(design_loglik), design_loglik, -np.inf)
    best = int(np.argmax(ll))
    finite = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731  (JSON)
    bar = loglik_gap_nats(n_rows, len(names))
    points = {}
    for name, v in fitted_loglik.items():
        gain = ll[best] - v
        points[name] = {"loglik": finite(v), "gain_nats": finite(gain),
                        "gain_per_row_nats": finite(gain / max(n_rows, 1)),
                        "flagged": bool(np.isfinite(gain) and gain > bar)}
    return {"theta": {n: float(v) for n, v in zip(names, design_theta[best], strict=True)},
            "loglik": finite(ll[best]), "threshold_nats": bar, "points": points,
            "flagged": any(p["flagged"] for p in points.values())}


def _better_problem(better: dict | None) -> str | None:
    if not better or not better["flagged"]:
        return None
    at = ", ".join(f"{n} {v:.3g}" for n, v in better["theta"].items())
    than = " and ".join(f"the {name} ({p['loglik']:.0f}) by {p['gain_nats']:.0f} nats, "
                        f"{p['gain_per_row_nats']:.1f} per row"
                        for name, p in better["points"].items() if p["flagged"])
    return (f"a point of the design ({at}, simulated log-likelihood {better['loglik']:.0f}) "
            f"fits the rows better than {than}: the fit missed a better region and does "
            "not describe the best fit found")


THRESHOLD_FACTOR = 0.1
THRESHOLD_SHIFT_M = 5.0
THRESHOLD_SHIFT_FRACTION = 0.1


def threshold_convergence(forward, estimate: np.ndarray,
                          factor: float = THRESHOLD_FACTOR) -> dict:
    """Check 6 (module docstring): each simulated entry's 5/50/95 % runouts at
    ``estimate`` with the forward model's rolling threshold and with ``factor``
    times it, the same blocks.

    Args:
        forward: a ``CrspForward`` (its entries, blocks and key).
        estimate: (d,) the parameter set.

    Returns:
        dict with ``threshold_m_s``, ``compared_m_s``, ``n_blocks``,
        ``entries`` (per entry: ``release_x_m``, ``size_m``, ``quantiles_m``
        and ``quantiles_compared_m`` (5/50/95 %), ``shift_m`` (the
        Wasserstein-1 distance between the two runout distributions, m),
        ``flagged``), and ``n_flagged``.
    """
    theta = np.atleast_2d(np.asarray(estimate, float))
    lower = dataclasses.replace(forward, rolling_threshold_m_s=factor
                                * forward.rolling_threshold_m_s)
    runs = [np.asarray(fw.runouts(theta)[0]) for fw in (forward, lower)]  # (S, B) each
    at, low = (np.nanquantile(r, (0.05, 0.5, 0.95), axis=-1).T for r in runs)
    # W1 as the mean distance between the quantile functions on a grid of the
    # blocks' own resolution (unfinished blocks, NaN, left out of each side)
    n = runs[0].shape[-1]
    u = (np.arange(n) + 0.5) / n
    q_at, q_low = (np.nanquantile(r, u, axis=-1) for r in runs)  # (n, S)
    shift = np.mean(np.abs(q_low - q_at), axis=0)
    flagged = (shift > THRESHOLD_SHIFT_M) & (shift > THRESHOLD_SHIFT_FRACTION * np.abs(at[:, 1]))
    e = forward.entries
    entries = [{"release_x_m": float(e.release_x_m[i]), "size_m": float(e.sizes_m[i]),
                "quantiles_m": [round(float(v), 2) for v in at[i]],
                "quantiles_compared_m": [round(float(v), 2) for v in low[i]],
                "shift_m": round(float(shift[i]), 2), "flagged": bool(flagged[i])}
               for i in range(at.shape[0])]
    return {"threshold_m_s": float(forward.rolling_threshold_m_s),
            "compared_m_s": float(lower.rolling_threshold_m_s),
            "n_blocks": int(forward.n_blocks), "entries": entries,
            "n_flagged": int(flagged.sum())}


def _threshold_problem(record: dict | None) -> str | None:
    """The flag of check 6, naming the entry that moves most and the fix."""
    if not record or not record["n_flagged"]:
        return None
    worst = max((x for x in record["entries"] if x["flagged"]), key=lambda x: x["shift_m"])
    q, q2 = ("/".join(str(round(v)) for v in worst[k])  # round: no "-0"
             for k in ("quantiles_m", "quantiles_compared_m"))
    return (f"CRSP's rolling threshold ({record['threshold_m_s']:g} m/s) is not converged at "
            f"the estimate: at {record['compared_m_s']:g} m/s the runout distributions of "
            f"{record['n_flagged']} of {len(record['entries'])} simulated releases move by more "
            f"than {THRESHOLD_SHIFT_M:g} m and {THRESHOLD_SHIFT_FRACTION:.0%} of their median "
            f"(Wasserstein-1 distance; most: {worst['shift_m']:.1f} m for "
            f"{worst['size_m']:.2f} m blocks released at x = {worst['release_x_m']:.1f} m, "
            f"5/50/95 % runouts {q} m against {q2} m); state the value the site's runouts "
            "converge at in its site file (rolling_threshold_m_s, measured with "
            "scripts/loglik_noise.py --rolling-threshold-m-s ... --entries)")


def fit_adequacy(forward, obs: Observations, rows, posterior, estimate: np.ndarray,
                 at_rows: np.ndarray, design: tuple | None, budget, key: jax.Array,
                 tally, mode_loglik: float | None = None) -> dict:
    """The adequacy record of one fit (``adequacy_record``).

    Its predictive: runouts at ``n_predictive_draws`` posterior draws spread
    evenly over the chains' output, with ``n_blocks_predictive`` fresh blocks
    per draw and entry; without a posterior, the check's runouts ``at_rows``
    at the point estimate (plug-in). CRSP: with the rolling resistance angle
    at each release of every draw (or of the estimate), for the rows that
    stall at their release (check 5). With a design, check 4 scores the
    estimate (the check's blocks; with passage-velocity rows, whose speeds the
    check does not record, the design's) and the posterior's mode (the
    design's own blocks) against the design's best point.

    Args:
        forward: the fit's forward model (``calib.model.forward``).
        obs: the calibration rows.
        rows: their likelihood (``calib.inference.likelihood.RowLikelihood``).
        posterior: ``calib.inference.bayes.Posterior`` or None.
        estimate: (d,) the point estimate.
        at_rows: (G, n) the check's runouts at the estimate per entry of the rows.
        design: (theta (D, d), summed simulated log-likelihoods (D,)) of a
            theta-space design (CRSP), or None.
        budget: ``calib.inference.budget.Budget``.
        key: PRNG key of the predictive's blocks.
        tally: records unfinished blocks per stage.
        mode_loglik: the posterior mode's summed simulated log-likelihood on
            the design's own blocks where the caller has it
            (``calibrate.point_estimate``); None: simulated here.
    """
    better = None
    if design is not None:
        if rows.velocities is None:
            fitted = {"estimate": float(rows.summed(at_rows[None])[0])}
        else:  # the check records no passage speeds: the design's own blocks
            fitted = {"estimate": float(rows.summed(*rows.simulate(forward, estimate[None]))[0])}
        if posterior is not None:  # its mode with the design's own blocks
            if mode_loglik is not None:
                fitted["posterior mode"] = float(mode_loglik)
            elif rows.velocities is not None and np.array_equal(estimate, posterior.map):
                fitted["posterior mode"] = fitted["estimate"]  # that point, those blocks
            else:
                fitted["posterior mode"] = float(rows.summed(
                    *rows.simulate(forward, posterior.map[None]))[0])
        better = better_design_point(forward.box.names, *design, fitted, rows.n_rows)
    release = forward.entries.release_x_m
    slopes_deg = release_slopes_deg(forward.profile, release, forward.entries.profiles)

    def rolling(theta):
        if not isinstance(forward, CrspForward) or theta is None:
            return None
        return release_rolling_deg(forward.box.names, theta, forward.profile, forward.entries)

    if posterior is None:
        samples, runouts, theta = None, at_rows, np.atleast_2d(estimate)
        source = (f"plug-in at the point estimate, {at_rows.shape[-1]} blocks per size "
                  "(no posterior)")
    else:
        n = posterior.samples.shape[0]
        pick = np.linspace(0, n - 1, min(budget.n_predictive_draws, n)).round().astype(int)
        samples, theta = posterior.samples, posterior.samples[pick]
        pred = dataclasses.replace(forward, n_blocks=budget.n_blocks_predictive, key=key)
        runs = pred.runouts(theta)  # (T, S, n)
        tally("predictive", runs, theta)
        runouts = pool_draws(runs)
        source = (f"posterior predictive, {len(pick)} draws x {budget.n_blocks_predictive} "
                  "blocks per size")
    threshold = (threshold_convergence(forward, estimate)
                 if isinstance(forward, CrspForward) else None)
    return adequacy_record(samples, forward.box, obs, runouts, source, rows.index, release,
                           slopes_deg, better, rolling(theta), threshold)

def adequacy_record(samples: np.ndarray | None, box: Box, obs: Observations,
                    runouts: np.ndarray, source: str, index=None, release_x_m=None,
                    release_slope_deg=None, better: dict | None = None,
                    release_rolling_deg=None, threshold: dict | None = None) -> dict:
    """The checks and one message (None when nothing is flagged).

    Args:
        samples: (n_draws, d) posterior draws, or None (no bound check).
        box: the prior box.
        obs: the calibration rows.
        runouts: (S, n) predictive runouts per entry, m.
        source: how ``runouts`` were made (e.g. "posterior predictive, 32 draws x
            64 blocks per size").
        index: (n_obs,) entry of each row in ``runouts`` (default ``obs.size_index``).
        release_x_m, release_slope_deg: (S,) each entry's release and the slope
            below it, for the stall report (``stalled_releases``; optional).
        better: the ``better_design_point`` record, or None (no design).
        release_rolling_deg: (S, T) the rolling-resistance angle at each
            entry's release in each draw (CRSP; None: unknown), for the rows
            that stall at their release (check 5, ``stalled_rows``).
        threshold: the ``threshold_convergence`` record (check 6; CRSP), or None.
    """
    bounds = None if samples is None else bound_mass(samples, box)
    stalls = stalled_releases(obs, runouts, index, release_x_m, release_slope_deg)
    cov = predictive_coverage(obs, runouts, index=index)
    stalled = stalled_rows(obs, runouts, index, release_x_m, release_slope_deg,
                           release_rolling_deg)
    problems = []
    for name, b in (bounds or {}).items():
        if b["flagged"]:
            side, m = max((("lower", b["lower"]), ("upper", b["upper"])),
                          key=lambda t: (b[f"{t[0]}_flagged"], t[1]))
            edge = box.lo[box.names.index(name)] if side == "lower" else \
                box.hi[box.names.index(name)]
            problems.append(f"{m:.0%} of the posterior of {name} lies within "
                            f"{BOUND_BAND:.0%} of its {side} prior bound {edge:g}")
    for p, c in cov["levels"].items():
        if c["flagged"]:
            problems.append(f"only {c['n_covered']} of {c['n_rows']} calibration rows lie "
                            f"inside their {float(p):.0%} predictive band (one-sided binomial "
                            f"p = {c['p_value']:.2g})")
    for extra in (_stall_problem(stalls), stall_message(stalled), _better_problem(better),
                  _threshold_problem(threshold)):
        if extra:
            problems.append(extra)
    message = None
    if problems:
        message = ("the model may not be able to fit these data: " + "; ".join(problems)
                   + ". " + _remedy(any(b["flagged"] for b in (bounds or {}).values())))
    return {"bound_band_fraction": BOUND_BAND, "bound_flag_fraction": BOUND_FLAG,
            "bounds": bounds, "coverage": cov, "stalls": stalls, "stalled_rows": stalled,
            "predictive": source,
            "better_design_point": better, "rolling_threshold": threshold,
            "ok": not problems,
            "problems": problems, "message": message}
