"""Simulation budgets: how much every stage of the toolkit's fits simulates.

One module for every budget, with its presets:

* ``Budget`` and ``presets(model, quick)``: the stages of a calibration
  (``calib.inference.calibrate``), the default of ``python -m calib.fit`` and
  its ``--quick`` budget (tests, a first look);
* ``DiscoveryBudget`` and ``discovery_budget(model, quick, n_blocks)``: the
  candidate fits of the discrepancy workflow (``calib.discovery.discrepancy``,
  ``python -m calib.discover`` and ``calib.power``).

Blocks are per parameter point and simulated entry (``calib.model.entries``).
"""

from __future__ import annotations

import dataclasses

__all__ = ["DISCOVERY_PRESETS", "MAX_DESIGN_SCALE", "Budget", "DiscoveryBudget",
           "discovery_budget", "has_scalable_design", "presets", "scaled_design"]


@dataclasses.dataclass(frozen=True)
class Budget:
    """Sizes of every stage (blocks are per parameter point and block size).

    ``refinements``: how many times, at most, NUTS runs again after draws of a
    run that failed its diagnostics (or where the log-likelihood GP was wrong)
    were simulated and joined the GP's design (``calib.inference.bayes_stage``).
    """

    n_design: int = 96
    n_design2: int = 64
    n_design3: int = 64
    n_blocks_design: int = 256
    n_levels: int = 10
    nuts_warmup: int = 500
    nuts_samples: int = 1000
    nuts_chains: int = 4
    refinements: int = 2
    n_realisations: int = 32
    # waves of n_realisations points while the realisation check fails. Measured on
    # all 62 Tschamut runs (docs/studies.md, "Twelve realisation waves"): seed 1's
    # posterior left a ridge 15 nats below the simulator's best region only after its
    # fifth wave; with 12 the seeds' posteriors agree with the simulator's own. Each
    # wave costs one NUTS run and 32 simulated points (about 30 s there on 2 cores).
    realisation_waves: int = 12
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
        # the check at the estimate and the posterior predictive each simulate 32
        # blocks per size: their 5/50/95 % runouts need 20
        # (solvers.percentiles.few_blocks); 32 fills one DEM call (DemForward.lane_batch)
        return Budget(n_design=16, n_design2=0, n_design3=0, n_blocks_design=12, grad_starts=2,
                      grad_steps=8, grad_k=1, n_blocks_grad=8, n_check=32,
                      n_predictive_draws=8, n_blocks_predictive=4)
    raise ValueError(f"unknown model {model!r}")


@dataclasses.dataclass(frozen=True)
class DiscoveryBudget:
    """Simulation budget of one candidate fit of the discrepancy workflow
    (``calib.discovery.discrepancy``).

    Attributes:
        n_sobol: points of the Sobol stage.
        n_warm: points of the warm stage (effects only).
        n_refine: points of each adaptive stage.
        n_blocks: blocks per (design point, size class), common random numbers.
        n_draws: posterior draws re-simulated for the predictive (fresh blocks).
        n_blocks_check: blocks per (draw, size class) of that predictive.
        k_folds: folds of the held-out score (leave-one-out below this many rows).
        noise_reps: independent block sets at the best design point that measure
            the Monte Carlo sd of the summed log-likelihood (``loglik_noise_sd``);
            below 2 it is skipped, as it is for forward models without
            ``replicates`` (the DEM's).
        smooth_loglik: weight the adaptive design's points by their summed
            log-likelihood smoothed by the log-likelihood GP, and fit each
            adaptive stage's proposal to that GP's posterior
            (``calib.discovery.candidate_fit``; one GP fit per stage and fit,
            3-5 minutes of a 60-row run at the default budget on 2 cores);
            off, by the simulated sums (the quick budgets: a first look
            whose folds' k-hats are flagged anyway).
        n_fold_refine, fold_rounds: with ``smooth_loglik``, after the adaptive
            stages, up to ``fold_rounds`` rounds of one stage of
            ``n_fold_refine`` points per fold whose training weights' k-hat
            lies above the bar min(0.7, 1 - 1/log10 S) (drawn where that
            fold's posterior lives; ``calib.discovery.candidate_fit``).
        n_fold_draws: with ``smooth_loglik``, a fold still above that bar
            after the rounds is scored on this many fresh draws from its
            training posterior under the log-likelihood GP, each simulated
            (``calib.discovery.candidate_fit``); 0: its importance-weighted
            score stays, flagged.
    """

    n_sobol: int = 128
    n_warm: int = 128
    n_refine: tuple[int, ...] = (64, 64, 64, 64)
    n_blocks: int = 128
    n_draws: int = 16
    n_blocks_check: int = 128
    k_folds: int = 5
    noise_reps: int = 8
    smooth_loglik: bool = True
    n_fold_refine: int = 64
    fold_rounds: int = 2
    n_fold_draws: int = 64

    @property
    def n_design(self) -> int:
        """Points of the main design (the fold stages, when needed, add to it)."""
        return self.n_sobol + self.n_warm + sum(self.n_refine)


