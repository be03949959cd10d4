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
      is dropped (``chains.screen_chains``). While the diagnostics still fail, or
      the GP's predictions at those draws disagree with the simulator
      (``loglik_emulator.at_posterior``), the re-simulated draws join the
      log-likelihood GP's design and NUTS runs again (at most
      ``MAX_REFINE`` times): the GP learns the simulator where the chains
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
2. Gradient (``method`` includes "gradient"): Adam on the smoothed CRN
   objective of the SIMULATOR itself (``calib.inference.gradient``) from several starts:
   J(theta) = -sum_i log p(y_i | theta), the negative log-likelihood of
   ``calib.inference.likelihood`` with ``n_blocks_grad`` blocks per size. The
   starts: the box's centre, ``grad_starts - 1`` quasi-random points and (CRSP
   after a design) the design point with the highest simulated likelihood.
3. Check: the point estimate is re-simulated with fresh random numbers
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

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import ndtr

from calib.files.observations import Observations
from calib.inference.adequacy import adequacy_record, better_design_point
from calib.inference.bayes import Posterior, run_nuts
from calib.inference.chains import chain_starts, screen_chains
from calib.inference.design_waves import focus_design, second_design, sir_draws
from calib.inference.emulator import fit_emulator, holdout_error
from calib.inference.focus import (
    MAX_WIDEN,
    cut_faces,
    face_problems,
    focus_boxes,
    region_record,
    widen,
)
from calib.inference.gradient import GradientFit, fit_gradient
from calib.inference.likelihood import log_likelihood, observed_rows
from calib.inference.loglik_emulator import (
    at_posterior,
    fit_loglik_emulator,
    loglik_holdout,
    loglik_noise_var,
    summed_loglik,
)
from calib.inference.predictive_check import pool_draws
from calib.inference.realisations import realisation_check
from calib.model.entries import Entries
from calib.model.forward import CrspForward, release_rolling_deg
from calib.model.forward import release_slopes_deg as _release_slopes_deg
from calib.model.unfinished import UnfinishedTally, unfinished_record, warn_unfinished
from solvers.percentiles import few_blocks

__all__ = ["Budget", "ModelFit", "calibrate", "fit_quality", "presets"]


@dataclasses.dataclass(frozen=True)
class Budget:
    """Sizes of every stage (blocks are per parameter point and block size)."""

    n_design: int = 96
    n_design2: int = 64
    n_design3: int = 64
    n_blocks_design: int = 256
    n_levels: int = 10
    nuts_warmup: int = 500
    nuts_samples: int = 1000
    nuts_chains: int = 4
    n_realisations: int = 32
    realisation_waves: int = 3
    grad_starts: int = 3
    grad_steps: int = 40
    grad_k: int = 3
    n_blocks_grad: int = 256
    n_check: int = 2000
    n_predictive_draws: int = 32
    n_blocks_predictive: int = 64


def presets(model: str, quick: bool) -> Budget:
    """Stage sizes per model (``--quick`` for tests; the default for real use)."""
    if model == "crsp":
        if quick:
            return Budget(n_design=48, n_design2=32, n_design3=32, n_blocks_design=128,
                          nuts_warmup=200, nuts_samples=400, nuts_chains=2, grad_starts=2,
                          grad_steps=8, grad_k=2, n_blocks_grad=64, n_check=128,
                          n_predictive_draws=16, n_blocks_predictive=32,
                          realisation_waves=1)
        # twice the draws of the DEM's: with the log-likelihood GP NUTS costs ~15-20 s
        # (was ~160 s on Postignano, ~760 s on Tschamut), and the CRSP posteriors of
        # both sites mix slowly (Postignano seed 0: R-hat 1.016-1.023 at 1,000 draws
        # per chain, 1.010-1.013 at 2,000)
        return Budget(nuts_warmup=1000, nuts_samples=2000)
    if model == "dem":
        if quick:
            return Budget(n_design=8, n_design2=0, n_design3=0, n_blocks_design=4, nuts_warmup=200,
                          nuts_samples=400, nuts_chains=2, grad_starts=1, grad_steps=2,
                          grad_k=1, n_blocks_grad=4, n_check=4, n_predictive_draws=2,
                          n_blocks_predictive=2)
        return Budget(n_design=16, n_design2=0, n_design3=0, n_blocks_design=12, grad_starts=2,
                      grad_steps=8, grad_k=1, n_blocks_grad=8, n_check=16,
                      n_predictive_draws=4, n_blocks_predictive=4)
    raise ValueError(f"unknown model {model!r}")


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


