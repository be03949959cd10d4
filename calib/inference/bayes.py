"""Bayesian calibration: NumPyro NUTS on the emulated likelihood, with diagnostics.

Model (uniform priors from ``calib.model.priors``; likelihood from
``calib.inference.likelihood`` with the emulated quantiles of ``calib.inference.emulator`` as the
simulated sample and the emulator's variance added):

    theta ~ Uniform(box),
    log p(D | theta) = sum_i log p(y_i | Q_{s(i)}(theta), v_{s(i)}(theta)).

The emulator makes the log-density smooth, so NUTS (Hoffman & Gelman 2014)
applies; NUTS on the raw simulator would not (discontinuous, noisy).

Diagnostics (``chain_diagnostics``; Vehtari, Gelman, Simpson, Carpenter &
Buerkner 2021, "Rank-normalization, folding, and localization: an improved
R-hat for assessing convergence of MCMC", Bayesian Analysis 16, 667-718),
computed by ArviZ (``arviz_stats``) on the C chains of N draws:

* rank-normalised split R-hat: each chain is split in half (2C chains of
  n = N/2), the S = CN pooled draws are replaced by their normal scores
  z = Phi^-1((rank - 3/8) / (S + 1/4)), and R-hat = sqrt(var+ / W) with
  var+ = (n - 1)/n W + B/n (W: mean within-chain variance, B: n times the
  variance of the chain means) is computed on z and on the folded draws
  |theta - median|; the larger of the two is reported;
* bulk ESS: the effective sample size of the rank-normalised split chains;
  tail ESS: the smaller of the ESS of the indicators I(theta <= q_0.05) and
  I(theta <= q_0.95).

Thresholds (the paper's recommendation, which calibrates the 1.01 rule for the
rank-normalised statistic; the classic split R-hat with 1.1 misses chains
with different tails or scales): R-hat < 1.01 and bulk and tail ESS > 400
for every parameter (100 per chain with 4 chains), no divergent transition.
A run that misses one is returned with ``ok = False`` and the reasons; the
command prints them loudly and records them in calibration.json; it never
hides them.

A run whose chains agree but had divergent transitions (``careful_run``) is
run again by the fit with a smaller step size (``CAREFUL_TARGET_ACCEPT``); a
divergence in that run still fails it.

A run whose chains agree but are too short for the ESS threshold
(``draw_factor``) is run again longer by the fit
(``calib.inference.bayes_stage``): ESS = S / tau, with tau the integrated
autocorrelation time of the chains (the paper's section 3), a property of
the sampler on that density and not of the run's length, so the draws the
threshold needs follow from the ESS the run reached.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.infer import MCMC, NUTS

from calib.model.priors import Box

__all__ = ["CAREFUL_TARGET_ACCEPT", "ESS_MIN", "MAX_DRAW_FACTOR", "Posterior", "RHAT_MAX",
           "TARGET_ACCEPT", "careful_run", "chain_diagnostics", "diagnosed", "draw_factor",
           "keep_chains", "run_nuts"]

RHAT_MAX = 1.01
ESS_MIN = 400.0
TAIL_PROB = 0.05  # tail ESS: the 5 % and 95 % quantiles
MAX_DRAW_FACTOR = 4  # draw_factor: at most this many times the draws (our choice)
_ESS_MARGIN = 1.25  # draw_factor: aim 25 % above ESS_MIN, for the ESS estimate's own error
# NUTS's target acceptance probability during warm-up (Stan's adapt_delta): the step
# size adapts until proposals are accepted at this rate. 0.9 by default (our choice,
# above Stan's 0.8); CAREFUL_TARGET_ACCEPT where a run's only sampler problem is
# divergent transitions (``careful_run``): a larger target gives a smaller step size
# and fewer divergences, the repair Stan's documentation gives for them ("increase
# adapt_delta ... to a value closer to 1 (e.g. from 0.95 to 0.99)", rstanarm's
# ``adapt_delta`` page, citing the Stan Reference Manual), at the cost of more
# leapfrog steps per draw.
TARGET_ACCEPT = 0.9
CAREFUL_TARGET_ACCEPT = 0.99

# NumPyro's extra fields -> ArviZ's sample_stats names (``arviz_base.from_numpyro``'s)
_SAMPLE_STATS = {"diverging": "diverging", "accept_prob": "acceptance_rate",
                 "num_steps": "n_steps", "energy": "energy",
                 "potential_energy": "lp", "adapt_state.step_size": "step_size"}


@dataclasses.dataclass
class Posterior:
    """Posterior draws and diagnostics.

    Attributes:
        names: parameter names.
        samples: (n_chains * n_samples, d) draws, chain after chain.
        log_density: (n,) unnormalised log posterior of each draw.
        pointwise_loglik: (n, n_obs) log-likelihood of each row at each draw.
        rhat, ess_bulk, ess_tail: (d,) rank-normalised split R-hat, bulk and
            tail effective sample size (``chain_diagnostics``).
        divergences: number of divergent transitions.
        accept_prob: mean acceptance probability.
        ok: all diagnostics pass; ``problems`` lists those that do not.
        n_chains: chains; ``samples`` reshapes to (n_chains, n_samples, d).
        sample_stats: ArviZ name -> (n_chains, n_samples) per-draw sampler
            statistics (diverging, acceptance_rate, n_steps, energy, lp =
            minus NumPyro's potential energy: the log density in the sampler's
            unconstrained coordinates, so it includes the log-Jacobian of the
            box's transform and differs from ``log_density`` by a function of
            theta, step_size).
        loglik_kind: "pointwise" (``pointwise_loglik`` has one column per
            observation row), "summed" (one column: the emulated summed
            log-likelihood, ``calib.inference.loglik_emulator``) or "expected"
            (one column: the log of the posterior averaged over the quantile
            emulator's realisations less the log prior,
            ``calib.inference.quantile_realisations``).
    """

    names: tuple[str, ...]
    samples: np.ndarray
    log_density: np.ndarray
    pointwise_loglik: np.ndarray
    rhat: np.ndarray
    ess_bulk: np.ndarray
    ess_tail: np.ndarray
    divergences: int
    accept_prob: float
    ok: bool
    problems: list[str]
    n_chains: int = 1
    sample_stats: dict = dataclasses.field(default_factory=dict)
    loglik_kind: str = "pointwise"

    @property
    def map(self) -> np.ndarray:
        """Highest-posterior-density draw (a MAP approximation)."""
        return self.samples[int(np.argmax(self.log_density))]

    @property
    def criteria(self) -> dict:
        """The diagnostics this posterior was judged by (recorded with it)."""
        return {"rhat": "rank-normalised split R-hat (Vehtari et al. 2021)",
                "rhat_max": RHAT_MAX, "ess": "bulk and tail ESS (same paper)",
                "ess_min": ESS_MIN}

    def summary(self) -> dict:
        q05, q50, q95 = np.quantile(self.samples, [0.05, 0.5, 0.95], axis=0)
        mean = self.samples.mean(axis=0)
        return {n: {"map": float(self.map[i]), "mean": float(mean[i]),
                    "median": float(q50[i]), "q05": float(q05[i]), "q95": float(q95[i]),
                    "rhat": float(self.rhat[i]), "ess_bulk": float(self.ess_bulk[i]),
                    "ess_tail": float(self.ess_tail[i])}
                for i, n in enumerate(self.names)}


def chain_diagnostics(draws: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rank-normalised split R-hat, bulk ESS and tail ESS of each parameter.

    Args:
        draws: (C, N, d) C chains of N draws of d parameters.

    Returns:
        (rhat, ess_bulk, ess_tail), each (d,); the equations are in the module
        docstring (Vehtari et al. 2021), computed by
        ``arviz_stats``. One chain is passed as its two halves.
    """
    from arviz_stats.base import array_stats

    x = np.asarray(draws, dtype=np.float64)
    if x.shape[0] == 1:  # one chain: its two halves as two chains (ArviZ needs two)
        half = x.shape[1] // 2
        x = x[0, :2 * half].reshape(2, half, x.shape[2])
    kw = {"chain_axis": 0, "draw_axis": 1}
    rhat = np.asarray(array_stats.rhat(x, method="rank", **kw))
    bulk = np.asarray(array_stats.ess(x, method="bulk", **kw))
    tail = np.asarray(array_stats.ess(x, method="tail", prob=TAIL_PROB, **kw))
    return rhat, bulk, tail


