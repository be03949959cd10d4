"""The Monte Carlo noise of a design's summed log-likelihood: measured at a
point over independent block sets, and carried to every design point.

The likelihood of ``calib.inference.likelihood`` is a simulation estimate, so
the summed log-likelihood of a design point carries Monte Carlo noise. The
discovery workflow measures it at the Sobol stage's best point
(``measured_noise_var``) and tells the log-likelihood GP that smooths its
importance weights that noise at every point (``calib.discovery.candidate_fit``).
"""

from __future__ import annotations

import jax
import numpy as np

from calib.inference.budget import DiscoveryBudget
from calib.model.unfinished import UnfinishedTally

__all__ = ["loglik_noise_sd", "measured_noise_var"]


def measured_noise_var(fw, loglik, theta, budget: DiscoveryBudget, key, tallies, names) -> float:
    """The variance (nats^2) of the summed log-likelihood at ``theta`` over
    ``noise_reps`` independent block sets (``loglik_noise_sd``), the noise the
    smoothing of the weights assumes at every design point; 0 (the GP's nugget
    alone) for forward models without ``replicate_sims`` or fewer than 2 reps."""
    if budget.noise_reps < 2 or not hasattr(fw, "replicate_sims"):
        return 0.0
    reps = fw.replicate_sims(theta, budget.noise_reps, jax.random.fold_in(key, 4))
    tallies.setdefault("noise", UnfinishedTally(tallies["design"].sizes_m))
    tallies["noise"].add(reps[0], np.broadcast_to(theta, (budget.noise_reps, theta.size)), names)
    return loglik_noise_sd(loglik(*reps)) ** 2


def loglik_noise_sd(loglik_reps: np.ndarray) -> float:
    """Monte Carlo sd (nats) of the summed log-likelihood, from (R, n_obs)
    pointwise values at one theta under R independent block sets.

    The likelihood is a simulation estimate (``calib.inference.likelihood``), so its
    logarithm carries noise that grows with the number of rows and falls
    roughly as 1 / sqrt(n_blocks) (measured on 180 rows of null data at the
    baseline's best point: 3.4 nats with 128 blocks, 1.7 with 512). With R = 8
    the sd itself is uncertain by about 1 / sqrt(2 (R - 1)) = 27 %.

    How large is too large, by analogy with pseudo-marginal MCMC (Doucet, Pitt,
    Deligiannidis & Kohn 2015, "Efficient implementation of Markov chain Monte
    Carlo when using an unbiased likelihood estimator", Biometrika 102,
    295-313): there the cost-optimal sd of the log-likelihood estimator is
    about 1.0-1.7 nats. Importance weights carrying independent log-normal noise
    of sd s lose a factor exp(s^2) of their ESS (E[w^2] / E[w]^2 = exp(s^2) for
    log-normal w). Within one fit the design points share their blocks (common
    random numbers), so what moves the weights is the noise of log-likelihood
    DIFFERENCES, small between close points and up to sqrt(2) times this sd
    between distant ones; the CRN surface is also rough (jumps of several nats between neighbouring
    roughness values were measured at 180 rows). Candidates are fitted with
    different block sets, so their score gains carry noise of this order that
    the data se of the gain does not include.
    """
    total = np.asarray(loglik_reps, float).sum(axis=1)
    return float(np.std(total, ddof=1))