def _median_kernel_var_m2(obs: Observations) -> float:
    """Median over rows of the kernel variance the likelihood gives one sample:
    the tolerance sd^2 of a point row, the smallest kernel width h^2 (0.5 m) of
    an interval row (``calib.inference.likelihood``)."""
    return float(np.median(np.where(obs.is_interval, 0.5**2, np.nan_to_num(obs.runout_sd_m)**2)))


def _loglik_of_runouts(obs: Observations, index=None):
    """runouts (T, S, n) -> pointwise log-likelihood (T, n_obs) (jitted); row i
    reads simulated entry ``index[i]`` (default ``obs.size_index``)."""
    y, sd, lo, hi, is_int = observed_rows(obs)
    idx = jnp.asarray(obs.size_index if index is None else index)

    @jax.jit
    def f(runouts):
        return jax.vmap(lambda r: log_likelihood(r[idx], y, sd, lo, hi, is_int))(runouts)

    return f


def _emulated_loglik(obs: Observations, emu, forward, inflation: float, index=None):
    """theta (d,) -> pointwise log-likelihood (n_obs,) from the emulator (row i:
    entry ``index[i]`` of the forward model, default ``obs.size_index``)."""
    y, sd, lo, hi, is_int = observed_rows(obs)
    idx = jnp.asarray(obs.size_index if index is None else index)

    def f(theta):
        mean, var = emu.predict(forward.emulator_inputs(theta))
        return log_likelihood(mean[idx], y, sd, lo, hi, is_int, inflation * var[idx])

    return f


def fit_quality(obs: Observations, runouts: np.ndarray, index=None) -> list[dict]:
    """Per-observation fit: simulated 5/50/95 % runouts, PIT and log-likelihood.

    Args:
        runouts: (S, n) runouts per simulated entry, m; NaN for an unfinished
            block (left out).
        index: (n_obs,) entry of each row (default ``obs.size_index``: one entry
            per distinct size, ``obs.sizes_m``).

    PIT = P(R + e <= y), e ~ N(0, sd^2), for a point (the predictive CDF of the
    OBSERVED value, tolerance included) (about uniform on [0, 1] if the model is right;
    below 0.05 or above 0.95 means the observation lies outside the simulated
    90 % band) and P(a <= R <= b) for an interval; all over the finished blocks
    (``sim_n_finished`` of them). With none, the simulated values are None;
    ``sim_few_blocks`` is True where 1 to 19 blocks finished, too few for the
    5/95 % values (``solvers.percentiles.few_blocks``).
    """
    index = obs.size_index if index is None else np.asarray(index)
    ll = np.asarray(_loglik_of_runouts(obs, index)(jnp.asarray(runouts)[None]))[0]
    out = []
    for i in range(obs.n_obs):
        r = runouts[index[i]]
        r = r[np.isfinite(r)]
        some = r.size > 0
        q05, q50, q95 = (map(float, np.quantile(r, [0.05, 0.5, 0.95])) if some
                         else (None,) * 3)
        row = {"row": i + 1, "block_size_m": float(obs.block_size_m[i]),
               "sim_q05_m": q05, "sim_median_m": q50, "sim_q95_m": q95,
               "sim_n_finished": int(r.size), "sim_few_blocks": bool(some and few_blocks(r.size)),
               "loglik": float(ll[i]) if np.isfinite(ll[i]) else None}
        if obs.is_interval[i]:
            a, b = obs.runout_min_m[i], obs.runout_max_m[i]
            row.update(observed_min_m=float(a), observed_max_m=float(b),
                       p_in_interval=float(np.mean((r >= a) & (r <= b))) if some else None)
        else:
            y, sd = obs.runout_m[i], obs.runout_sd_m[i]
            pit = float(np.mean(ndtr((y - r) / sd))) if some else None
            row.update(observed_m=float(y), observed_sd_m=float(obs.runout_sd_m[i]), pit=pit,
                       in_90_band=bool(some and 0.05 <= pit <= 0.95))
        out.append(row)
    return out


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