def run_nuts(pointwise_loglik: Callable[[jax.Array], jax.Array], box: Box, key: jax.Array,
             num_warmup: int = 500, num_samples: int = 1000, num_chains: int = 4,
             loglik_kind: str = "pointwise", init: np.ndarray | None = None,
             target_accept_prob: float = TARGET_ACCEPT) -> Posterior:
    """Sample theta ~ p(theta | D) with NUTS.

    Args:
        pointwise_loglik: theta (d,) -> (n_obs,) log-likelihoods; must be smooth
            and jit-able (the emulated likelihood).
        box: uniform prior.
        key: PRNG key.
        num_warmup, num_samples, num_chains: NUTS settings (chains vectorised).
        loglik_kind: what ``pointwise_loglik`` returns: "pointwise" (n_obs,),
            "summed" or "expected" (1,) (``Posterior.loglik_kind``).
        init: (num_chains, d) starting points inside the box; None: NumPyro's
            default (uniform in (-2, 2) in the unconstrained coordinates).
        target_accept_prob: the acceptance rate the step size adapts to
            (``TARGET_ACCEPT``; ``CAREFUL_TARGET_ACCEPT`` where divergences are
            repaired).
    """
    lo, hi = jnp.asarray(box.lo), jnp.asarray(box.hi)
    # NumPyro also runs the model on concrete values, outside its sampler's
    # jit (to find the sample sites): there the likelihood runs as one
    # compiled program, not as its operations compiled one by one. Wherever
    # the model is traced (the sampler, NumPyro's gradients) the likelihood is
    # traced as it is, so the draws are those of the un-jitted likelihood.
    loglik = jax.jit(pointwise_loglik)

    def model():
        theta = numpyro.sample("theta", dist.Uniform(lo, hi).to_event(1))
        f = pointwise_loglik if isinstance(theta, jax.core.Tracer) else loglik
        numpyro.factor("loglik", jnp.sum(f(theta)))

    mcmc = MCMC(NUTS(model, target_accept_prob=target_accept_prob), num_warmup=num_warmup,
                num_samples=num_samples, num_chains=num_chains, chain_method="vectorized",
                progress_bar=False)
    if init is not None:
        width = hi - lo
        init = {"theta": jnp.clip(jnp.asarray(init, jnp.float64), lo + 1e-6 * width,
                                  hi - 1e-6 * width)}
    mcmc.run(key, extra_fields=tuple(_SAMPLE_STATS), init_params=init)
    by_chain = np.asarray(mcmc.get_samples(group_by_chain=True)["theta"])  # (C, N, d)
    extra = {_SAMPLE_STATS[k]: np.asarray(v)
             for k, v in mcmc.get_extra_fields(group_by_chain=True).items()}
    extra["lp"] = -extra["lp"]  # NumPyro's potential energy is minus the log density
    samples = by_chain.reshape(-1, box.dim)
    pw = np.asarray(jax.jit(jax.vmap(pointwise_loglik))(jnp.asarray(samples)))
    logd = pw.sum(axis=1)  # + log prior, constant inside the box
    return diagnosed(tuple(box.names), by_chain, logd, pw, extra, loglik_kind)


