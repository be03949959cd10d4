"""The discrepancy workflow's warnings: when a verdict of ``calib.discover``
rests on too little (few effective design points, heavy-tailed importance
weights, simulation noise near the naming threshold, a gain carried by few
rows). Each rule takes the ranked candidate table (``discovery.json``'s
``candidates``) and returns the warning lines, empty where none applies; the
command prints them and records them in ``discovery.json``.
"""

from __future__ import annotations

import numpy as np

from calib.inference.budget import MAX_DESIGN_SCALE

__all__ = ["MIN_ESS", "concentration_warnings", "ess_warnings", "gap_warnings",
           "grid_warnings", "noise_warnings", "psis_warnings"]

# below this importance-sampling ESS a fit's posterior rests on a handful of
# design points (measured: ESS 1-14 with 180 rows at the default budget)
MIN_ESS = 10.0


def _more_points(design_scale: float | None) -> str:
    """The rerun that adds design points: ``--design-scale`` doubled from the
    run's (``calib.inference.budget.scaled_design``), up to its largest; None:
    the run's designs are fixed grids (the DEM candidates'), which
    ``--design-scale`` refuses, so no rerun of this run adds points."""
    if design_scale is None:
        return "--model crsp; the dem candidates' fixed grids have no points to add"
    if design_scale >= MAX_DESIGN_SCALE:
        return f"already at the largest --design-scale, {MAX_DESIGN_SCALE:g}"
    return f"--design-scale {min(2.0 * design_scale, MAX_DESIGN_SCALE):g}"


def ess_warnings(ess: dict, min_ess: float = MIN_ESS,
                 design_scale: float | None = 1.0) -> list[str]:
    """Warnings for fits whose importance weights rest on few design points.

    ``ess``: effect -> (effective sample size, design points); ``design_scale``:
    the run's factor on its design's points (the rerun suggested doubles it),
    None for fixed-grid designs (the DEM's: no rerun adds points).
    With few effective points the posterior intervals understate the
    uncertainty and the held-out score carries Monte Carlo error that its
    standard error omits.
    """
    low = {e: v for e, v in ess.items() if v[0] < min_ess}
    if not low:
        return []
    listing = ", ".join(f"{e} {v[0]:.1f} of {v[1]}" for e, v in low.items())
    return [f"few effective design points (importance-sampling ESS < {min_ess:g}): {listing}. "
            f"Their 90 % intervals understate the uncertainty, and their held-out scores carry "
            f"Monte Carlo error that the reported se omits: treat gains near the naming "
            f"threshold with care, or rerun with more design points "
            f"({_more_points(design_scale)})."]


def psis_warnings(candidates: list[dict], design_scale: float | None = 1.0) -> list[str]:
    """A warning naming the folds whose training weights have a Pareto k-hat above
    the bar of the design's size, min(0.7, 1 - 1/log10 S)
    (``calib.inference.importance.khat_threshold``; ``psis_flagged_folds`` of each
    candidate row); ``design_scale`` as for ``ess_warnings``.

    There the smoothed weights rest on a few design points (or, for a fold
    scored on fresh draws of its training posterior, the draws' weights on a
    few points of their cloud) and the folds' held-out scores (so the gains
    and their se) are unreliable (Vehtari et al. 2024); more design points
    where the posterior lives help (``calib.discover
    --design-scale``; measured in docs/studies.md, "The noise measured where
    the weight lies, and eight times the blocks").
    """
    flagged = [c for c in candidates if c.get("psis_flagged_folds")]
    if not flagged:
        return []
    listing = "; ".join(
        f"{c['effect']} fold{'s' if len(c['psis_flagged_folds']) > 1 else ''} "
        + ", ".join(f"{j} ({_khat_text(c['khat_by_fold'][j])})" for j in c["psis_flagged_folds"])
        for c in flagged)
    return [f"Pareto k-hat above the bar min(0.7, 1 - 1/log10 S) in the held-out folds' "
            f"importance weights "
            f"({listing}): those folds' scores rest on few weighted points and are unreliable; "
            f"treat the gains that involve them with care, or rerun with more design points "
            f"({_more_points(design_scale)}; more blocks per point, --n-blocks, sharpen the "
            f"posterior and can raise k-hat)."]


