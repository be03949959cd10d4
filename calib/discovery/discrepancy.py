"""The discrepancy workflow: fit the baseline, locate where it fails, fit each
candidate effect, name the one that clearly predicts better, show the gap
shrink; then add it to the baseline and search again.

1. Every candidate (the baseline ``none`` and each effect of ``calib.model.effects``)
   is fitted the same way, by adaptive importance sampling over a simulated
   design (``calib.discovery.candidate_fit``: the stages, the weights, the
   held-out scores, the posterior predictive and the gap).
2. The baseline's posterior predictive (``n_draws`` posterior draws re-simulated
   with fresh blocks) gives quantile residuals, tested against block size and
   stop position (``calib.discovery.residuals``): WHERE it fails, with p-values.
3. The candidates are compared by their K-fold held-out log predictive density
   (``calib.discovery.scores``); the best is named only when its gain over the
   baseline exceeds ``ELPD_MIN`` = 4 nats and z standard errors, else ``none``:
   z = ``Z_MIN`` = 2 at the first step (its false-positive rate over the whole
   candidate set measured on null data, ``docs/studies.md``), raised
   Bonferroni-style for the m candidates a later step compares
   (``calib.discovery.scores.naming_z``: 2.53 for four).
   Each effect's row of the table also gives ``effective_rows``, the number of
   rows that effectively carry its gain (the 2-se bar is a bar on it, see
   ``calib.discovery.scores.effective_rows``), and ``carrying_rows``, the indices of the
   rows that carry 90 % of it (runout rows in file order, then speed rows).
4. The gap metric (``GAP_METRIC``) is computed for every candidate from its own
   posterior predictive; gap_before is the baseline's, gap_after the final
   model's (re-fitted on all rows, which its design already is).
5. Discovery keeps going (``discover``'s ``combine``): once an effect is named,
   the model with it is the new baseline, and steps 1 and 3 run again with
   each remaining candidate added to it (baseline + named + candidate against
   baseline + named, whose fit is reused; its posterior seeds the warm
   stage). Stopping rule: a step that names none, no candidate left, or the
   step limit. Multiple testing: within a step the bar is Bonferroni's over the
   m candidates compared (3.), i.e. each step tests "no remaining candidate
   gains" at the one-sided level ALPHA = Phi(-2) = 2.3 % whatever the
   dependence of the candidates' gains; across steps nothing more is spent,
   because a step runs only after the one before rejected: once every real
   effect is in the model, the next step is the first whose candidates all
   lack a gain, and it names one with probability at most ALPHA, after which
   the loop stops or has already erred (the fixed-sequence argument: Westfall
   & Krishen 2001, "Optimally weighted, fixed sequence and gatekeeper multiple
   testing procedures", J. Statist. Plann. Inference 99, 25-40). Our choice
   over splitting a family-wise level across the steps (ALPHA / K each), which
   would make later steps needlessly blind. Two caveats: the sequence of
   hypotheses depends on what earlier steps named (an early wrong effect can
   change the later ones), and the level rests on the normal approximation of
   the score difference, which is optimistic with few rows (Sivula et al.
   2022); the levels are nominal.

Unfinished blocks (NaN runouts and speeds from the forward models,
``calib.model.unfinished``) are left out of the likelihood, the predictive and the
gap; each fit counts them (design, predictive and noise simulations,
``CandidateFit.unfinished``) and warns once (``UnfinishedBlocksWarning``) when
some (design point, size class) has more than 1 % of them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import numpy as np

from calib.discovery.candidate_fit import Candidate, CandidateFit, fit_candidate
from calib.discovery.proposals import gaussian_fit
from calib.discovery.residuals import locate
from calib.discovery.scores import (
    best_effect,
    carrying_rows,
    effective_rows,
    elpd_difference,
    folds,
    naming_threshold,
    naming_z,
)
from calib.files.inputs import own_profile
from calib.inference.budget import DiscoveryBudget
from calib.inference.likelihood import VelocityRows
from calib.model.entries import Entries
from calib.model.warp import unit_coordinates

__all__ = ["MULTIPLE_TESTING", "STOPPING_RULE", "Discovery", "discover", "model_label",
           "size_classes"]


def size_classes(sizes_m: np.ndarray, max_classes: int = 8):
    """Size classes of the rows: the distinct sizes, or (more than ``max_classes``)
    ``max_classes`` bins of equal width in log size, represented by their
    members' geometric mean (an approximation stated in the output).

    Returns:
        (class_sizes_m (C,), row_class (n_obs,)).
    """
    sizes = np.asarray(sizes_m, float)
    uniq = np.unique(sizes)
    if uniq.size <= max_classes:
        return uniq, np.searchsorted(uniq, sizes)
    edges = np.linspace(np.log(uniq[0]), np.log(uniq[-1]), max_classes + 1)
    idx = np.clip(np.searchsorted(edges, np.log(sizes), side="right") - 1, 0, max_classes - 1)
    used = np.unique(idx)
    reps = np.array([np.exp(np.mean(np.log(sizes[idx == u]))) for u in used])
    return reps, np.searchsorted(used, idx)


@dataclasses.dataclass
class Discovery:
    """Outcome of the workflow (``discover``).

    Attributes:
        named_effect: the effect named at the first step, against the plain
            baseline ("none": none).
        fits: every fitted model by its label (``model_label``: "none", an
            effect, or the effects of each step joined by "+").
        table: the first step's ranked table (``steps[0]["candidates"]``).
        where_before: where the plain baseline disagrees (``residuals.locate``);
            where_after: the same for the final model (None: nothing named).
        class_sizes_m, row_class: the size classes and each row's class.
        gap_before: the plain baseline's gap; gap_after: the final model's.
        timings_s: seconds per fitted model.
        entries: the simulated (size class, release) groups, or None.
        steps: one record per step (``_step_record``): its baseline, the
            candidates compared, the naming bar, what it named and the gap.
        named_effects: the effects named, in order (the final model's effects).
    """

    named_effect: str
    fits: dict[str, CandidateFit]
    table: list[dict]
    where_before: dict
    where_after: dict | None
    class_sizes_m: np.ndarray
    row_class: np.ndarray
    gap_before: float
    gap_after: float
    timings_s: dict
    entries: Entries | None = None
    steps: list[dict] = dataclasses.field(default_factory=list)
    named_effects: tuple[str, ...] = ()

    @property
    def final_model(self) -> str:
        """The label of the model discovery ends with (``model_label``)."""
        return model_label(self.named_effects)


def model_label(effects) -> str:
    """A model's label: "none" (the baseline) or its effects joined by "+" in the
    order they were named (``calib.model.effects.model_label`` for CRSP's)."""
    return "+".join(effects) or "none"


STOPPING_RULE = ("after an effect is named, the model with it becomes the baseline and the "
                 "remaining candidates are fitted on top of it; discovery stops at the first "
                 "step that names none, when no candidate is left, or after --max-steps steps")
MULTIPLE_TESTING = ("step 1 names the best candidate only if its gain exceeds max(4 nats, "
                    "2 se), the bar whose false-positive rate over the whole candidate set "
                    "was measured on null data (docs/studies.md); each later step raises "
                    "it to z_m se with z_m = Phi^-1(1 - 0.023 / m) over the m candidates it "
                    "compares (Bonferroni at the one-sided level of the 2-se bar, 0.023; "
                    "z = 2.28, 2.43, 2.53 for m = 2-4); a step runs only after the one "
                    "before named an effect (a fixed-sequence procedure)")


def discover(candidates: list[Candidate], obs, profile, key: jax.Array, budget: DiscoveryBudget,
             progress=None, velocities=None, release_tolerance_m: float | None = None,
             release_errors: tuple[float, float] = (0.0, 0.0),
             combine: Callable[[tuple[str, ...]], Candidate] | None = None,
             max_steps: int | None = None) -> Discovery:
    """Run the whole workflow on observations ``obs`` (see module docstring).

    ``candidates[0]`` must be the baseline (effect ``none``). ``velocities``
    (optional, ``calib.files.observations.Velocities``): passage speeds at stations,
    scored with the runouts by every candidate (forward models with
    ``simulate``, i.e. CRSP); the gap metric and the residuals stay on runouts.

    Steps: the first step compares the candidates with the baseline. With
    ``combine`` (effects -> the ``Candidate`` of the baseline with those
    effects added in that order, e.g. ``calib.discovery.candidates.crsp_model``)
    discovery keeps going: a named effect joins the baseline, and the next step
    compares baseline + named + each remaining candidate with baseline +
    named (whose fit is reused), until a step names none, no candidate is
    left, or ``max_steps`` steps ran (None: no limit but those). Without
    ``combine`` (candidates that cannot be combined, the DEM's) there is one
    step. Stopping rule and multiple-testing control: ``STOPPING_RULE``,
    ``MULTIPLE_TESTING`` (module docstring, step 5).

    Releases: where the rows give ``release_x_m`` (and ``release_tolerance_m``
    is not None), every row is simulated from its own point, as ``calib.fit``
    does: rows of one size class whose releases lie within
    ``release_tolerance_m`` share one simulated (size class, release) group
    (``calib.model.entries.Entries.from_rows``; rows without a release start
    at the profile's first vertex), and stop positions for the residual tests
    are each row's release plus its runout. Velocity rows are simulated from the
    median of the rows' releases. Otherwise every block starts at the
    profile's first vertex. Both solvers release each group at its rows' mean
    speed and height where the rows give them; each block (CRSP's and the
    DEM's) draws its height and speed about them with the sds
    ``release_errors`` (m, m/s: the site's, ``calib.files.site``;
    ``Entries.with_release_errors``). Rows on their own
    profiles (``Observations.profile``) are simulated on them; their stop
    positions enter the residual tests as abscissae of the command's profile
    (our choice: it assumes lines cut alike, e.g. the mean fall lines of
    nearby spots with one margin, as ``calib.field`` users cut them).
    """
    if candidates[0].effect != "none":
        raise ValueError("the first candidate must be the baseline (effect 'none')")
    if max_steps is not None and max_steps < 1:
        raise ValueError(f"max_steps: expected at least 1, got {max_steps}")
    n_run = obs.n_obs
    class_sizes, row_class, fold, entries, vel, row_release = _rows(
        obs, profile, budget, velocities, release_tolerance_m, release_errors)
    fits, timings = {}, {}

    def fit(cand, label, k, warm):
        fits[label] = fit_candidate(cand, obs, class_sizes, row_class, k, budget, fold,
                                    progress, warm=warm, velocities=vel, entries=entries)
        timings[label] = fits[label].seconds

    # step 1 keeps the keys it always had (candidate i: fold_in(key, i))
    fit(candidates[0], "none", jax.random.fold_in(key, 0), None)
    steps, named = _steps(candidates, fit, fits, key, combine, max_steps, n_run, vel)
    base = fits["none"]
    final = fits[model_label(named)]
    where_before, where_after = _where(obs, profile, row_class, class_sizes, base,
                                       final if named else None, entries, row_release)
    return Discovery(steps[0]["named"], fits, steps[0]["candidates"], where_before, where_after,
                     class_sizes, row_class, base.gap, final.gap, timings, entries, steps, named)


def _steps(candidates: list[Candidate], fit: Callable, fits: dict, key: jax.Array,
           combine, max_steps: int | None, n_run: int, vel):
    """The steps of ``discover``, once the plain baseline is fitted: each step fits
    the remaining candidates on top of its baseline (``fit(candidate, label, key,
    warm)`` stores the fit in ``fits`` under its label), scores them against it
    (``_step_record``) and names one or none; the loop ends by ``STOPPING_RULE``.

    Keys: step 1's candidate i gets ``fold_in(key, i)``, as it always has; a later
    step s uses ``fold_in(key, 1000 + s)`` in place of ``key``.

    Returns:
        (steps, named): the step records and the effects named, in order.
    """
    base_cand, named = candidates[0], ()
    remaining = {c.effect: c for c in candidates[1:]}
    steps = []
    while True:  # step 1 always (a baseline alone gets its table), later ones while named
        step = len(steps) + 1
        step_key = key if step == 1 else jax.random.fold_in(key, 1000 + step)
        base = fits[model_label(named)]
        warm = None  # the step's baseline posterior seeds its candidates (not for grids)
        if base_cand.design is None:
            warm = gaussian_fit(unit_coordinates(base_cand.box)[0](base.theta), base.weights)
        cands = {e: c if step == 1 else combine(named + (e,)) for e, c in remaining.items()}
        for i, (e, c) in enumerate(cands.items(), start=1):
            fit(c, model_label(named + (e,)), jax.random.fold_in(step_key, i), warm)
        steps.append(_step_record(step, named, {e: fits[model_label(named + (e,))]
                                                for e in cands}, base, n_run, vel))
        new = steps[-1]["named"]
        if new == "none" or combine is None or (max_steps is not None and step >= max_steps):
            break
        named, base_cand = named + (new,), cands[new]
        del remaining[new]
        if not remaining:
            break
    if steps[-1]["named"] != "none" and steps[-1]["named"] not in named:
        named = named + (steps[-1]["named"],)  # the last step's, when the loop stopped on it
    return steps, named


def _where(obs, profile, row_class, class_sizes, base: CandidateFit,
           final: CandidateFit | None, entries, row_release):
    """Where the plain baseline disagrees with the rows and where the final model
    does (None when nothing was named): ``calib.discovery.residuals.locate`` on
    each one's posterior predictive, each with its own ``default_rng(0)``."""
    rng = np.random.default_rng(0)
    row_entry = None if entries is None else entries.index
    where_before = locate(obs, row_class, class_sizes, base.samples, profile, rng, row_release,
                          row_entry)
    where_after = None if final is None else locate(
        obs, row_class, class_sizes, final.samples, profile, np.random.default_rng(0),
        row_release, row_entry)
    return where_before, where_after


def _rows(obs, profile, budget: DiscoveryBudget, velocities, release_tolerance_m,
          release_errors):
    """The rows as the candidates see them: size classes, folds, the simulated
    entries (``_entries``), the passage-velocity rows, and each runout row's release."""
    n_run = obs.n_obs
    vel = None
    if velocities is not None and velocities.n_obs:
        class_sizes, all_class = size_classes(np.concatenate([obs.block_size_m,
                                                              velocities.block_size_m]))
        row_class = all_class[:n_run]
        vel_class = all_class[n_run:]
        # velocity rows are their own fold strata (after the runout rows' strata,
        # so the runout rows keep the folds they have without velocities)
        fold = folds(np.concatenate([all_class[:n_run], all_class[n_run:] + class_sizes.size]),
                     budget.k_folds, seed=0)
    else:
        class_sizes, row_class = size_classes(obs.block_size_m)
        vel_class = None
        fold = folds(row_class, budget.k_folds, seed=0)
    entries = _entries(obs, profile, class_sizes, row_class, vel_class, release_tolerance_m,
                       release_errors)
    row_release = None
    if entries is not None:
        row_release = entries.release_x_m[entries.index[:n_run]]
        if vel_class is not None:  # the velocity rows' entries follow the runout rows'
            vel_class = entries.index[n_run:]
        entries = dataclasses.replace(entries, index=entries.index[:n_run])
    if vel_class is not None:
        vel = VelocityRows.of(velocities, vel_class)
    return class_sizes, row_class, fold, entries, vel, row_release


def _step_record(step: int, named: tuple[str, ...], cand_fits: dict, base: CandidateFit,
                 n_run: int, vel) -> dict:
    """One step of ``discover``: its candidates scored against its baseline (the
    model with the effects ``named``) and its verdict.

    Keys: ``step``, ``baseline`` (label) and ``baseline_effects``;
    ``candidates``, the ranked table (row ``effect`` "none": the step's
    baseline; others the effect added, ``model`` the label of the model fitted;
    ``delta_vs_none``/``se_delta``: gain over the step's baseline);
    ``n_compared`` (m), ``z`` (``naming_z(m)``), ``threshold_nats`` (the best
    candidate's bar, ``naming_threshold``); ``named`` ("none" or the effect),
    ``gain_nats``, ``se_nats`` (the best candidate's), ``gap_before``,
    ``gap_after`` (the step's baseline, and the model after the step)."""
    table = []
    for eff, f in {"none": base, **cand_fits}.items():
        gains = f.elpd - base.elpd  # per row
        d, se = (0.0, 0.0) if eff == "none" else elpd_difference(f.elpd, base.elpd)
        table.append({"effect": eff, "model": model_label(named + (() if eff == "none"
                                                                   else (eff,))),
                      "score": float(f.elpd.sum()), "delta_vs_none": d,
                      "se_delta": se, "gap": f.gap, "n_params": len(f.names),
                      "ess": f.ess, "loglik_noise_sd_nats": f.loglik_noise_sd_nats,
                      "khat": f.khat, "khat_by_fold": [float(k) for k in f.khat_folds],
                      "khat_bar": f.khat_bar, "n_fold_points": f.n_fold_points,
                      "fresh_draw_folds": list(f.fresh_draw_folds),
                      "psis_flagged_folds": [int(j) for j in
                                             np.flatnonzero(f.khat_folds > f.khat_bar)]})
        if eff != "none":  # how many rows carry the gain (the se rule is a bar on it)
            table[-1]["effective_rows"] = effective_rows(gains)
            table[-1]["carrying_rows"] = [int(i) for i in carrying_rows(gains)]
        if vel is not None:  # the part of the gain that the speeds carry
            table[-1]["delta_velocity_rows"] = float(gains[n_run:].sum())
    table.sort(key=lambda r: -r["score"])
    m = len(cand_fits)
    # step 1 keeps the 2-se bar whose false-positive rate over the whole candidate
    # set was measured on null data (docs/studies.md); later steps, which no null
    # study covers, raise it Bonferroni-style over the candidates they compare
    m_bar = 1 if step == 1 else m
    best = best_effect(table)
    threshold = naming_threshold(None if best is None else best["se_delta"], m_bar)
    new = best["effect"] if best is not None and best["delta_vs_none"] > threshold else "none"
    for r in table:
        r["clear_gain"] = r["effect"] == new and new != "none"
    return {"step": step, "baseline": model_label(named), "baseline_effects": list(named),
            "n_compared": m, "z": naming_z(m_bar), "threshold_nats": threshold, "named": new,
            "best": None if best is None else best["effect"],
            "gain_nats": None if best is None else best["delta_vs_none"],
            "se_nats": None if best is None else best["se_delta"],
            "gap_before": base.gap,
            "gap_after": cand_fits[new].gap if new != "none" else base.gap,
            "candidates": table}


def _entries(obs, profile, class_sizes, row_class, vel_class, tol_m,
             release_errors=(0.0, 0.0)) -> Entries | None:
    """The simulated (size class, release) groups of ``discover``, None where every
    block starts at the profile's first vertex (no ``release_x_m`` in the rows,
    or ``tol_m`` None). Runout rows first in ``index``, then the velocity rows
    (``vel_class``), whose groups are their size classes at the median of the
    runout rows' releases, released at the solver's default speed and height.
    The rows' tracked heights and speeds carry the sds ``release_errors``."""
    rel = np.asarray(obs.release_x_m, float)
    if tol_m is None or not (np.any(np.isfinite(rel)) or any(obs.profile)):
        return None
    binned = dataclasses.replace(obs, block_size_m=np.asarray(class_sizes)[row_class])
    g = Entries.from_rows(binned, float(profile.x_m[0]), tol_m, profile_of=own_profile
                          ).with_release_errors(*release_errors)
    if vel_class is None:
        return g
    speed, vel_entry = g.with_speed_entries(np.asarray(class_sizes)[vel_class])
    return dataclasses.replace(speed, index=np.concatenate([g.index, vel_entry]))