DISCOVERY_PRESETS = {
    "crsp": DiscoveryBudget(),
    "crsp-quick": DiscoveryBudget(n_sobol=32, n_warm=32, n_refine=(32, 32), n_blocks=32,
                                  n_draws=8, n_blocks_check=64, smooth_loglik=False,
                                  fold_rounds=0),
    "dem": DiscoveryBudget(n_sobol=0, n_warm=0, n_refine=(), n_blocks=8, n_draws=8,
                           n_blocks_check=0, noise_reps=0, fold_rounds=0),
    "dem-quick": DiscoveryBudget(n_sobol=0, n_warm=0, n_refine=(), n_blocks=4, n_draws=8,
                                 n_blocks_check=0, noise_reps=0, fold_rounds=0),
}


# the largest factor on a discovery design's points (the GP fits grow as the cube of them)
MAX_DESIGN_SCALE = 8.0


def discovery_budget(model: str, quick: bool = False,
                     n_blocks: int | None = None) -> DiscoveryBudget:
    """The preset budget of ``model`` ("crsp" or "dem"; ``DISCOVERY_PRESETS``), with
    ``n_blocks`` blocks per (design point, size class) if given (at least 2: the
    kernel width needs a spread). Candidates with their own ``n_blocks`` (the
    DEM's fragmentation) keep it."""
    budget = DISCOVERY_PRESETS[model + ("-quick" if quick else "")]
    if n_blocks is None:
        return budget
    if n_blocks < 2:
        raise ValueError(f"expected an integer of at least 2, got {n_blocks}")
    return dataclasses.replace(budget, n_blocks=n_blocks)


def has_scalable_design(budget: DiscoveryBudget) -> bool:
    """Whether ``scaled_design`` can add points to the budget's designs: not for
    a fixed grid (the DEM candidates', ``n_sobol`` 0)."""
    return budget.n_sobol > 0


def scaled_design(budget: DiscoveryBudget, factor: float) -> DiscoveryBudget:
    """``budget`` with the points of its main design (the Sobol, warm and adaptive
    stages) multiplied by ``factor`` (1 to ``MAX_DESIGN_SCALE``), each rounded to
    an integer; the fold stages keep theirs.

    Why a factor on the design and not only more blocks (measured in
    docs/studies.md, "The noise measured where the weight lies, and eight times
    the blocks"): on the 62 Tschamut runs, twice the design points brought 19
    of 20 folds' Pareto k-hats below the bar (18 at the default), while eight
    times the blocks per point sharpened the posterior and left 1 of the
    baseline's and size dissipation's 10 folds below; on 180 synthetic rows
    with a forest belt, 34 of 40 (28 at the default), but the named belt's
    own five folds rose above the bar.
    A fixed-grid design (the DEM's, ``n_sobol`` 0) has no points to scale:
    refused."""
    if not (1.0 <= factor <= MAX_DESIGN_SCALE):
        raise ValueError(f"expected a number from 1 to {MAX_DESIGN_SCALE:g}, got {factor:g}")
    if not has_scalable_design(budget):
        raise ValueError("the dem candidates run on fixed grids, which have no points to "
                         "scale (crsp only)")
    return dataclasses.replace(
        budget, n_sobol=round(budget.n_sobol * factor), n_warm=round(budget.n_warm * factor),
        n_refine=tuple(round(n * factor) for n in budget.n_refine))
