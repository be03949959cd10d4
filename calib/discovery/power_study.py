"""A power study of the discrepancy workflow (the library of ``python -m
calib.power``): one run (synthetic data with a hidden effect, then the whole
workflow of ``calib.discovery.discrepancy`` on it) and the detection table over runs
(rates with exact Clopper-Pearson 90 % intervals, what was named instead, the
median gains).
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["detection_table", "one_run"]


def one_run(profile, effect, strength, n_obs, seed, sd_m, fit_seed, budget,
            speeds=None, budget_name=None) -> dict:
    """One run of the study: synthetic data with ``effect`` at ``strength``
    (``n_obs`` rows, measurement sd ``sd_m``, data seed ``seed``; ``speeds``:
    None or (stations_m, n_rows, sd_m_s) passage speeds too), the discrepancy
    workflow on it with ``fit_seed`` and ``budget``; the run's record (what was
    named, gains and their se, diagnostics, warnings, time; ``budget_name``
    recorded as "budget" if given).

    A pure function of its arguments, so that runs can go to any process in any
    order (``solvers.dispatch``): the data's keys come from ``seed``
    (``synthesize_effect``, ``synthesize_velocities``), the fits' from
    ``fit_seed``; no state is shared between runs. Only "seconds" differs
    between two calls."""
    import warnings

    import jax

    from calib.discovery.candidates import crsp_candidates
    from calib.discovery.discrepancy import discover
    from calib.discovery.synthetic import synthesize_effect, synthesize_velocities
    from calib.model.unfinished import UnfinishedBlocksWarning

    t0 = time.perf_counter()
    obs, _ = synthesize_effect(profile, effect, strength, n_obs, seed, sd_m=sd_m)
    vel = None if speeds is None else synthesize_velocities(
        profile, effect, strength, speeds[1], seed, speeds[0], speeds[2])
    with warnings.catch_warnings():  # recorded in the run's "warnings"
        warnings.simplefilter("ignore", UnfinishedBlocksWarning)
        d = discover(crsp_candidates(profile), obs, profile, jax.random.key(fit_seed), budget,
                     velocities=vel)
    extra = {} if vel is None else {
        "velocity_stations_m": [float(x) for x in speeds[0]], "n_velocity": speeds[1],
        "velocity_sd_m_s": speeds[2],
        "velocity_gains": {r["effect"]: float(r["delta_velocity_rows"])
                           for r in d.table if r["effect"] != "none"}}
    return {"effect": effect, "strength": strength, "n_obs": n_obs, "seed": seed,
            "sd_m": sd_m, "fit_seed": fit_seed, "named": d.named_effect, **extra,
            "gap_before": d.gap_before, "gap_after": d.gap_after,
            "gains": {r["effect"]: [float(r["delta_vs_none"]), float(r["se_delta"])]
                      for r in d.table if r["effect"] != "none"},
            "effective_rows": {r["effect"]: float(r["effective_rows"])
                               for r in d.table if r["effect"] != "none"},
            "ess": {r["effect"]: float(r["ess"]) for r in d.table},
            "loglik_noise_sd_nats": {r["effect"]: float(r["loglik_noise_sd_nats"])
                                     for r in d.table},
            "khat": {r["effect"]: float(r["khat"]) for r in d.table},
            "khat_by_fold": {r["effect"]: r["khat_by_fold"] for r in d.table},
            "psis_flagged_folds": {r["effect"]: r["psis_flagged_folds"] for r in d.table},
            "fresh_draw_folds": {r["effect"]: r["fresh_draw_folds"] for r in d.table},
            "warnings": [f.unfinished["warning"] for f in d.fits.values()
                         if f.unfinished and f.unfinished["warning"]],
            "seconds": time.perf_counter() - t0,
            **({} if budget_name is None else {"budget": budget_name})}


def detection_table(runs: list[dict], effects=None) -> list[dict]:
    """Per (effect, strength, n_obs): detection rate, exact 90 % interval, what was
    named, and how far the held-out scores behind those verdicts can be trusted.

    ``runs``: records with keys effect, strength, n_obs, named, gains
    ({effect: [gain, se]}) and, where ``one_run`` wrote them, the first step's
    ``khat_by_fold`` and ``psis_flagged_folds`` ({effect: [...]}, every
    candidate and the baseline). From those, per cell: ``folds`` (every
    candidate's folds over the runs), ``folds_above_bar`` (k-hat above the
    bar of its fit's design size, min(0.7, 1 - 1/log10 S), as ``calib.discover``
    flags them), ``folds_khat_above_0_7``, ``runs_warned`` (runs with a
    flagged fold: ``calib.discover`` printed its k-hat warning, so their
    verdict rests in part on scores it calls unreliable) and
    ``named_right_unwarned`` (right verdicts of the other runs); all None
    where no run of the cell has them (records of older studies). And
    ``folds_fresh_draws``: the folds scored on fresh draws of their training
    posterior (``fresh_draw_folds`` of the records; None where a run of the
    cell lacks them).
    """
    from scipy.stats import binomtest

    from calib.model.effects import EFFECT_NAMES

    names = list(effects or EFFECT_NAMES)
    cells: dict[tuple, list[dict]] = {}
    for r in runs:
        cells.setdefault((r["effect"], r["strength"], r["n_obs"]), []).append(r)
    table = []
    for (eff, s, n), rows in sorted(cells.items()):
        hits = sum(r["named"] == eff for r in rows)
        ci = binomtest(hits, len(rows)).proportion_ci(confidence_level=0.9, method="exact")
        gains = [r["gains"].get(eff) for r in rows] if eff != "none" else []
        gains = [x for x in gains if x is not None and x[0] is not None]
        table.append({
            "effect": eff, "strength": s, "n_obs": n, "runs": len(rows), "named_right": hits,
            "rate": hits / len(rows), "rate_q05": float(ci.low), "rate_q95": float(ci.high),
            "named": {k: sum(r["named"] == k for r in rows) for k in names
                      if any(r["named"] == k for r in rows)},
            "median_gain_nats": _median([x[0] for x in gains]),
            "median_gain_se": _median([x[0] / x[1] for x in gains
                                       if x[1] is not None and x[1] > 0]),
            "median_loglik_noise_sd_none_nats": _median(
                [r.get("loglik_noise_sd_nats", {}).get("none") for r in rows]),
            **_fold_counts(rows, eff),
            "seeds": [r["seed"] for r in rows]})
    return table


def _fold_counts(rows: list[dict], effect: str) -> dict:
    """The k-hat counts of ``detection_table`` for one cell's runs."""
    keys = ("folds", "folds_above_bar", "folds_khat_above_0_7", "runs_warned",
            "named_right_unwarned")
    rows = [r for r in rows if r.get("khat_by_fold") and "psis_flagged_folds" in r]
    if not rows:
        return dict.fromkeys(keys + ("folds_fresh_draws",))
    k = [np.array([np.nan if x is None else x for x in ks], float)
         for r in rows for ks in r["khat_by_fold"].values()]
    warned = [any(r["psis_flagged_folds"].values()) for r in rows]
    fresh = (int(sum(len(f) for r in rows for f in r["fresh_draw_folds"].values()))
             if all("fresh_draw_folds" in r for r in rows) else None)
    return dict(zip(keys, (
        int(sum(v.size for v in k)),
        int(sum(len(f) for r in rows for f in r["psis_flagged_folds"].values())),
        int(sum(np.sum(~(v <= 0.7)) for v in k)),  # a NaN k-hat counts as above
        int(sum(warned)),
        int(sum(r["named"] == effect and not w for r, w in zip(rows, warned, strict=True))),
    ), strict=True)) | {"folds_fresh_draws": fresh}


def _median(values) -> float | None:
    v = np.array([x for x in values if x is not None], float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else None