def _khat_text(k) -> str:
    return f"k-hat {float('nan') if k is None else k:.2f}"


def grid_warnings(emulators: dict) -> list[str]:
    """What a fit on a fixed grid (the DEM's) leaves out, where any fit was one.

    ``emulators``: effect -> the fit's ``grid_emulator`` record (None on an
    adaptive design). Such a fit's weights and held-out scores come from each
    row's log-likelihood emulated between the grid's points, its posterior
    averaged over the summed log-likelihood's realisations
    (``calib.discovery.grid_emulation``). Measured on data the DEM made
    (docs/studies.md, "DEM discovery: the grid's noise in the intervals",
    2026-12-05): the held-out score rests on one set of blocks per point, and
    the baseline's held-out total moved by an sd of 10 nats (60 rows) and 30
    nats (180 rows) between four block sets, which the gain's se (over rows)
    does not hold; the likelihood of 8 blocks per point is biased low (by
    65-95 nats at 180 rows against 32 blocks, unevenly over alpha
    0.36-0.44), which the intervals do not hold either.
    """
    used = {e: r for e, r in emulators.items() if r}
    if not used:
        return []
    listing = ", ".join(f"{e} {r['loo_rmse_nats']:.2f}" for e, r in used.items())
    noise = ", ".join(f"{e} {r['sum_noise_sd_nats']:.0f}" for e, r in used.items()
                      if r.get("sum_noise_sd_nats") is not None)
    return [f"fixed grids: each row's log-likelihood is emulated between the grid's points "
            f"(error of a left-out point, nats per row: {listing}; the summed log-likelihood's "
            f"noise from point to point, nats: {noise}), and the intervals carry that noise. "
            f"The held-out scores rest on one set of blocks per point: on DEM-made data the "
            f"baseline's held-out total moved by an sd of 10 nats at 60 rows and 30 at 180 "
            f"between block sets, which the gain's se does not hold (a gain between two "
            f"candidates carries about 1.4 times that): read a gain within about 30 nats "
            f"(60 rows) to 85 nats (180 rows) of the naming threshold as unsettled; "
            f"--n-blocks 32 cut the noise about threefold at four times the cost "
            f"(docs/studies.md)."]


def gap_warnings(named: str, gap_before_m: float, gap_after_m: float) -> list[str]:
    """A warning when the named effect WIDENS the gap (mean CRPS per size
    class) that it is named to close: its better held-out score then comes
    from the likelihood's tails (rows the baseline gives almost no density),
    not from predicting the runouts better; our rule, any growth at all."""
    if named == "none" or not (np.isfinite(gap_before_m) and np.isfinite(gap_after_m)):
        return []
    if gap_after_m <= gap_before_m:
        return []
    ratio = gap_after_m / gap_before_m
    return [f"the named effect {named} widens the gap it is named to close: mean CRPS "
            f"{gap_before_m:.2f} m before, {gap_after_m:.2f} m after (x{ratio:.2f}); its "
            "better score comes from rows the baseline gives almost no density, not from "
            "better predicted runouts: do not take it as found"]


