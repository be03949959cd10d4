"""Predictive check: does a calibration predict runouts it was not fitted to?

For each held-out row (a block of size d released at ``release_x_m``, seen at
runout y with tolerance s) the calibration's posterior predictive distribution
of the OBSERVED value is simulated: the runouts R of fresh blocks of that size
released there, at ``n_posterior`` posterior draws (``calib.files.calibration_file.
draw_parameters``), plus the measurement error e ~ N(0, s^2) of the
observation model (``calib.inference.likelihood``): Y = R + e, an ensemble of
``n_posterior x n_blocks`` members. Scores per point row:

* CRPS(F, y) = E|Y - y| - E|Y - Y'| / 2 (Gneiting & Raftery 2007, JASA 102,
  359-378), of the ensemble's empirical distribution, in metres
  (``scoringrules.crps_ensemble``, quantile-decomposition estimator, exact for
  that distribution; lower is better; it is the mean absolute error for a
  point forecast);
* PIT = P(Y <= y) (uniform on [0, 1] for a calibrated forecast; Dawid 1984);
* whether the central 50 % and 90 % predictive intervals contain y;
* the error of the predictive mean, E[Y] - y (positive: overshoot).

Baseline (climatology): the empirical distribution of the runouts observed in
the CALIBRATION rows, (a) all of them and (b) those of the held-out row's block
size (rows whose size is within 1 % of it; where fewer than
``MIN_ROWS_PER_SIZE`` such rows exist, (b) falls back to (a) and the row says
so). Its CRPS is computed the same way. Skill against a baseline:
``1 - mean CRPS / mean CRPS_baseline`` (1: perfect, 0: no better than quoting
the observed distribution, < 0: worse).

A row whose ensemble holds 1 to 19 finished blocks (``n_predictive``) has
``few_blocks`` set: its quantiles and bands rest on too few blocks
(``solvers.percentiles.few_blocks``); the summary lists those rows
(``few_blocks_rows``: [row, n_predictive] pairs).

Interval rows (runout seen to lie in [a, b]) have no CRPS here; they are
reported with their coverage only (an interval is inside a band when it
overlaps it) and left out of the averages of the scores.

Rows that stall at their release (``stalled_rows``; a safety net, shared with
the fit's adequacy check, ``calib.inference.adequacy``): a row is flagged
when at least ``STALL_MASS`` (half) of its predictive runouts end within
``STALL_NEAR_M`` (5 m) of the release while its observed runout exceeds
``STALL_OBSERVED_M`` (20 m). The record says why, where it can: the slope
just below the release against CRSP's rolling-resistance angle phi_r of the
draws (the fraction of draws with phi_r above the slope, where a block on
the ground that starts slowly cannot get going, ``solvers.crsp._contact``).
Thresholds our own choice: 5 m is a few block sizes and well below any
runout a tracked run calls a run; 20 m is the shortest runout that is
clearly one.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import scoringrules as sr

from calib.files.observations import Observations
from solvers.percentiles import few_blocks

__all__ = ["MIN_ROWS_PER_SIZE", "STALL_MASS", "STALL_NEAR_M", "STALL_OBSERVED_M",
           "PredictiveCheck", "heldout_entries", "in_band", "observed_ensemble", "pool_draws",
           "predictive_runouts", "score_rows", "stall_message", "stalled_rows"]

MIN_ROWS_PER_SIZE = 3  # fewest calibration rows of one size for a per-size baseline
STALL_NEAR_M = 5.0  # a predictive runout within this distance of the release stalled, m
STALL_OBSERVED_M = 20.0  # ... flagged where the observed runout exceeds this, m
STALL_MASS = 0.5  # ... and at least this fraction of the predictive stalled


def pool_draws(runouts: np.ndarray) -> np.ndarray:
    """Runouts (T draws, S groups, n blocks) -> (S, T n): each group's predictive
    sample pooled over the posterior draws."""
    return np.moveaxis(runouts, 0, 1).reshape(runouts.shape[1], -1)


def observed_ensemble(obs: Observations, i: int, runouts: np.ndarray,
                      rng: np.random.Generator) -> np.ndarray:
    """Predictive ensemble of row i's OBSERVED value from its group's simulated
    runouts (NaN: unfinished, left out): R + e, e ~ N(0, sd^2), for a point row
    (the observation model of ``calib.inference.likelihood``); R itself for an interval row."""
    r = np.asarray(runouts, float)
    r = r[np.isfinite(r)]
    if obs.is_interval[i] or r.size == 0:
        return r
    return r + float(obs.runout_sd_m[i]) * rng.standard_normal(r.size)


def in_band(obs: Observations, i: int, ensemble: np.ndarray, p: float) -> bool:
    """Whether the central p interval of ``ensemble`` (``observed_ensemble``)
    covers row i: contains its value (point row) or overlaps its interval."""
    lo, hi = np.quantile(ensemble, [0.5 - p / 2, 0.5 + p / 2])
    if obs.is_interval[i]:
        return bool(obs.runout_min_m[i] <= hi and obs.runout_max_m[i] >= lo)
    return bool(lo <= obs.runout_m[i] <= hi)


def _baseline(calib_obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """Observed runouts and sizes of the calibration's point rows."""
    point = ~np.asarray(calib_obs.is_interval)
    return np.asarray(calib_obs.runout_m)[point], np.asarray(calib_obs.block_size_m)[point]