def diagnosed(names: tuple[str, ...], by_chain: np.ndarray, log_density: np.ndarray,
              pointwise: np.ndarray, sample_stats: dict, loglik_kind: str) -> Posterior:
    """A ``Posterior`` of chains (C, N, d), with its diagnostics and problems."""
    rhat, ess_bulk, ess_tail = chain_diagnostics(by_chain)
    div = int(np.sum(sample_stats["diverging"]))
    acc = float(np.mean(sample_stats["acceptance_rate"]))
    problems = []
    for i, n in enumerate(names):
        if not np.isfinite(rhat[i]) or rhat[i] >= RHAT_MAX:
            problems.append(f"R-hat of {n} is {rhat[i]:.3f} (>= {RHAT_MAX})")
        for kind, ess in (("bulk", ess_bulk), ("tail", ess_tail)):
            if not np.isfinite(ess[i]) or ess[i] < ESS_MIN:
                problems.append(f"{kind} ESS of {n} is {ess[i]:.0f} (< {ESS_MIN:.0f})")
    if div:
        problems.append(f"{div} divergent transitions")
    return Posterior(names, by_chain.reshape(-1, len(names)), log_density, pointwise, rhat,
                     ess_bulk, ess_tail, div, acc, not problems, problems, by_chain.shape[0],
                     sample_stats, loglik_kind)


