"""The Bayesian stage of a calibration: designs, emulator, NUTS, and their repairs.

``bayes_stage`` runs stage 1 of ``calib.inference.calibrate``'s docstring for one
forward model:

a. a first design (``forward.design``) and, where the budget asks, a second
   one drawn from a pilot posterior of the runout-quantile emulator
   (``calib.inference.design_waves.Design``);
b. CRSP: the focus region (``calib.inference.focus``) and its own design;
c. emulate (``calib.inference.loglik_emulator`` inside the focus region,
   ``calib.inference.emulator`` elsewhere; for the DEM's one input per size, the
   posterior averaged over that emulator's realisations,
   ``calib.inference.quantile_realisations``, drawn from its grid) and sample
   the rest with NUTS (``calib.inference.bayes``), chains screened against the
   simulator (``calib.inference.chains``);
d. CRSP, until settled: widen a focus face the posterior piles against (at
   most ``focus.MAX_WIDEN`` times); where a design point's simulated
   log-likelihood beats every chain's by more than ``best_point_bar``, narrow
   the focus region to the points near the best one, fill it and sample again
   (``_Stage._best_point_wave``; at most ``Budget.refinements`` times); while
   the diagnostics fail or the GP is wrong at the screened draws, add those
   draws to the GP's design and sample again (at most ``Budget.refinements``
   times); then, while the GP's realisations move the posterior beyond its
   intervals, simulate one point per realisation and sample again
   (``calib.inference.realisations``); then, where the chains agree but had
   divergent transitions, sample once more with a smaller step size
   (``calib.inference.bayes.careful_run``, ``_Stage._careful_run``); last,
   where the chains agree but fall short of the ESS threshold, sample once
   more with as many times the draws as ``calib.inference.bayes.draw_factor``
   asks (``_Stage._longer_run``).

The simulated design is a ``Design`` (``calib.inference.design_waves``), which
simulates every wave the steps ask for and scores it with the rows' likelihood
(``calib.inference.likelihood.RowLikelihood``); the focus region is a
``FocusRegion`` (``calib.inference.focus``), which widens itself and fills the
slabs it uncovers; the rest of the stage's state (the emulators, the posterior,
the records) lives in one ``_Stage`` object whose methods are the steps above.
"""

from __future__ import annotations

import time

import jax
import numpy as np
from scipy.stats import chi2

from calib.inference.bayes import (
    CAREFUL_TARGET_ACCEPT,
    ESS_MIN,
    TARGET_ACCEPT,
    careful_run,
    draw_factor,
    run_nuts,
)
from calib.inference.chains import chain_starts, screen_chains
from calib.inference.design_waves import Design
from calib.inference.emulator import fit_emulator, holdout_error
from calib.inference.focus import MAX_WIDEN, FocusRegion
from calib.inference.loglik_emulator import at_posterior, fit_loglik_emulator, loglik_holdout
from calib.inference.quantile_realisations import expected_posterior, sample_expected
from calib.inference.realisations import realisation_check

__all__ = ["bayes_stage", "best_point_bar"]