def _check_entries(entries: Entries, sizes_m: np.ndarray) -> tuple[Entries, np.ndarray]:
    """What the check simulates: first the figure's sizes ``sizes_m`` at the
    median of the rows' releases, on the command's profile, with the solver's
    release speed and height, then every entry of the rows that is not one of
    these.

    Returns:
        the check's entries (E,), and the check entry of each of ``entries`` (G,).
    """
    median = float(np.median(entries.release_x_m[entries.index]))
    figure = Entries.at_sizes(sizes_m, median, density_kg_m3=entries.density_kg_m3)
    at = np.empty(entries.n, int)
    own = []
    for g in range(entries.n):
        if (entries.release_x_m[g] == median and np.isnan(entries.release_speed_m_s[g])
                and np.isnan(entries.release_height_m[g]) and entries.profiles[g] is None):
            at[g] = int(np.searchsorted(sizes_m, entries.sizes_m[g]))
        else:
            at[g] = len(sizes_m) + len(own)
            own.append(g)
    return (figure.concat(entries.take(own)) if own else figure), at


def calibrate(forward, obs: Observations, key: jax.Array, methods: tuple[str, ...],
              budget: Budget, progress: Callable[[str, int, int], None] | None = None,
              extra_sizes_m=()) -> ModelFit:
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
    """
    entries = _row_entries(forward, obs)
    index = entries.index
    k_design, k_grad, k_nuts, k_pilot, k_check = jax.random.split(key, 5)
    tick = progress or (lambda *a: None)
    timings, posterior, gfit, emu_check, x, design_ll = {}, None, None, None, None, None
    focus_record = chain_screen = None
    loglik_runs = _loglik_of_runouts(obs, index)
    box = forward.box
    sizes = np.unique(np.concatenate([obs.sizes_m, np.asarray(extra_sizes_m, float)]))
    tallies = {}

    def tally(stage, runouts, theta=None, sizes_m=forward.sizes_m):
        t = tallies.setdefault(stage, UnfinishedTally(tuple(map(float, sizes_m))))
        t.add(runouts, theta, tuple(box.names))

    if "bayes" in methods:
        posterior, emu_check, focus_record, chain_screen, x, design_ll = _bayesian(
            forward, obs, index, loglik_runs, budget, (k_design, k_pilot, k_nuts), tick, tally,
            timings)

    if "gradient" in methods:
        t0 = time.perf_counter()
        grad_forward = dataclasses.replace(forward, n_blocks=budget.n_blocks_grad, key=k_grad)

        def objective(theta):
            runs = grad_forward.runouts(theta)
            tally("gradient", runs, theta)
            return -np.asarray(loglik_runs(jnp.asarray(runs))).sum(1)

        from scipy.stats import qmc

        starts = [0.5 * (box.lo + box.hi)]
        if budget.grad_starts > 1:
            z = qmc.Halton(box.dim, scramble=True, seed=1).random(budget.grad_starts - 1)
            starts += list(box.from_unit(0.15 + 0.7 * z))
        if design_ll is not None and hasattr(forward, "from_input") and \
                np.isfinite(design_ll).any():
            # one more start at the design's best simulated point: where the
            # likelihood is peaked in a thin part of the box, the box's centre and
            # a few quasi-random starts may all lie on its flat part
            starts.append(np.clip(forward.from_input(x[int(np.argmax(design_ll))]),
                                  box.lo, box.hi))
        gfit = fit_gradient(objective, box, np.array(starts), k_grad, n_steps=budget.grad_steps,
                            k=budget.grad_k,
                            progress=lambda i: tick("gradient", i + 1, budget.grad_steps))
        timings["gradient_s"] = time.perf_counter() - t0

    if gfit is not None:
        estimate, source = gfit.theta, "gradient"
    else:
        estimate, source = posterior.map, "posterior_mode"
    t0 = time.perf_counter()
    checked, entry = _check_entries(entries, sizes)
    runs = dataclasses.replace(forward, entries=checked, n_blocks=budget.n_check,
                               key=k_check).runouts(estimate[None])[0]
    tally("check", runs[None], estimate[None], checked.sizes_m)
    check, at_rows = runs[:len(sizes)], runs[entry]
    quality = fit_quality(obs, at_rows, index)
    better = None
    if design_ll is not None and hasattr(forward, "from_input"):  # CRSP: theta-space design
        fitted = {"estimate": float(summed_loglik(loglik_runs, at_rows[None])[0])}
        if posterior is not None:  # its mode with the design's own blocks
            fitted["posterior mode"] = float(summed_loglik(
                loglik_runs, forward.runouts(posterior.map[None]))[0])
        better = better_design_point(box.names, forward.from_input(x), design_ll, fitted,
                                     obs.n_obs)
    timings["check_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    adequacy = _adequacy(forward, obs, posterior, at_rows, budget,
                         jax.random.fold_in(k_check, 1), tally, index, better, estimate)
    timings["adequacy_s"] = time.perf_counter() - t0
    record = unfinished_record(tallies, f"{type(forward).__name__} calibration")
    warn_unfinished(record)
    return ModelFit(tuple(box.names), np.asarray(estimate), source, posterior, gfit, emu_check,
                    quality, sizes, check, timings, budget, record, adequacy, focus_record,
                    chain_screen)


def _bayesian(forward, obs: Observations, index, loglik_runs, budget: Budget, keys, tick,
              tally, timings: dict):
    """Stage 1 of the module docstring: designs, emulator, NUTS, chain screening and
    (CRSP) the focus region, widened while the posterior piles against one of
    its faces (at most ``focus.MAX_WIDEN`` times), then refined while the
    diagnostics fail or the GP is wrong at the screened draws
    (``loglik_emulator.at_posterior``; at most ``MAX_REFINE`` times: the
    screened draws join the GP's design, ``bayes.focus.refined``); a GP still
    wrong there is a problem of the posterior.

    Returns:
        (posterior, emulator check, focus record or None, chain-screen record or
        None, design inputs (D, d), their summed simulated log-likelihoods (D,)).
    """
    k_design, k_pilot, k_nuts = keys
    box = forward.box
    t0 = time.perf_counter()
    tick("design", 0, 1)
    x, r = forward.design(budget.n_design, seed=int(jax.random.randint(k_design, (), 0,
                                                                          2**31 - 1)))
    design_ll = summed_loglik(loglik_runs, r)
    tick("design", 1, 1)
    tally("design", r)
    timings["design_s"] = time.perf_counter() - t0
    ibox = forward.input_box

    refined = np.zeros(len(x), bool)  # points of the refinement waves

    def add_simulated(theta, runs, refinement=False):
        nonlocal x, r, design_ll, refined
        design_ll = np.concatenate([design_ll, summed_loglik(loglik_runs, runs)])
        x = np.concatenate([x, np.asarray(forward.to_input(theta))])
        r = np.concatenate([r, runs])
        refined = np.concatenate([refined, np.full(len(runs), refinement)])

    def simulate_more(theta):
        runs = forward.runouts(theta)
        tally("design", runs, theta)
        add_simulated(theta, runs)

    def inside():
        return np.all((x >= ibox.lo - 1e-9) & (x <= ibox.hi + 1e-9), axis=1)

    if budget.n_design2 > 0:
        t0 = time.perf_counter()
        emu = fit_emulator(x, r, ibox.lo, ibox.hi, budget.n_levels)
        tick("design2", 0, 1)
        simulate_more(second_design(forward, _emulated_loglik(obs, emu, forward, 1.0, index),
                                     forward.from_input(x), design_ll, budget.n_design2,
                                     k_pilot))
        tick("design2", 1, 1)
        timings["design2_s"] = time.perf_counter() - t0
    nuts_box, focus_record, chain_screen = box, None, None
    focus = (focus_boxes(forward, forward.from_input(x), design_ll, obs.n_obs)
             if budget.n_design3 > 0 and hasattr(forward, "from_input") else None)
    if focus is not None:
        t0 = time.perf_counter()
        ibox, nuts_box, focus_record = focus
        k_fill, k_sir, k_widen = jax.random.split(jax.random.fold_in(k_pilot, 1), 3)
        n_sir = budget.n_design3 // 2
        tick("design3", 0, 2)
        simulate_more(focus_design(forward, ibox, nuts_box, budget.n_design3 - n_sir, k_fill))
        tick("design3", 1, 2)
        if n_sir:
            keep = inside()
            emu = fit_emulator(x[keep], r[keep], ibox.lo, ibox.hi, budget.n_levels)
            simulate_more(sir_draws(forward, _emulated_loglik(obs, emu, forward, 1.0, index),
                                     ibox, nuts_box, n_sir, k_sir))
        tick("design3", 2, 2)
        timings["design3_s"] = time.perf_counter() - t0
        focus_record["widened"], focus_record["refined"] = [], []
        focus_record["realisation_waves"] = []
    timings["emulator_s"] = timings["nuts_s"] = 0.0
    if focus is not None:
        timings["realisations_s"] = 0.0
    n_widened = n_nuts = 0
    screened = None
    while True:
        t0 = time.perf_counter()
        keep = inside() if focus is not None else np.ones(len(x), bool)
        x_emu, r_emu, ll_emu = x[keep], r[keep], design_ll[keep]
        if focus is not None:  # a GP of the summed log-likelihood (calib.inference.loglik_emulator)
            noise = loglik_noise_var(loglik_runs, r_emu)
            level_of = ~refined[keep]
            emu_check = loglik_holdout(x_emu, ll_emu, noise, ibox.lo, ibox.hi, obs.n_obs,
                                       level_of=level_of)
            lemu = fit_loglik_emulator(x_emu, ll_emu, noise, ibox.lo, ibox.hi, obs.n_obs,
                                       level_of)

            def target(theta, lemu=lemu):
                return lemu.predict(forward.to_input(theta))[0][None]
        else:  # GPs of the runout quantiles (calib.inference.emulator)
            emu_check = holdout_error(x_emu, r_emu, ibox.lo, ibox.hi, budget.n_levels,
                                      kernel_var_m2=_median_kernel_var_m2(obs))
            emu = fit_emulator(x_emu, r_emu, ibox.lo, ibox.hi, budget.n_levels)
            target = _emulated_loglik(obs, emu, forward, emu_check["variance_inflation"], index)
        emu_check["n_design"] = int(x_emu.shape[0])
        emu_check["n_blocks_per_point"] = int(r_emu.shape[-1])
        timings["emulator_s"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        n_nuts += 1  # each run its own bar, numbered (re-runs after refinement or waves)
        tick(f"nuts run {n_nuts}", 0, 1)
        posterior = run_nuts(target, nuts_box, k_nuts, budget.nuts_warmup, budget.nuts_samples,
                             budget.nuts_chains,
                             loglik_kind="summed" if focus is not None else "pointwise",
                             init=(None if focus is None else
                                   chain_starts(forward.from_input(x_emu), ll_emu, nuts_box,
                                                 budget.nuts_chains)))
        if hasattr(forward, "from_input") and posterior.n_chains > 1:
            def screen_runs(theta):
                runs = forward.runouts(theta)
                tally("screen", runs, theta)
                return runs

            posterior, chain_screen, screened = screen_chains(posterior, screen_runs,
                                                               loglik_runs, obs.n_obs)
        tick(f"nuts run {n_nuts}", 1, 1)
        timings["nuts_s"] += time.perf_counter() - t0
        if focus is None:
            break
        emu_there = None
        if screened is not None:  # the GP against the simulator at the screened draws
            emu_there = at_posterior(lemu, np.asarray(forward.to_input(screened[0])),
                                     summed_loglik(loglik_runs, screened[1]),
                                     loglik_noise_var(loglik_runs, screened[1]))
            focus_record["at_posterior"] = emu_there
        faces = cut_faces(posterior.samples, nuts_box, box)
        if not faces or n_widened == MAX_WIDEN:
            wrong_there = emu_there is not None and not emu_there["ok"]
            if ((posterior.ok and not wrong_there) or screened is None
                    or len(focus_record["refined"]) == MAX_REFINE):
                if budget.n_realisations == 0:
                    break
                # how far the GP's own uncertainty could move the posterior
                # (calib.inference.realisations); while it could move it
                # beyond the intervals, simulate where the realisations put
                # their posteriors, and emulate and sample again
                t0 = time.perf_counter()
                waves = focus_record["realisation_waves"]
                record, spread, pts = realisation_check(
                    lemu, forward.to_input, nuts_box, posterior.samples, tuple(box.names),
                    jax.random.fold_in(jax.random.fold_in(k_nuts, 7), len(waves)),
                    budget.n_realisations, draw=len(waves) < budget.realisation_waves)
                if pts is None:
                    focus_record["realisations"] = record
                    posterior.problems += spread
                    posterior.ok = posterior.ok and not spread
                    timings["realisations_s"] += time.perf_counter() - t0
                    break
                tick("realisation waves", len(waves), budget.realisation_waves)
                runs = forward.runouts(pts)
                tally("design", runs, pts)
                waves.append({**record, "n_points": int(len(pts)),
                              "problems_before": list(posterior.problems) + spread})
                add_simulated(pts, runs, refinement=True)
                tick("realisation waves", len(waves), budget.realisation_waves)
                timings["realisations_s"] += time.perf_counter() - t0
                continue
            # the chains do not agree (or mix too slowly), or the GP is wrong
            # where they sit: it is taught the simulated log-likelihood there,
            # and NUTS runs again
            focus_record["refined"].append({
                "n_points": int(screened[0].shape[0]),
                "problems_before": list(posterior.problems),
                "emulator_at_posterior": emu_there,
                "chain_loglik": chain_screen["chain_loglik"]})
            add_simulated(*screened, refinement=True)
            continue
        # the posterior piles against a face the focus region drew, not the prior:
        # move that face out, fill the new slab, emulate and sample again
        t0 = time.perf_counter()
        ibox, nuts_box, slabs = widen(forward, ibox, faces)
        focus_record["widened"].append([{"parameter": box.names[i], "side": side,
                                         "posterior_mass_at_face": mass}
                                        for i, side, mass in faces])
        per = max(2, (budget.n_design3 // 2) // len(slabs))
        for j, slab in enumerate(slabs):
            simulate_more(focus_design(forward, slab, nuts_box, per,
                                        jax.random.fold_in(k_widen, 16 * n_widened + j)))
        n_widened += 1
        timings["design3_s"] += time.perf_counter() - t0
    if focus is not None:
        focus_record["n_emulator_points"] = int(inside().sum())
        focus_record.update(region_record(nuts_box, box))  # after any widening
        cut = face_problems(posterior.samples, nuts_box, box)
        there = focus_record.get("at_posterior")
        if there is not None and not there["ok"]:
            cut.append(f"the log-likelihood GP is wrong where the posterior sits: at "
                       f"{len(screened[0])} of its draws it promised a median of "
                       f"{there['emulated_median_nats']:.1f} nats, the simulator gave "
                       f"{there['simulated_median_nats']:.1f} (RMS z {there['z_rms']:.1f} > "
                       f"{there['z_max']:.0f})")
        posterior.problems += cut
        posterior.ok = posterior.ok and not cut
    return posterior, emu_check, focus_record, chain_screen, x, design_ll


MAX_REFINE = 2  # refinement waves: screened draws added to the log-likelihood GP


def _adequacy(forward, obs: Observations, posterior: Posterior | None, check: np.ndarray,
              budget: Budget, key: jax.Array, tally, index, better: dict | None = None,
              estimate=None) -> dict:
    """``calib.inference.adequacy`` of one fit: posterior predictive runouts at
    ``n_predictive_draws`` draws spread evenly over the chains' output, with
    ``n_blocks_predictive`` fresh blocks per draw and size; without a posterior,
    the check's runouts at the point estimate (plug-in). CRSP: with the rolling
    resistance angle at each release of every draw (or of the estimate), for
    the rows that stall at their release (``adequacy_record``)."""
    release = forward.entries.release_x_m
    slopes_deg = _release_slopes_deg(forward.profile, release, forward.entries.profiles)

    def rolling(theta):
        if not isinstance(forward, CrspForward) or theta is None:
            return None
        return release_rolling_deg(forward.box.names, theta, forward.profile, forward.entries)

    if posterior is None:
        return adequacy_record(None, forward.box, obs, check,
                               f"plug-in at the point estimate, {check.shape[-1]} blocks "
                               "per size (no posterior)", index, release, slopes_deg, better,
                               rolling(None if estimate is None else np.atleast_2d(estimate)))
    n = posterior.samples.shape[0]
    pick = np.linspace(0, n - 1, min(budget.n_predictive_draws, n)).round().astype(int)
    draws = posterior.samples[pick]
    pred = dataclasses.replace(forward, n_blocks=budget.n_blocks_predictive, key=key)
    runs = pred.runouts(draws)  # (T, S, n)
    tally("predictive", runs, draws)
    return adequacy_record(posterior.samples, forward.box, obs, pool_draws(runs),
                           f"posterior predictive, {len(pick)} draws x "
                           f"{budget.n_blocks_predictive} blocks per size", index, release,
                           slopes_deg, better, rolling(draws))