def draw_factor(post: Posterior, n_chains: int) -> int:
    """How many times its draws per chain a NUTS run needs for its ESS to pass,
    where ESS is all it fails; 1 where it is not.

    The run's chains must agree and be whole: every R-hat below ``RHAT_MAX``,
    no divergent transition, and ``n_chains`` chains (none dropped by a
    screening). Its smallest bulk or tail ESS E below ``ESS_MIN`` then asks for
    k = ceil(1.25 ESS_MIN / E) times the draws (ESS = S / tau, module
    docstring; the 25 % margin covers the error of E itself). Our rule: k above
    ``MAX_DRAW_FACTOR`` (E below 125 of ``ESS_MIN`` 400) gives 1, since chains
    that slow are better repaired where the density is wrong (the fit's
    refinements) than by running them longer."""
    ess = float(min(np.min(post.ess_bulk), np.min(post.ess_tail)))
    if (not _chains_agree(post) or post.divergences or post.n_chains < n_chains
            or not np.isfinite(ess) or ess >= ESS_MIN or ess <= 0.0):
        return 1
    k = int(np.ceil(_ESS_MARGIN * ESS_MIN / ess))
    return k if k <= MAX_DRAW_FACTOR else 1


def careful_run(post: Posterior, n_chains: int) -> bool:
    """Whether a NUTS run's divergent transitions are what a run with a smaller
    step size (``CAREFUL_TARGET_ACCEPT``) should repair: it has divergences, its
    chains agree (every R-hat below ``RHAT_MAX``) and all ``n_chains`` of them
    are kept. Chains that disagree or were dropped are repaired where the
    density is wrong (the fit's refinements), not by a smaller step. Our rule,
    after Stan's advice for divergences (``TARGET_ACCEPT``)."""
    return bool(post.divergences > 0 and _chains_agree(post) and post.n_chains >= n_chains)


def _chains_agree(post: Posterior) -> bool:
    """Every parameter's R-hat finite and below ``RHAT_MAX``."""
    return bool(np.all(np.isfinite(post.rhat)) and np.all(post.rhat < RHAT_MAX))


def keep_chains(post: Posterior, keep) -> Posterior:
    """The posterior of the chains ``keep`` ((C,) bool) alone, diagnostics
    recomputed on them (with one chain, R-hat compares its two halves)."""
    keep = np.asarray(keep, bool)
    n = post.samples.shape[0] // post.n_chains
    rows = np.repeat(keep, n)
    return diagnosed(post.names,
                     post.samples.reshape(post.n_chains, n, -1)[keep],
                     post.log_density[rows], post.pointwise_loglik[rows],
                     {k: np.asarray(v)[keep] for k, v in post.sample_stats.items()},
                     post.loglik_kind)
