"""The later waves of a CRSP fit's design (``calib.inference.calibrate``, stage 1):
where to simulate next, given the first design and an emulator.

* ``second_design``: a pilot posterior on the whole box plus points around
  the best simulated ones;
* ``focus_design``: scrambled Sobol in the focus region
  (``calib.inference.focus``);
* ``sir_draws``: draws from an emulated posterior restricted to a box.

Every design is chosen in the emulator's coordinates (``forward.to_input``)
and returned in theta, inside the prior box.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["focus_design", "second_design", "sir_draws"]


def sir_draws(forward, pointwise_loglik, input_box, box, n: int, key: jax.Array
              ) -> np.ndarray:
    """theta (n, d): n draws from the emulated posterior restricted to ``input_box``
    (emulator coordinates; ``box`` its image in theta) by sampling-importance-
    resampling (Rubin 1988) of 4096 scrambled-Sobol points of ``input_box``,
    weighted by the emulated likelihood times the prior's density in those
    coordinates, 1 / |det d to_input / d theta| (the prior is uniform in theta),
    and jittered by 2 % of ``input_box`` so that repeats differ."""
    from scipy.stats import qmc

    seed = int(jax.random.randint(key, (), 0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    span = input_box.hi - input_box.lo
    u = input_box.from_unit(qmc.Sobol(box.dim, scramble=True, seed=seed).random_base2(12))
    pts = jnp.asarray(_in_box(forward, u, input_box, box))
    logdet = jax.vmap(lambda t: jnp.linalg.slogdet(jax.jacfwd(forward.to_input)(t))[1])
    logw = np.asarray(jax.jit(jax.vmap(pointwise_loglik))(pts)).sum(1) - np.asarray(
        jax.jit(logdet)(pts))
    logw = np.where(np.isfinite(logw), logw, -np.inf)
    w = np.exp(logw - logw.max())
    pick = u[rng.choice(len(u), n, p=w / w.sum())]
    return _in_box(forward, pick + 0.02 * span * rng.standard_normal(pick.shape), input_box,
                   box)


def _in_box(forward, u: np.ndarray, input_box, box) -> np.ndarray:
    """theta of emulator coordinates u, clipped to ``input_box`` and to its image
    ``box``."""
    return np.clip(forward.from_input(np.clip(u, input_box.lo, input_box.hi)), box.lo, box.hi)


def second_design(forward, pointwise_loglik, design_theta: np.ndarray,
                   design_ll: np.ndarray, n: int, key: jax.Array) -> np.ndarray:
    """theta (n, d) of the second design, in two parts.

    * ``n - n // 4`` draws from a pilot posterior on the whole box
      (``sir_draws``);
    * ``n // 4`` points around the design points with the highest SIMULATED
      likelihood (the best ``max(1, n // 16)``, equally many each), jittered by
      5 % of the input box.

    Our choice, and why the second part: where the likelihood is peaked in a
    thin part of the box, an emulator fitted on a few points there can put its
    pilot posterior elsewhere; the simulator's own best points are where the
    emulator must be right (as history matching refines its non-implausible
    region in waves: Vernon et al. 2010).
    """
    k_sir, k_near = jax.random.split(key)
    ibox, box = forward.input_box, forward.box
    n_near = n // 4 if np.isfinite(design_ll).any() else 0
    parts = [sir_draws(forward, pointwise_loglik, ibox, box, n - n_near, k_sir)]
    if n_near:
        rng = np.random.default_rng(int(jax.random.randint(k_near, (), 0, 2**31 - 1)))
        best = np.argsort(-np.where(np.isfinite(design_ll), design_ll, -np.inf))
        best = best[:max(1, n // 16)]
        centre = np.asarray(forward.to_input(design_theta[best]))[
            np.arange(n_near) % len(best)]
        parts.append(_in_box(forward, centre + 0.05 * (ibox.hi - ibox.lo)
                             * rng.standard_normal(centre.shape), ibox, box))
    return np.concatenate(parts)


def focus_design(forward, input_box, box, n: int, key: jax.Array) -> np.ndarray:
    """theta (n, d): scrambled Sobol in the focus box's emulator coordinates
    (``calib.inference.focus``), as the first design fills the prior box's."""
    from scipy.stats import qmc

    seed = int(jax.random.randint(key, (), 0, 2**31 - 1))
    z = qmc.Sobol(box.dim, scramble=True, seed=seed).random_base2(int(np.ceil(np.log2(n))))[:n]
    return _in_box(forward, input_box.from_unit(z), input_box, box)