class _Stage:
    """The Bayesian stage's state and steps (module docstring)."""

    def __init__(self, forward, rows, budget, keys, tick, tally, timings: dict):
        self.forward, self.rows = forward, rows
        self.budget, self.tick, self.tally, self.timings = budget, tick, tally, timings
        self.k_design, self.k_pilot, self.k_nuts = keys
        self.box = forward.box
        self.region = self.chain_screen = self.screened = self.lemu = None
        self.posterior = self.emu_check = None
        self.n_nuts = 0
        self.draw_factor = 1  # NUTS draws per chain: budget.nuts_samples times this
        self.target_accept = TARGET_ACCEPT  # NUTS's step-size target (_careful_run)

    @property
    def ibox(self):
        """The emulator's box: the focus region's (``FocusRegion.input_box``), or the prior's."""
        return self.forward.input_box if self.region is None else self.region.input_box

    @property
    def nuts_box(self):
        """The box NUTS samples: the focus region's (``FocusRegion.box``), or the prior."""
        return self.box if self.region is None else self.region.box

    # -- a, b: the designs ----------------------------------------------------
    def first_designs(self) -> None:
        b = self.budget
        t0 = time.perf_counter()
        self.tick("design", 0, 1)
        self.design = Design(self.forward, self.rows, self.tally, b.n_design, seed=int(
            jax.random.randint(self.k_design, (), 0, 2**31 - 1)))
        self.tick("design", 1, 1)
        self.timings["design_s"] = time.perf_counter() - t0
        if b.n_design2 > 0:
            t0 = time.perf_counter()
            self.tick("design2", 0, 1)
            self.design.second_wave(b.n_levels, b.n_design2, self.k_pilot)
            self.tick("design2", 1, 1)
            self.timings["design2_s"] = time.perf_counter() - t0

    def focus_region(self) -> bool:
        """CRSP: the focus region and its design; False where there is none."""
        b, fw, design = self.budget, self.forward, self.design
        if b.n_design3 > 0 and hasattr(fw, "from_input"):
            self.region = FocusRegion.around(fw, design, self.rows.n_rows)
        if self.region is None:
            return False
        t0 = time.perf_counter()
        k_fill, k_sir, self.k_widen = jax.random.split(jax.random.fold_in(self.k_pilot, 1), 3)
        n_sir = b.n_design3 // 2
        self.tick("design3", 0, 2)
        design.fill(self.ibox, self.nuts_box, b.n_design3 - n_sir, k_fill)
        self.tick("design3", 1, 2)
        if n_sir:
            design.sir_wave(self.ibox, self.nuts_box, b.n_levels, n_sir, k_sir)
        self.tick("design3", 2, 2)
        self.timings["design3_s"] = time.perf_counter() - t0
        self.region.record.update(refined=[], realisation_waves=[])
        return True

    # -- c: emulate and sample ------------------------------------------------
    def emulate(self, focus: bool):
        """The density NUTS samples, and the design points it was fitted on."""
        t0 = time.perf_counter()
        d = self.design
        keep = d.inside(self.ibox) if focus else np.ones(len(d.x), bool)
        x_emu, r_emu, ll_emu = d.x[keep], d.r[keep], d.ll[keep]
        if focus:  # a GP of the summed log-likelihood (calib.inference.loglik_emulator)
            noise = self.rows.noise_var(r_emu, None if d.v is None else d.v[keep])
            level_of = ~d.refined[keep]
            self.emu_check = loglik_holdout(x_emu, ll_emu, noise, self.ibox.lo, self.ibox.hi,
                                            self.rows.n_rows, level_of=level_of)
            lemu = self.lemu = fit_loglik_emulator(x_emu, ll_emu, noise, self.ibox.lo,
                                                   self.ibox.hi, self.rows.n_rows, level_of)

            def target(theta, lemu=lemu):
                return lemu.predict(self.forward.to_input(theta))[0][None]
            self.loglik_kind = "summed"
        else:  # GPs of the runout quantiles (calib.inference.emulator)
            self.emu_check = holdout_error(x_emu, r_emu, self.ibox.lo, self.ibox.hi,
                                           self.budget.n_levels,
                                           kernel_var_m2=self.rows.kernel_var_m2)
            emu = fit_emulator(x_emu, r_emu, self.ibox.lo, self.ibox.hi, self.budget.n_levels)
            inflation = self.emu_check["variance_inflation"]
            if emu.x_unit.shape[1] == 1:  # the DEM's alpha per size: averaged over realisations
                target, self.expected_grid, self.emu_check["expected_posterior"] = (
                    expected_posterior(emu, self.forward.emulator_inputs, self.rows,
                                       self.nuts_box, jax.random.fold_in(self.k_pilot, 2),
                                       inflation))
                self.loglik_kind = "expected"
            else:
                target = self.rows.emulated(emu, self.forward.emulator_inputs, inflation)
                self.loglik_kind = "pointwise"
        self.emu_check["n_design"] = int(x_emu.shape[0])
        self.emu_check["n_blocks_per_point"] = int(r_emu.shape[-1])
        self.timings["emulator_s"] += time.perf_counter() - t0
        return target, x_emu, ll_emu

    def sample(self, target, x_emu, ll_emu, focus: bool) -> None:
        """NUTS on ``target``; CRSP: chains screened against the simulator."""
        b, fw = self.budget, self.forward
        t0 = time.perf_counter()
        if self.loglik_kind == "expected":  # drawn from its grid, not by NUTS
            self.tick("posterior draws", 0, 1)
            self.posterior = sample_expected(target, self.expected_grid, tuple(self.box.names),
                                             self.k_nuts, b.nuts_chains, b.nuts_samples)
            self.tick("posterior draws", 1, 1)
            self.timings["draws_s"] = (self.timings.get("draws_s", 0.0)
                                       + time.perf_counter() - t0)
            return
        self.n_nuts += 1  # each run its own bar, numbered (re-runs after refinement or waves)
        self.tick(f"nuts run {self.n_nuts}", 0, 1)
        self.posterior = run_nuts(
            target, self.nuts_box, self.k_nuts, b.nuts_warmup, b.nuts_samples * self.draw_factor,
            b.nuts_chains,
            loglik_kind=self.loglik_kind, target_accept_prob=self.target_accept,
            init=(chain_starts(fw.from_input(x_emu), ll_emu, self.nuts_box, b.nuts_chains)
                  if focus else None))
        if hasattr(fw, "from_input") and self.posterior.n_chains > 1:
            def screen_runs(theta):
                runs, speeds = self.rows.simulate(fw, theta)
                self.tally("screen", runs, theta)
                return runs, speeds

            self.posterior, self.chain_screen, self.screened = screen_chains(
                self.posterior, screen_runs, self.rows)
        self.tick(f"nuts run {self.n_nuts}", 1, 1)
        self.timings["nuts_s"] = self.timings.get("nuts_s", 0.0) + time.perf_counter() - t0

    # -- d: settle --------------------------------------------------------------
    def settled(self) -> bool:
        """One repair step where the posterior needs one (module docstring, d);
        True when none is left to make."""
        emu_there = None
        if self.screened is not None:  # the GP against the simulator at the screened draws
            emu_there = at_posterior(
                self.lemu, np.asarray(self.forward.to_input(self.screened[0])),
                self.rows.summed(*self.screened[1:]), self.rows.noise_var(*self.screened[1:]))
            self.region.record["at_posterior"] = emu_there
        faces = self.region.faces_holding(self.posterior.samples)
        if faces and self.region.n_widened != MAX_WIDEN:
            # the posterior piles against a face the focus region drew, not the
            # prior's: move that face out and fill the new slab
            t0 = time.perf_counter()
            self.region.widen_faces(faces, self.design, self.budget.n_design3 // 2, self.k_widen)
            self.timings["design3_s"] += time.perf_counter() - t0
            return False
        if self.screened is not None and self._best_point_wave():
            return False
        wrong_there = emu_there is not None and not emu_there["ok"]
        if ((self.posterior.ok and not wrong_there) or self.screened is None
                or len(self.region.record["refined"]) >= self.budget.refinements):
            done = self.budget.n_realisations == 0 or self._realisation_wave()
            return done and not self._careful_run() and not self._longer_run()
        # the chains do not agree (or mix too slowly), or the GP is wrong where
        # they sit: it is taught the simulated log-likelihood there
        self.region.record["refined"].append({
            "n_points": int(self.screened[0].shape[0]),
            "problems_before": list(self.posterior.problems),
            "emulator_at_posterior": emu_there,
            "chain_loglik": self.chain_screen["chain_loglik"]})
        self.design.add(*self.screened, refinement=True)
        return False

    def _best_point_wave(self) -> bool:
        """Where the design's best point inside the sampled box beats the best
        chain's median simulated log-likelihood (``chains.screen_chains``) by
        more than ``best_point_bar``, the chains have left (or never reached)
        a mode the design found: the focus region narrows to the design points
        within twice that bar of the best (``FocusRegion.narrow``), ``Budget.
        n_design3 // 2`` new points fill it, and NUTS samples again (at most
        ``Budget.refinements`` such waves). True when a wave was made.

        Our rule: a refocusing of history matching (module ``focus``) with a
        band set by the simulation noise and a likelihood-ratio bound, not by
        the rows' number, applied only where the chains show they need it: a
        mode that many nats below a simulated point holds e^-(that) of its
        mass per unit volume. Measured on a forest belt hidden in 180 runout
        rows and 30 passage speeds (``scripts/hidden_effect_chain.py --effect
        vegetation_belt``, seed 9101): the design's best points sat at the true
        belt (start 122-137 m, -758 to -762 nats, the GP within 3 nats of
        them), while every chain sat at a belt beyond 240 m (-828 nats, the GP
        right there too), the GP between the two falling to -1,150: chains
        started at the best points left them during warm-up and could not come
        back. Points added about the best one alone did not bring them back."""
        waves = self.region.record.setdefault("best_point_waves", [])
        if len(waves) >= self.budget.refinements:
            return False
        d = self.design
        inside = d.inside(self.ibox) & np.isfinite(d.ll)
        chains = [v for v in self.chain_screen["chain_loglik"] if v is not None]
        if not inside.any() or not chains:
            return False
        i = int(np.flatnonzero(inside)[np.argmax(d.ll[inside])])
        noise = float(self.rows.noise_var(d.r[i:i + 1], None if d.v is None
                                          else d.v[i:i + 1])[0])
        bar = best_point_bar(self.box.dim, noise)
        gain = float(d.ll[i] - max(chains))
        if not gain > bar:
            return False
        t0 = time.perf_counter()
        n = max(2, self.budget.n_design3 // 2)
        ibox, box = self.region.narrow(d, 2.0 * bar)
        waves.append({"best_point": dict(zip(self.box.names, map(float, d.theta[i]))),
                      "best_loglik": float(d.ll[i]), "chain_loglik": float(max(chains)),
                      "gain_nats": gain, "bar_nats": bar, "n_points": n})
        d.fill(ibox, box, n, jax.random.fold_in(jax.random.fold_in(self.k_nuts, 11), len(waves)))
        self.timings["design3_s"] += time.perf_counter() - t0
        return True

    def _realisation_wave(self) -> bool:
        """How far the GP's own uncertainty could move the posterior
        (``calib.inference.realisations``); while it could move it beyond the
        intervals, simulate where the realisations put their posteriors.
        True when no wave is needed (or none is left)."""
        b, post = self.budget, self.posterior
        t0 = time.perf_counter()
        waves = self.region.record["realisation_waves"]
        record, spread, pts = realisation_check(
            self.lemu, self.forward.to_input, self.nuts_box, post.samples,
            tuple(self.box.names), jax.random.fold_in(jax.random.fold_in(self.k_nuts, 7),
                                                      len(waves)),
            b.n_realisations, draw=len(waves) < b.realisation_waves)
        if pts is None:
            self.region.record["realisations"] = record
            post.problems += spread
            post.ok = post.ok and not spread
            self.timings["realisations_s"] += time.perf_counter() - t0
            return True
        self.tick("realisation waves", len(waves), b.realisation_waves)
        waves.append({**record, "n_points": int(len(pts)),
                      "problems_before": list(post.problems) + spread})
        self.design.simulate(pts, refinement=True)
        self.tick("realisation waves", len(waves), b.realisation_waves)
        self.timings["realisations_s"] += time.perf_counter() - t0
        return False

    def _careful_run(self) -> bool:
        """Where the last run's chains agree but had divergent transitions
        (``calib.inference.bayes.careful_run``), NUTS samples again, once, with
        the target acceptance ``CAREFUL_TARGET_ACCEPT`` (a smaller step size);
        the realisation check then runs on its draws, and a run that still
        diverges fails its diagnostics as before. True when it will. Measured
        on all 62 Tschamut runs, seed 1 (docs/studies.md, "Divergences
        repaired with a smaller step"): after the third realisation wave R-hat
        was at most 1.002, every chain kept, and 4 divergent transitions failed
        the run."""
        if self.target_accept != TARGET_ACCEPT or self.screened is None:
            return False
        post = self.posterior
        if not careful_run(post, self.budget.nuts_chains):
            return False
        self.target_accept = CAREFUL_TARGET_ACCEPT
        self.region.record["careful_run"] = {
            "target_accept_prob": CAREFUL_TARGET_ACCEPT,
            "target_accept_prob_before": TARGET_ACCEPT,
            "divergences_before": int(post.divergences),
            "problems_before": list(post.problems)}
        return True

    def _longer_run(self) -> bool:
        """Where the last run's chains agree but fall short of the ESS
        threshold (``calib.inference.bayes.draw_factor``), NUTS samples again
        with that many times the draws, once; the realisation check then runs
        on the longer run's draws. True when it will. Measured on all 62
        Tschamut runs, seed 2 (docs/studies.md, "A longer NUTS run where the
        ESS alone falls short"): after the twelfth wave R-hat was at most 1.003
        and every chain kept, and the tail ESS of Kn 385 failed the threshold of
        400; twice the draws gave 717, R-hat at most 1.002."""
        if self.draw_factor > 1 or self.screened is None:
            return False
        post = self.posterior
        k = draw_factor(post, self.budget.nuts_chains)
        if k == 1:
            return False
        self.draw_factor = k
        self.region.record["longer_run"] = {
            "draw_factor": k, "draws_per_chain": self.budget.nuts_samples * k,
            "ess_bulk_min_before": float(post.ess_bulk.min()),
            "ess_tail_min_before": float(post.ess_tail.min()), "ess_min": ESS_MIN,
            "problems_before": list(post.problems)}
        return True

    def finish_focus(self) -> None:
        """The focus region's record, and its problems joined to the posterior's."""
        post = self.posterior
        cut = self.region.finish(post.samples, self.design)
        there = self.region.record.get("at_posterior")
        if there is not None and not there["ok"]:
            cut.append(f"the log-likelihood GP is wrong where the posterior sits: at "
                       f"{len(self.screened[0])} of its draws it promised a median of "
                       f"{there['emulated_median_nats']:.1f} nats, the simulator gave "
                       f"{there['simulated_median_nats']:.1f} (RMS z {there['z_rms']:.1f} > "
                       f"{there['z_max']:.0f})")
        post.problems += cut
        post.ok = post.ok and not cut


def best_point_bar(n_params: int, noise_var: float) -> float:
    """How far, nats, the design's best simulated log-likelihood may lie above
    the best chain's before the chains are taken to have missed its peak:
    half the 99.9 % point of chi-square with ``n_params`` degrees of freedom
    (a likelihood-ratio bound on how far a posterior's bulk lies below its
    mode; the same term as ``adequacy.loglik_gap_nats``) plus three times the
    Monte Carlo sd of the best point's summed log-likelihood (``noise_var``,
    nats^2: the best of a design's noisy values lies above its mean). Our
    choice."""
    return 0.5 * float(chi2.ppf(0.999, n_params)) + 3.0 * float(np.sqrt(max(noise_var, 0.0)))


def bayes_stage(forward, rows, budget, keys, tick, tally, timings: dict):
    """Stage 1 of ``calib.inference.calibrate`` (module docstring).

    Args:
        forward: the forward model.
        rows: the rows' likelihood (``calib.inference.likelihood.RowLikelihood``).
        budget: ``calib.inference.budget.Budget``.
        keys: (design, pilot, NUTS) PRNG keys.
        tick: progress callable(stage, done, total).
        tally: records unfinished blocks per stage.
        timings: stage timings, s (filled in).

    Returns:
        (posterior, emulator check, focus record or None, chain-screen record or
        None, the simulated design: ``calib.inference.design_waves.Design``).
    """
    s = _Stage(forward, rows, budget, keys, tick, tally, timings)
    s.first_designs()
    focus = s.focus_region()
    timings["emulator_s"] = 0.0
    if focus:
        timings["realisations_s"] = 0.0
    while True:
        s.sample(*s.emulate(focus), focus)
        if not focus or s.settled():
            break
    if focus:
        s.finish_focus()
        s.region.record["nuts_runs"] = s.n_nuts
    return (s.posterior, s.emu_check, None if s.region is None else s.region.record,
            s.chain_screen, s.design)
