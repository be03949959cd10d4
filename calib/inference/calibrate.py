"""Calibrate one forward model against observations: gradient fit, Bayesian fit, check.

Stages (each timed; ``Budget`` sets the sizes, ``QUICK`` / ``DEFAULT`` the presets):

1. Bayesian (``method`` includes "bayes"):
   a. design: simulate the runout distribution at ``n_design`` points of the
      prior box (CRSP: scrambled Sobol in the emulator's coordinates,
      ``CrspForward.design``; DEM: a grid in alpha per size) with common random
      numbers, ``n_blocks_design`` blocks per point and size;
   b. emulator: GPs of the runout quantiles (``calib.inference.emulator``); CRSP adds a
      second design of ``n_design2`` points, three quarters drawn from a pilot
      posterior and one quarter around the design points with the highest
      simulated likelihood (``calib.inference.design_waves``), so the emulator
      is accurate where the posterior lives (sequential design, as in history matching:
      Vernon et al. 2010);
   b'. CRSP: refocusing (``calib.inference.focus``): a third design of
      ``n_design3`` points fills the part of the box whose simulated
      likelihood the first two designs do not rule out (half scrambled Sobol,
      half drawn from an emulated posterior restricted to it); the emulator is
      refitted on the design points inside it and NUTS samples the prior
      restricted to it (its faces checked for piled-up posterior mass);
   c. hold-out check of the emulator; its predictive variance is inflated by the
      factor c >= 1 with which it accounts for the held-out errors, weighted by
      the variance the likelihood uses (the median kernel variance of the rows
      plus c times the emulator's; ``calib.inference.emulator.variance_inflation``);
   d. NUTS (``calib.inference.bayes``; CRSP: its chains start at the best
      design points, spread apart, ``chains.chain_starts``); CRSP: each chain's draws are
      re-simulated and a chain the simulator fits far worse than the best one
      is dropped (``chains.screen_chains``). Where a design point's simulated
      log-likelihood beats every chain's by more than
      ``bayes_stage.best_point_bar``, the chains missed a mode the design
      found: the focus region narrows to the design points near it, new
      points fill it and NUTS runs again. While the diagnostics still fail, or
      the GP's predictions at those draws disagree with the simulator
      (``loglik_emulator.at_posterior``), the re-simulated draws join the
      log-likelihood GP's design and NUTS runs again (at most
      ``Budget.refinements`` times): the GP learns the simulator where the chains
      sat, which is where it was wrong (sequential design at the emulated
      posterior, as in Gaussian-process ABC: Wilkinson 2014;
      Jarvenpaa et al. 2019, Bayesian Analysis 14(2), 595-622).
   e. CRSP: the posterior medians of ``n_realisations`` realisations of the
      log-likelihood GP (``calib.inference.realisations``); while they spread
      beyond a parameter's 90 % interval (the interval is narrower than the
      GP's own uncertainty allows), one point drawn from each realisation's
      posterior is simulated, joins the GP's design, and d runs again (at
      most ``realisation_waves`` times, ``bayes.focus.realisation_waves``):
      the simulations settle what the realisations disagree on (Thompson
      sampling of the GP's posterior over functions; our choice of design
      rule). A spread that outlasts the waves is a problem of the posterior.
      A run whose chains agree but that had divergent transitions runs again
      with a smaller step size (once; ``bayes.focus.careful_run``,
      ``calib.inference.bayes.careful_run``).
      Last, a run whose chains agree but whose ESS falls short runs again with
      as many times the draws as ``calib.inference.bayes.draw_factor`` asks
      (once; ``bayes.focus.longer_run``).
2. Gradient (``method`` includes "gradient"): Adam on the smoothed CRN
   objective of the SIMULATOR itself (``calib.inference.gradient``) from several starts:
   J(theta) = -sum_i log p(y_i | theta), the negative log-likelihood of
   ``calib.inference.likelihood`` with ``n_blocks_grad`` blocks per size. The
   starts: the box's centre, ``grad_starts - 1`` quasi-random points and (CRSP
   after a design) the design point with the highest simulated likelihood.
3. Check: the point estimate (the gradient stage's point, or the posterior's
   mode where the simulator scores that clearly higher: ``point_estimate``)
   is re-simulated with fresh random numbers
   (``n_check`` blocks per entry: the figure's sizes at the rows' median release,
   and every row's (size, release) group that is not one of them) and every
   observation gets its fit quality against its group's blocks: simulated
   5/50/95 % runouts, its PIT value P(R <= y) and log-likelihood.
4. Adequacy (``calib.inference.adequacy``): posterior mass near each prior bound and the
   posterior predictive coverage of the calibration rows (``n_predictive_draws``
   draws x ``n_blocks_predictive`` fresh blocks per size), flagged when the
   model looks unable to fit the data; and (CRSP with a design) whether a
   design point's simulated log-likelihood beats the estimate's (the check's),
   flagged when the fit missed a better region.

Unfinished blocks (NaN runouts from the forward model, ``calib.model.unfinished``)
are left out of every stage and counted per stage (design, gradient, check):
``ModelFit.unfinished``; one ``UnfinishedBlocksWarning`` per fit when some
(parameter point, block size) has more than ``UNFINISHED_WARN_FRACTION`` of them.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import numpy as np

from calib.files.observations import Observations
from calib.inference.adequacy import fit_adequacy
from calib.inference.bayes import Posterior
from calib.inference.bayes_stage import bayes_stage
from calib.inference.budget import Budget, presets
from calib.inference.fit_check import check_estimate
from calib.inference.gradient import GradientFit, gradient_stage
from calib.inference.likelihood import RowLikelihood, VelocityRows
from calib.model.entries import Entries
from calib.model.unfinished import UnfinishedTally, unfinished_record, warn_unfinished

# Budget and presets are re-exported: the fit driver's API in one place
__all__ = ["ESTIMATE_MARGIN_SD", "Budget", "ModelFit", "ModelRun", "calibrate", "crsp_prior_box",
           "fit_model", "point_estimate", "presets", "unfinished_remedy"]

ESTIMATE_MARGIN_SD = 2.0  # MC sds by which the posterior mode must beat the gradient point


@dataclasses.dataclass
class ModelFit:
    """Everything one model's calibration produced (``unfinished``: the counts of
    unfinished blocks per stage and the warning, ``calib.model.unfinished.unfinished_record``)."""

    names: tuple[str, ...]
    estimate: np.ndarray
    estimate_source: str
    posterior: Posterior | None
    gradient: GradientFit | None
    emulator_check: dict | None
    quality: list[dict]
    check_sizes_m: np.ndarray
    check_runouts: np.ndarray
    timings_s: dict
    budget: Budget
    unfinished: dict | None = None
    adequacy: dict | None = None
    focus: dict | None = None
    chain_screen: dict | None = None
    estimate_choice: dict | None = None


def _row_entries(forward, obs: Observations) -> Entries:
    """The forward model's entries with the entry of every row: its own
    ``Entries.index`` (entries made from the rows, ``Entries.from_rows``), or,
    where it has none, one entry per distinct size of the rows (``obs.size_index``)."""
    entries = forward.entries
    if entries.index is not None:
        if entries.index.shape != (obs.n_obs,):
            raise ValueError(f"the forward model's entries map {entries.index.shape[0]} rows, "
                             f"the observations have {obs.n_obs}")
        return entries
    if not np.array_equal(entries.sizes_m, obs.sizes_m):
        raise ValueError("forward must be built on the rows' entries (Entries.from_rows or "
                         "Entries.one_per_size) or on one entry per distinct size of the rows")
    return dataclasses.replace(entries, index=obs.size_index)


def calibrate(forward, obs: Observations, key: jax.Array, methods: tuple[str, ...],
              budget: Budget, progress: Callable[[str, int, int], None] | None = None,
              extra_sizes_m=(), velocities: VelocityRows | None = None) -> ModelFit:
    """Run the stages of the module docstring for one forward model.

    Every row is scored against the blocks of its entry of the forward model
    (``forward.entries.index``: a (size, release) group of
    ``calib.model.entries.Entries.from_rows``); a forward without a row index
    has one entry per distinct size of the rows, every row of a size scored
    against its size's blocks.

    Args:
        forward: ``CrspForward`` or ``DemForward`` built on the rows' entries.
        obs: observations.
        key: PRNG key of the fit (common random numbers, directions, NUTS, check).
        methods: subset of ("gradient", "bayes").
        budget: stage sizes.
        progress: optional callable(stage, done, total).
        extra_sizes_m: more block sizes to simulate in the check (for figures);
            ``ModelFit.check_sizes_m`` lists every size checked, simulated at
            the median of the rows' releases (``ModelFit.check_runouts``).
        velocities: passage-velocity rows (CRSP; ``VelocityRows``, each reading
            an entry of the forward model, which records speeds at their
            stations), scored with the runout rows in every summed
            log-likelihood (the designs, the log-likelihood GP that NUTS
            samples, the chain screen, the adequacy check's best design
            point); the runout-quantile emulator (the pilot posteriors of the
            design waves) and the check's fit quality per row score the runout
            rows. The gradient stage fits runouts only and is refused with them.
    """
    if velocities is not None and "gradient" in methods:
        raise ValueError("the gradient stage fits runout rows only: with passage speeds "
                         "the fit is Bayesian (method 'bayes')")
    if velocities is not None and tuple(getattr(forward, "stations_x_m", ())) != \
            velocities.stations_x_m:
        raise ValueError("the forward model must record passage speeds at the rows' stations")
    entries = _row_entries(forward, obs)
    k_design, k_grad, k_nuts, k_pilot, k_check = jax.random.split(key, 5)
    tick = progress or (lambda *a: None)
    timings, posterior, gfit, emu_check, design = {}, None, None, None, None
    focus_record = chain_screen = None
    rows = RowLikelihood(obs, entries.index, velocities)
    box = forward.box
    sizes = np.unique(np.concatenate([obs.sizes_m, np.asarray(extra_sizes_m, float)]))
    tallies = {}

    def tally(stage, runouts, theta=None, sizes_m=forward.sizes_m):
        t = tallies.setdefault(stage, UnfinishedTally(tuple(map(float, sizes_m))))
        t.add(runouts, theta, tuple(box.names))

    if "bayes" in methods:
        posterior, emu_check, focus_record, chain_screen, design = bayes_stage(
            forward, rows, budget, (k_design, k_pilot, k_nuts), tick, tally, timings)

    if "gradient" in methods:
        t0 = time.perf_counter()
        gfit = gradient_stage(forward, rows, budget, k_grad, tick, tally, design)
        timings["gradient_s"] = time.perf_counter() - t0

    estimate, source, choice = point_estimate(forward, rows, gfit, posterior)
    t0 = time.perf_counter()
    check = check_estimate(forward, entries, obs, rows, estimate, sizes, budget.n_check,
                           k_check, tally)
    timings["check_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scored = ((design.theta, design.ll)
              if design is not None and hasattr(forward, "from_input")  # CRSP: theta space
              else None)
    mode_ll = None  # the mode's score, where the estimate's choice already simulated it
    if choice is not None:
        v = choice["posterior_mode"]["loglik"]
        mode_ll = -np.inf if v is None else v
    adequacy = fit_adequacy(forward, obs, rows, posterior, estimate, check.at_rows, scored,
                            budget, jax.random.fold_in(k_check, 1), tally, mode_ll)
    timings["adequacy_s"] = time.perf_counter() - t0
    record = unfinished_record(tallies, f"{type(forward).__name__} calibration",
                               unfinished_remedy(forward))
    warn_unfinished(record)
    return ModelFit(tuple(box.names), np.asarray(estimate), source, posterior, gfit, emu_check,
                    check.quality, sizes, check.runouts, timings, budget, record, adequacy,
                    focus_record, chain_screen, choice)


def point_estimate(forward, rows: RowLikelihood, gfit: GradientFit | None,
                   posterior: Posterior | None) -> tuple[np.ndarray, str, dict | None]:
    """The fit's point estimate, its source and, where both stages ran, the record
    of the choice between them.

    The gradient stage's end point (stage 2), unless the posterior's mode (its
    highest-density draw) fits the rows clearly better: both are simulated
    with the forward model's own blocks (common random numbers) and scored by
    the rows' summed log-likelihood l; the mode replaces the gradient point
    when l_mode - l_gradient > ``ESTIMATE_MARGIN_SD`` sqrt(v_mode + v_gradient),
    v the bootstrap Monte Carlo variance of each score
    (``RowLikelihood.noise_var``). Our rule: the point a user reads as "the
    estimate" must not be one the fit's own simulations score clearly below
    another point it found. Why (measured on the Tschamut runs, all 62, seeds
    1-3, 2026-12-05): from its starts and 40 steps the gradient stage ended
    at -300, -300 and -293 nats (the check's blocks) where the posterior's
    mode scored -287, -274 and -275 (the design's), at points outside the
    posterior's 90 % intervals (phi_r 38.9 and 39.4 deg against 29.5-35.8
    and 35.0-37.4); scored with the same blocks, seed 1's two points gave
    -297.2 and -287.1 (docs/studies.md, "The point estimate").

    Returns:
        (estimate (d,), "gradient" or "posterior_mode", record or None): the
        record holds both points' summed log-likelihoods and Monte Carlo sds,
        the margin and the choice.
    """
    if gfit is None:
        return np.asarray(posterior.map), "posterior_mode", None
    if posterior is None:
        return np.asarray(gfit.theta), "gradient", None
    thetas = np.stack([np.asarray(gfit.theta, float), np.asarray(posterior.map, float)])
    sims = rows.simulate(forward, thetas)
    ll, var = rows.summed(*sims), rows.noise_var(*sims)
    margin = ESTIMATE_MARGIN_SD * float(np.sqrt(var.sum()))
    mode_wins = bool(np.isfinite(ll[1]) and (not np.isfinite(ll[0]) or ll[1] - ll[0] > margin))
    finite = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731  (JSON)
    record = {"rule": (f"the posterior's mode replaces the gradient stage's point when the "
                       f"simulator scores it higher by more than {ESTIMATE_MARGIN_SD:g} Monte "
                       "Carlo sds of the difference (the forward model's blocks)"),
              "gradient": {"loglik": finite(ll[0]), "mc_sd": float(np.sqrt(var[0]))},
              "posterior_mode": {"loglik": finite(ll[1]), "mc_sd": float(np.sqrt(var[1]))},
              "margin_nats": margin, "chosen": "posterior_mode" if mode_wins else "gradient"}
    return thetas[int(mode_wins)], record["chosen"], record


def unfinished_remedy(forward) -> str:
    """What a fit's warning about unfinished blocks tells its user to raise: the
    DEM's simulated time per block (``calib.fit --dem-max-time-s``, the forward
    model's ``run``), else CRSP's event budget."""
    run = getattr(forward, "run", None)  # the DEM's numerics (calib.model.dem_run)
    if run is None:
        return "raise CRSP's event budget (Settings.max_events)"
    return (f"give the DEM's blocks more simulated time (calib.fit --dem-max-time-s; "
            f"this fit: {run.max_time_s:g} s)")


class ModelRun(NamedTuple):
    """One model's calibration on a data set (``fit_model``).

    Attributes:
        fit: the stages' results (``ModelFit``).
        forward: the forward model fitted (``calib.model.forward.CrspForward`` or
            ``DemForward``: its prior box, entries and, for the DEM, run numerics).
        alpha_form: the DEM's damping law ("power" or "constant"); None for CRSP.
    """

    fit: ModelFit
    forward: object
    alpha_form: str | None


def crsp_prior_box(rolling_resistance: str, profile, entries: Entries, effects=()):
    """CRSP's prior box of a fit (without the effects' columns, which
    ``CrspForward`` appends): ``CRSP_ROLLING_BOX`` ("fit"), ``CRSP_BOX``
    ("profile") or one angle per zone of the profiles ("zones",
    ``zoned_rolling_box``); the one angle of "fit" starts at the flattest slope
    of the profiles that carry rows where that is steeper than the published
    range (``calib.model.priors.rest_possible_box``), unless an effect adds
    rolling resistance. A ``NoRestError`` where no angle of the box lets a block
    rest on them."""
    from calib.model import priors
    from calib.model.effects import rest_possible_base

    profiles = [p for p in (q if q is not None else profile for q in entries.profiles)
                if p is not None]
    box = {"fit": priors.CRSP_ROLLING_BOX, "profile": priors.CRSP_BOX}.get(rolling_resistance) \
        or priors.zoned_rolling_box(dict.fromkeys(
            z for pr in (profile, *profiles) if pr is not None for z in pr.zone_names))
    return rest_possible_base(box, list({id(p): p for p in profiles}.values()), tuple(effects))


def fit_model(model: str, inputs, entries: Entries, key: jax.Array, *,
              methods: tuple[str, ...] = ("gradient", "bayes"), quick: bool = False,
              rolling_resistance: str = "fit", effects: tuple[str, ...] = (),
              alpha_law: str = "power", dem_run=None,
              progress: Callable[[str, int, int], None] | None = None) -> ModelRun:
    """Calibrate one model on a data set's rows, as ``python -m calib.fit`` does.

    Builds the forward model on the rows' ``entries`` with the preset budget
    (``presets(model, quick)``) and runs ``calibrate``; the check also simulates
    the sizes of the runout-vs-size figure (CRSP: six sizes from 0.2 to 2.0 m,
    geometric; DEM: 0.2, 0.9, 2.0 m quick, else 0.2, 0.5, 0.9, 1.4, 2.0 m). A DEM
    fit is not yet checked against the consumers' alpha-law rule: that is
    ``calib.model.alpha_law.check_fit``, which ``calib.fit.run_fit`` applies.

    Args:
        model: "crsp" or "dem".
        inputs: the data set (``calib.files.inputs.Inputs``); with passage
            speeds (``Inputs.speeds``, CRSP only) they are fitted with the
            runouts, their blocks simulated as ``Entries.with_speed_entries``
            says, and the fit is Bayesian (``calibrate``'s ``velocities``).
        entries: what the rows make the solvers simulate (``Inputs.entries``).
        key: PRNG key of this model's fit.
        methods: subset of ("gradient", "bayes").
        quick: the small budgets (``calib.inference.budget.QUICK``).
        rolling_resistance: CRSP's prior box: "fit" (``CRSP_ROLLING_BOX``, one
            rolling resistance angle), "zones" (one angle per material zone of
            the profiles, ``zoned_rolling_box``) or "profile" (``CRSP_BOX``:
            the profile's angles).
        effects: CRSP candidate effects switched on (``calib.model.effects``).
        alpha_law: DEM damping law, "power" or "constant".
        dem_run: the DEM's numerics (``calib.model.dem_run.DemRun``; None:
            ``DEM_RUN``), recorded with the fit.
        progress: optional callable(stage, done, total).
    """
    from calib.model.forward import CrspForward, DemForward

    budget = presets(model, quick)
    profile = inputs.profile
    vel_rows, stations, velocities = None, (), inputs.speeds
    if velocities is not None:
        if model != "crsp":
            raise ValueError("passage speeds are fitted with the crsp model only")
        entries, vel_entry = entries.with_speed_entries(velocities.block_size_m)
        vel_rows = VelocityRows.of(velocities, vel_entry)
        stations = vel_rows.stations_x_m
    if model == "crsp":
        box = crsp_prior_box(rolling_resistance, profile, entries, effects)
        forward = CrspForward(profile, entries, budget.n_blocks_design,
                              jax.random.fold_in(key, 1), box=box,
                              effect=tuple(effects) or "none",  # columns after box's
                              stations_x_m=stations,
                              rolling_threshold_m_s=inputs.site.rolling_threshold_m_s)
        extra = np.geomspace(0.2, 2.0, 6)  # the check's sizes for the runout-vs-size figure
    else:
        forward = DemForward(profile, entries, budget.n_blocks_design,
                             jax.random.fold_in(key, 1), form=alpha_law,
                             **({} if dem_run is None else {"run": dem_run}))
        extra = [0.2, 0.9, 2.0] if quick else [0.2, 0.5, 0.9, 1.4, 2.0]
    fit = calibrate(forward, inputs.obs, jax.random.fold_in(key, 2), methods, budget, progress,
                    extra_sizes_m=extra, velocities=vel_rows)
    return ModelRun(fit, forward, alpha_law if model == "dem" else None)