@dataclasses.dataclass
class PredictiveCheck:
    """Scores of one predictive check.

    Attributes:
        rows: one row per held-out observation (pandas DataFrame; columns in
            ``score_rows``).
        summary: averages and counts (plain Python numbers).
    """

    rows: pd.DataFrame
    summary: dict


def score_rows(obs: Observations, predictive: np.ndarray, group_index: np.ndarray,
               calib_obs: Observations, seed: int = 0) -> PredictiveCheck:
    """Score held-out rows against their predictive runouts and the baselines.

    Args:
        obs: held-out rows.
        predictive: (G, m) simulated runouts of each (size, release) group,
            pooled over the posterior draws, m; NaN for unfinished blocks.
        group_index: (n_obs,) group of each row.
        calib_obs: the calibration rows (the climatology baselines).
        seed: seed of the measurement-error draws.

    Returns:
        ``PredictiveCheck``.
    """
    rng = np.random.default_rng(seed)
    clim_all, clim_sizes = _baseline(calib_obs)
    if clim_all.size < 2:
        raise ValueError("the calibration data have fewer than 2 point rows: no climatology "
                         "baseline can be formed")
    out = [_row_score(obs, i, observed_ensemble(obs, i, predictive[group_index[i]], rng),
                      clim_all, clim_sizes)
           for i in range(obs.n_obs)]
    rows = pd.DataFrame(out)
    return PredictiveCheck(rows, _summary(obs, rows))