def noise_warnings(candidates: list[dict], n_blocks: int, n_compared: int = 1) -> list[str]:
    """A warning when simulation noise could flip the verdict.

    ``candidates``: rows of the ranked table (``effect``, ``delta_vs_none``,
    ``se_delta``, ``loglik_noise_sd_nats``; nan or None: not measured). The rule
    looks at the effect with the largest gain g and names it when g exceeds
    T = max(ELPD_MIN, z se), z = ``naming_z(n_compared)`` for the
    ``n_compared`` candidates of the step. The candidates are fitted with different
    blocks, so g carries simulation noise of about s = sqrt(s_effect^2 +
    s_none^2), from their summed log-likelihood sds (an approximation: the
    score is a held-out average over the posterior, not the likelihood at one
    point). If |g - T| < 2 s the verdict may change with other simulated blocks.
    """
    from calib.discovery.scores import best_effect, naming_threshold

    rows = {c["effect"]: c for c in candidates}
    best = best_effect(candidates)
    if "none" not in rows or best is None:
        return []
    sds = [rows["none"].get("loglik_noise_sd_nats"), best.get("loglik_noise_sd_nats")]
    if any(v is None or not np.isfinite(v) for v in sds):
        return []
    noise = float(np.hypot(*sds))
    gain, threshold = best["delta_vs_none"], naming_threshold(best["se_delta"], n_compared)
    if abs(gain - threshold) >= 2 * noise:
        return []
    return [f"the verdict may change with other simulated blocks: {best['effect']} gains "
            f"{gain:+.1f} nats against a naming threshold of {threshold:.1f}, and the simulation "
            f"noise of that gain is about {noise:.1f} nats (sd of the summed log-likelihood of "
            f"{best['effect']} and of the baseline, combined; {n_blocks} blocks per size "
            f"class). --n-blocks {4 * n_blocks} roughly halves the noise (cost about x4)."]


def concentration_warnings(candidates: list[dict], runout_sizes_m: np.ndarray,
                           speed_sizes_m: np.ndarray | None = None,
                           n_compared: int = 1) -> list[str]:
    """A warning when the best effect gains more than ``ELPD_MIN`` but is not
    named because few rows carry its gain.

    ``candidates``: rows of the ranked table (``effect``, ``delta_vs_none``,
    ``se_delta``, ``effective_rows``, ``carrying_rows``). The 2-se bar asks that
    a gain rest on more than ``rows_needed(n)`` effective rows (3.8 of 60), so a
    gain of hundreds of nats from three rows is not named (the normal
    approximation behind the se is least trustworthy there: Sivula, Magnusson,
    Matamoros & Vehtari, arXiv:2008.10296). The warning names the sizes of the
    rows that carry the gain: more observations of those sizes settle it, and
    one or two aberrant rows could also be the cause. ``n_compared``: the
    candidates of the step, which set the bar (``naming_z``).
    """
    from calib.discovery.scores import (
        ELPD_MIN,
        best_effect,
        naming_threshold,
        naming_z,
        rows_needed,
    )

    best = best_effect(candidates)
    if best is None or "effective_rows" not in best:
        return []
    gain = best["delta_vs_none"]
    if not gain > ELPD_MIN or gain > naming_threshold(best["se_delta"], n_compared):
        return []
    z = naming_z(n_compared)
    runs = np.asarray(runout_sizes_m, float)
    speeds = np.zeros(0) if speed_sizes_m is None else np.asarray(speed_sizes_m, float)
    n = runs.size + speeds.size
    rows = np.asarray(best["carrying_rows"], int)
    parts = []
    for kind, idx, sizes in (("runout", rows[rows < runs.size], runs),
                             ("speed", rows[rows >= runs.size] - runs.size, speeds)):
        if idx.size:
            vals, counts = np.unique(sizes[idx], return_counts=True)
            what = ", ".join(f"{v:g} m x{c}" for v, c in zip(vals, counts))
            parts.append(f"{kind} rows of {what}" if speeds.size else what)
    return [f"{best['effect']} gains {gain:+.1f} nats ({gain / best['se_delta']:.2f} se) but is "
            f"not named: {rows.size} of the {n} rows carry 90 % of the gain "
            f"({'; '.join(parts)}), {best['effective_rows']:.1f} effective rows, and the "
            f"{z:.3g}-se bar needs more than {rows_needed(n, z):.1f}. More observations of "
            f"blocks of those sizes would show whether the effect is real; one or two aberrant "
            f"rows could also give such a gain."]
