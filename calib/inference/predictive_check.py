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
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import scoringrules as sr

from calib.files.observations import Observations
from solvers.percentiles import few_blocks

__all__ = ["MIN_ROWS_PER_SIZE", "PredictiveCheck", "in_band", "observed_ensemble",
           "pool_draws", "predictive_runouts", "score_rows"]

MIN_ROWS_PER_SIZE = 3  # fewest calibration rows of one size for a per-size baseline


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
    out = []
    for i in range(obs.n_obs):
        ens = observed_ensemble(obs, i, predictive[group_index[i]], rng)
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
            out.append(row)
            continue
        y, s = float(obs.runout_m[i]), float(obs.runout_sd_m[i])
        row.update(observed_m=y, observed_sd_m=s)
        if ens.size == 0:  # no simulated block of this group finished
            out.append(row)
            continue
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
        out.append(row)
    rows = pd.DataFrame(out)
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
    return PredictiveCheck(rows, summary)


def predictive_runouts(cal, heldout: Observations, profile, n_posterior: int,
                       n_blocks: int | None, seed: int):
    """The posterior predictive runouts of held-out rows, each from its own
    release (``calib.model.entries.Entries.from_rows``) at ``n_posterior`` draws of
    the calibration ``cal`` (``calib.files.calibration_file``), its blocks at the
    calibration's rock density, with the effects it was fitted with
    (``Calibration.effects``: each draw's effect columns switch them on in the
    solver, as in the fit).

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
    from calib.files.inputs import own_profile
    from calib.model.entries import Entries
    from calib.model.forward import CrspForward, DemForward

    start = float(profile.x_m[0])
    common = start if cal.release_x_m is None else float(cal.release_x_m)
    # the fit's rules: rows without release_x_m start at the profile's first vertex
    # (calib.fit's release groups); a DEM fit of an older file ran every block at
    # the calibration's one release
    default = start if cal.own_releases else common
    entries = Entries.from_rows(heldout, default, profile_of=own_profile,
                                density_kg_m3=cal.rock_density_kg_m3)
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
                         effect=cal.effects or "none")
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