def _row_score(obs: Observations, i: int, ens: np.ndarray, clim_all: np.ndarray,
               clim_sizes: np.ndarray) -> dict:
    """One held-out row's record: its observation, its predictive ensemble
    ``ens`` (with measurement error) and, for a point row with an ensemble, the
    predictive quantiles, PIT, band hits and the CRPS of the prediction and of the
    climatology baselines (all rows, and the rows of its size where there are
    ``MIN_ROWS_PER_SIZE``). An interval row gets band hits only."""
    d = float(obs.block_size_m[i])
    same = np.abs(clim_sizes - d) <= 0.01 * d
    per_size = clim_all[same] if same.sum() >= MIN_ROWS_PER_SIZE else clim_all
    row = {"row": i + 1, "block_size_m": d, "n_predictive": int(ens.size),
           "few_blocks": bool(ens.size and few_blocks(ens.size)),
           "baseline_size": "size" if same.sum() >= MIN_ROWS_PER_SIZE else "overall"}
    if obs.is_interval[i]:
        a, b = float(obs.runout_min_m[i]), float(obs.runout_max_m[i])
        row.update(observed_min_m=a, observed_max_m=b)
        if ens.size:
            row.update(in_50=in_band(obs, i, ens, 0.5), in_90=in_band(obs, i, ens, 0.9))
        return row
    y, s = float(obs.runout_m[i]), float(obs.runout_sd_m[i])
    row.update(observed_m=y, observed_sd_m=s)
    if ens.size == 0:  # no simulated block of this group finished
        return row
    q = np.quantile(ens, [0.05, 0.25, 0.5, 0.75, 0.95])
    row.update(
        pred_q05_m=q[0], pred_q25_m=q[1], pred_median_m=q[2], pred_q75_m=q[3],
        pred_q95_m=q[4], pred_mean_m=float(ens.mean()),
        error_of_mean_m=float(ens.mean() - y),
        pit=float(np.mean(ens <= y)),
        in_50=in_band(obs, i, ens, 0.5), in_90=in_band(obs, i, ens, 0.9),
        crps_m=float(sr.crps_ensemble(y, ens, estimator="qd")),
        crps_climatology_m=float(sr.crps_ensemble(y, clim_all, estimator="qd")),
        crps_climatology_size_m=float(sr.crps_ensemble(y, per_size, estimator="qd")))
    return row


def _summary(obs: Observations, rows: pd.DataFrame) -> dict:
    """The summary of ``score_rows`` over the scored point rows (those with a
    CRPS): mean CRPS of the prediction and the baselines, errors of the mean,
    50 % and 90 % coverage, rows outside the 90 % band, rows with few blocks,
    and the skill against each climatology (None where nothing was scored)."""
    scored = rows[rows.get("crps_m", pd.Series(dtype=float)).notna()] if "crps_m" in rows \
        else rows.iloc[0:0]
    n = len(scored)

    def mean(col):
        return float(scored[col].mean()) if n else None

    summary = {
        "n_rows": int(obs.n_obs), "n_scored": n,
        "n_interval_rows": int(np.sum(obs.is_interval)),
        "n_without_prediction": int(obs.n_obs - np.sum(obs.is_interval) - n),
        "mean_crps_m": mean("crps_m"),
        "mean_crps_climatology_m": mean("crps_climatology_m"),
        "mean_crps_climatology_size_m": mean("crps_climatology_size_m"),
        "mean_error_of_mean_m": mean("error_of_mean_m"),
        "mean_abs_error_of_mean_m": float(scored["error_of_mean_m"].abs().mean()) if n else None,
        "coverage_50": float(scored["in_50"].mean()) if n else None,
        "coverage_90": float(scored["in_90"].mean()) if n else None,
        "n_above_90": int((scored["pit"] > 0.95).sum()) if n else 0,
        "n_below_90": int((scored["pit"] < 0.05).sum()) if n else 0,
        "few_blocks_rows": [[int(r), int(k)] for r, k, f in
                            zip(rows["row"], rows["n_predictive"], rows["few_blocks"]) if f],
    }
    for name, ref in (("skill_vs_climatology", "mean_crps_climatology_m"),
                      ("skill_vs_climatology_size", "mean_crps_climatology_size_m")):
        summary[name] = (1.0 - summary["mean_crps_m"] / summary[ref]
                         if n and summary[ref] > 0 else None)
    return summary


