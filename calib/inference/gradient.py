"""Gradient fitting: a smoothed-gradient estimator with common random numbers + optax.

Why not autodiff: a block's runout is a piecewise-smooth function of the
parameters with many jumps (which facet is hit, when rolling starts, where it
stops), and pathwise derivatives through long contact rollouts are biased at
the jumps and explode with rollout length (Metz et al. 2021; Suh et al. 2022;
NOTES.md measured 10^2-10^200 errors past 1 s on a toy DEM).

What we use instead (randomized smoothing; Nesterov & Spokoiny 2017, Le Lidec
et al. 2022): the objective J(u) is an average over n blocks with COMMON
random numbers (a deterministic function of u, ``calib.model.forward``), and we
descend its Gaussian smoothing J_sigma(u) = E_eps[J(u + sigma eps)], whose
gradient has the antithetic estimator

    g(u) = 1/K sum_k [J(u + sigma eps_k) - J(u - sigma eps_k)] / (2 sigma) eps_k,
    eps_k ~ N(0, I),

unbiased for grad J_sigma and equal to grad J when J is smooth on the scale
sigma. ``tests/test_calib_gradient.py`` proves it on the CRSP objective: the
estimator agrees with central finite differences of the same objective, and
the optimiser converges to the same point from several starts.

u is unconstrained: theta = lo + (hi - lo) sigmoid(u) maps it into the prior
box. The optimiser is optax Adam with a cosine-decayed step; all starts and
all perturbations of one optimiser step go to the simulator as ONE batch.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from calib.model.priors import Box

__all__ = ["GradientFit", "fit_gradient", "gradient_stage", "smoothed_gradient", "theta_of_u",
           "u_of_theta"]


def theta_of_u(box: Box, u):
    """theta = lo + (hi - lo) sigmoid(u)."""
    return box.lo + (box.hi - box.lo) / (1.0 + np.exp(-np.asarray(u, float)))


def u_of_theta(box: Box, theta):
    """Inverse of ``theta_of_u`` (theta strictly inside the box)."""
    z = np.clip(box.to_unit(np.asarray(theta, float)), 1e-6, 1 - 1e-6)
    return np.log(z) - np.log1p(-z)


def _directions(key, n_starts: int, k: int, d: int) -> np.ndarray:
    return np.asarray(jax.random.normal(key, (n_starts, k, d)))


def smoothed_gradient(objective: Callable[[np.ndarray], np.ndarray], u: np.ndarray,
                      sigma: float, key: jax.Array, k: int):
    """Antithetic Gaussian-smoothing gradient at several points at once.

    Args:
        objective: maps a batch (T, d) of unconstrained points to (T,) values;
            called ONCE per gradient (the whole batch goes to the simulator).
        u: (S, d) points (one per start).
        sigma: smoothing scale in u.
        key: PRNG key of the directions.
        k: directions per point (2 k objective values per point).

    Returns:
        (g, j_mean, se): g (S, d) the estimate; j_mean (S,) the mean of the 2 k
        perturbed values (an estimate of J_sigma(u)); se (S, d) the standard
        error of g (spread of the k per-direction terms / sqrt(k)).

    A direction whose two values are not both finite (a point where some block
    size has no finished block has log-likelihood -inf, ``calib.inference.likelihood``) is
    left out of g and se; with none left g is 0 and se infinite.
    """
    u = np.atleast_2d(np.asarray(u, float))
    n_s, d = u.shape
    eps = _directions(key, n_s, k, d)
    pts = np.concatenate([u[:, None] + sigma * eps, u[:, None] - sigma * eps], axis=1)
    vals = np.asarray(objective(pts.reshape(-1, d)), float).reshape(n_s, 2 * k)
    fin = np.isfinite(vals[:, :k]) & np.isfinite(vals[:, k:])  # (S, k)
    if fin.all():
        diff = (vals[:, :k] - vals[:, k:]) / (2 * sigma)
        terms = diff[..., None] * eps  # (S, k, d)
        g = terms.mean(axis=1)
        se = terms.std(axis=1, ddof=1) / np.sqrt(k) if k > 1 else np.full_like(g, np.inf)
        return g, vals.mean(axis=1), se
    plus, minus = np.where(fin, vals[:, :k], 0.0), np.where(fin, vals[:, k:], 0.0)
    terms = ((plus - minus) / (2 * sigma))[..., None] * eps * fin[..., None]
    m = fin.sum(axis=1)[:, None]  # (S, 1) usable directions
    g = terms.sum(axis=1) / np.maximum(m, 1)
    var = ((terms - g[:, None]) ** 2 * fin[..., None]).sum(axis=1) / np.maximum(m - 1, 1)
    se = np.where(m > 1, np.sqrt(var / np.maximum(m, 1)), np.inf)
    return g, vals.mean(axis=1), se


@dataclasses.dataclass
class GradientFit:
    """Result of ``fit_gradient``.

    Attributes:
        theta: (d,) best estimate (the start whose final smoothed objective is lowest).
        theta_starts: (S, d) final point of each start.
        u_starts: (S, d) the same in u.
        history: (n_steps, S) smoothed objective per step and start.
        objective_final: (S,) final smoothed objective per start.
    """

    theta: np.ndarray
    theta_starts: np.ndarray
    u_starts: np.ndarray
    history: np.ndarray
    objective_final: np.ndarray


def fit_gradient(objective_theta: Callable[[np.ndarray], np.ndarray], box: Box,
                 theta_starts: np.ndarray, key: jax.Array, n_steps: int = 40,
                 learning_rate: float = 0.3, sigma: float = 0.15, k: int = 3,
                 progress: Callable[[int], None] | None = None) -> GradientFit:
    """Minimise objective(theta) over the box by Adam on the smoothed gradient.

    Args:
        objective_theta: (T, d) theta -> (T,) values (one simulator batch).
        box: prior box (defines the u <-> theta map).
        theta_starts: (S, d) starting points.
        key: PRNG key (directions; one fresh draw per step).
        n_steps, learning_rate, sigma, k: optimiser settings (lr and sigma in u).
        progress: optional callable(step) after each step.
    """
    u = u_of_theta(box, np.atleast_2d(theta_starts))

    def obj_u(pts):
        return objective_theta(theta_of_u(box, pts))

    sched = optax.cosine_decay_schedule(learning_rate, n_steps, alpha=0.1)
    opt = optax.adam(sched)
    state = opt.init(jnp.asarray(u))
    hist = []
    for i in range(n_steps):
        g, j, _ = smoothed_gradient(obj_u, u, sigma, jax.random.fold_in(key, i), k)
        hist.append(j)
        upd, state = opt.update(jnp.asarray(g), state)
        u = np.asarray(optax.apply_updates(jnp.asarray(u), upd))
        u = np.clip(u, -8.0, 8.0)
        if progress is not None:
            progress(i)
    # final smoothed objective at each start (same estimator, fresh directions)
    _, j_final, _ = smoothed_gradient(obj_u, u, sigma, jax.random.fold_in(key, n_steps), k)
    hist = np.array(hist)
    best = int(np.argmin(j_final))
    thetas = theta_of_u(box, u)
    return GradientFit(thetas[best], thetas, u, hist, j_final)


def gradient_stage(forward, rows, budget, key: jax.Array, tick, tally, design) -> GradientFit:
    """The gradient stage of a calibration (``calib.inference.calibrate``, stage 2):
    ``fit_gradient`` on J(theta) = -sum_i log p(y_i | theta) of the rows
    (``calib.inference.likelihood.RowLikelihood.pointwise``), each point simulated
    by ``forward`` with ``budget.n_blocks_grad`` common-random-number blocks, from
    the box's centre, ``budget.grad_starts - 1`` quasi-random points and (after a
    CRSP design) the design's best simulated point.

    Args:
        forward: ``CrspForward`` or ``DemForward``; rows: ``RowLikelihood``;
        budget: ``calib.inference.budget.Budget``; key: the stage's PRNG key.
        tick: callable(stage, done, total) for progress; tally: callable(stage,
            runouts, theta) counting unfinished blocks.
        design: the Bayesian stage's first design (``theta``, ``x``, ``ll``), or None.
    """
    from scipy.stats import qmc

    box = forward.box
    grad_forward = dataclasses.replace(forward, n_blocks=budget.n_blocks_grad, key=key)

    def objective(theta):
        runs = grad_forward.runouts(theta)
        tally("gradient", runs, theta)
        return -np.asarray(rows.pointwise(jnp.asarray(runs))).sum(1)

    starts = [0.5 * (box.lo + box.hi)]
    if budget.grad_starts > 1:
        z = qmc.Halton(box.dim, scramble=True, seed=1).random(budget.grad_starts - 1)
        starts += list(box.from_unit(0.15 + 0.7 * z))
    if design is not None and hasattr(forward, "from_input") and np.isfinite(design.ll).any():
        # one more start at the design's best simulated point: where the
        # likelihood is peaked in a thin part of the box, the box's centre and
        # a few quasi-random starts may all lie on its flat part
        starts.append(np.clip(forward.from_input(design.x[int(np.argmax(design.ll))]),
                              box.lo, box.hi))
    return fit_gradient(objective, box, np.array(starts), key, n_steps=budget.grad_steps,
                        k=budget.grad_k,
                        progress=lambda i: tick("gradient", i + 1, budget.grad_steps))