def stalled_rows(obs: Observations, runouts: np.ndarray, index=None, release_x_m=None,
                 release_slope_deg=None, rolling_deg=None) -> dict:
    """Rows whose predictive distribution stalls at the release though the
    observed block ran on (module docstring).

    Args:
        obs: the rows.
        runouts: (S, n) predictive runouts per entry, pooled over the draws, m;
            NaN for unfinished blocks.
        index: (n_obs,) entry of each row (default ``obs.size_index``).
        release_x_m, release_slope_deg: (S,) each entry's release abscissa, m,
            and the slope just below it, deg (optional, for the record).
        rolling_deg: (S, T) CRSP's rolling-resistance angle at each entry's
            release in each of the T draws, deg
            (``calib.model.forward.release_rolling_deg``), or None (DEM, or
            unknown).

    Returns:
        {"near_m", "observed_beyond_m", "mass", "rows": [per flagged row: row
        (1-based), run_id, entry, release_x_m, release_slope_deg,
        fraction_within (of the finished predictive runouts), n_predictive,
        observed_m (an interval row's lower bound), rolling_deg_median and
        rolling_above_slope (the fraction of draws with phi_r above the
        slope; None where unknown)]}.
    """
    index = obs.size_index if index is None else np.asarray(index)
    observed = np.where(obs.is_interval, obs.runout_min_m, obs.runout_m)
    run_id = getattr(obs, "run_id", None)
    flagged = []
    for i in range(obs.n_obs):
        e = int(index[i])
        r = np.asarray(runouts[e], float)
        r = r[np.isfinite(r)]
        if not r.size or not observed[i] > STALL_OBSERVED_M:
            continue
        within = float(np.mean(np.abs(r) < STALL_NEAR_M))
        if within < STALL_MASS:
            continue
        slope = None if release_slope_deg is None else float(release_slope_deg[e])
        phi = None if rolling_deg is None else np.asarray(rolling_deg[e], float)
        flagged.append({
            "row": i + 1, "run_id": (str(run_id[i]) or None) if run_id is not None else None,
            "entry": e, "release_x_m": None if release_x_m is None else float(release_x_m[e]),
            "release_slope_deg": slope, "fraction_within": within, "n_predictive": int(r.size),
            "observed_m": float(observed[i]),
            "rolling_deg_median": None if phi is None else float(np.median(phi)),
            "rolling_above_slope": (None if phi is None or slope is None
                                    else float(np.mean(phi > slope)))})
    return {"near_m": STALL_NEAR_M, "observed_beyond_m": STALL_OBSERVED_M,
            "mass": STALL_MASS, "rows": flagged}


def stall_message(stalls: dict) -> str | None:
    """One sentence on the rows of ``stalled_rows`` and why they stall (None: none)."""
    rows = stalls["rows"]
    if not rows:
        return None

    def one(x):
        name = f"row {x['row']}" + (f" (run {x['run_id']})" if x["run_id"] else "")
        why = ""
        if x["release_slope_deg"] is not None:
            why = f"; slope below its release {x['release_slope_deg']:.0f} deg"
            if x["rolling_above_slope"] is not None:
                why += (f", phi_r above it in {x['rolling_above_slope']:.0%} of the draws "
                        f"(median {x['rolling_deg_median']:.1f} deg)")
        return (f"{name}: {x['fraction_within']:.0%} of its predictive runouts end within "
                f"{stalls['near_m']:g} m of the release, observed {x['observed_m']:.1f} m"
                + why)

    more = f"; and {len(rows) - 4} more rows" if len(rows) > 4 else ""
    return (f"{len(rows)} rows stall at their release in the simulation though the blocks ran "
            f"more than {stalls['observed_beyond_m']:g} m (" + "; ".join(map(one, rows[:4]))
            + more + "): where the rolling resistance angle exceeds the slope, a block released "
            "slowly on the ground cannot start; check the release (a release_height_m below "
            "the profile's ground, the site's release_height_sd_m)")


def heldout_entries(cal, heldout: Observations, profile):
    """The simulated entries of held-out rows (``Entries.from_rows``), each
    from its own release by the fit's rules, at the calibration's rock density
    and release errors (``cal.release_height_sd_m``, ``release_speed_sd_m_s``),
    in the rows' shape classes where the fit simulated its own rows' (``cal.row_shapes``)."""
    from calib.files.inputs import own_profile
    from calib.model.entries import Entries

    start = float(profile.x_m[0])
    common = start if cal.release_x_m is None else float(cal.release_x_m)
    # the fit's rules: rows without release_x_m start at the profile's first vertex
    # (calib.fit's release groups); a DEM fit of an older file ran every block at
    # the calibration's one release
    default = start if cal.own_releases else common
    return Entries.from_rows(heldout, default, profile_of=own_profile,
                             density_kg_m3=cal.rock_density_kg_m3,
                             row_shapes=cal.row_shapes).with_release_errors(
        cal.release_height_sd_m, cal.release_speed_sd_m_s)


def predictive_runouts(cal, heldout: Observations, profile, n_posterior: int,
                       n_blocks: int | None, seed: int):
    """The posterior predictive runouts of held-out rows, each from its own
    release (``calib.model.entries.Entries.from_rows``) at ``n_posterior`` draws of
    the calibration ``cal`` (``calib.files.calibration_file``), its blocks at the
    calibration's rock density and release errors (``heldout_entries``), with the
    effects it was fitted with (``Calibration.effects``: each draw's effect
    columns switch them on in the solver, as in the fit).

    Returns:
        (pooled (G, n_posterior * n_blocks) runouts per (size, release) group,
        group index per row, the ``Draws``, blocks per draw and group).

    Raises:
        ValueError: a release outside the profile, more draws than the
            posterior has, or rows with their own releases for a DEM fit that
            released every block at one point.
    """
    import jax

    from calib.files.calibration_file import draw_parameters
    from calib.model.forward import CrspForward, DemForward

    common = float(profile.x_m[0]) if cal.release_x_m is None else float(cal.release_x_m)
    entries = heldout_entries(cal, heldout, profile)
    releases, index = entries.release_x_m, entries.index
    for g, x0 in enumerate(releases):
        p, name = ((profile, cal.profile_csv) if entries.profiles[g] is None
                   else (entries.profiles[g], entries.profile_csv[g]))
        lo, hi = float(p.x_m[0]), float(p.x_m[-1])
        if not lo <= x0 < hi:
            raise ValueError(f"release_x_m {x0:g}: outside the profile {name} "
                             f"({lo:g} to {hi:g} m)")
    draws = draw_parameters(cal, n_posterior, seed)
    key = jax.random.fold_in(jax.random.key(seed), 7)
    if not cal.release_heights and np.any(np.isfinite(entries.release_height_m)):
        raise ValueError(f"the held-out rows give release_height_m but the {cal.model.upper()} "
                         f"fit {cal.path} released its rows on the ground (an older "
                         "calibration file): refit with calib.fit to release both alike")
    if cal.model == "crsp":
        from calib.model.priors import crsp_box

        # the fitted model: the baseline's box, the effects' columns after it
        # (calib.model.effects), mapped onto the solver as the fit mapped them
        fw = CrspForward(profile, entries, n_blocks or 100, key, box=crsp_box(cal.base_names),
                         effect=cal.effects or "none",
                         rolling_threshold_m_s=cal.rolling_threshold_m_s)
    else:
        from calib.model.dem_run import DEM_RUN, DemRun

        if not cal.own_releases and np.any(releases != common):
            raise ValueError(f"the DEM fit released every block at x = {common:g} m; held-out "
                             "rows with other release_x_m need a calibration that releases "
                             "each row from its own point (refit with calib.fit)")
        if not cal.release_heights:  # an older DEM fit released on the ground
            entries = entries.with_release_state()
        fw = DemForward(profile, entries, n_blocks or 4, key, form=cal.alpha_form,
                        run=DemRun(**cal.dem_run) if cal.dem_run else DEM_RUN)
    return pool_draws(fw.runouts(draws.values)), index, draws, fw.n_blocks
