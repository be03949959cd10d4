"""The simulated design of a fit's Bayesian stage (``calib.inference.bayes_stage``)
and where its later waves go.

``Design`` holds every simulated point: its emulator coordinates, its runouts,
the rows' summed simulated log-likelihood there, and whether a repair wave put
it there. Its waves:

* ``Design.second_wave``: a pilot posterior on the whole box plus points
  around the best simulated ones (``second_design``);
* ``Design.fill``: scrambled Sobol in a box of the emulator's coordinates, the
  focus region or a slab it widened into (``focus_design``,
  ``calib.inference.focus``);
* ``Design.sir_wave``: draws from an emulated posterior restricted to the focus
  region (``sir_draws``).

Every wave is chosen in the emulator's coordinates (``forward.to_input``)
and simulated in theta, inside the prior box.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from calib.inference.emulator import fit_emulator

__all__ = ["Design", "focus_design", "second_design", "sir_draws"]


class Design:
    """The simulated design: the first one (``forward.design``) and every point
    simulated after it.

    Attributes:
        x: (D, d) the points in the emulator's coordinates.
        r: (D, S, n) their runouts, m.
        v: (D, S, K, n) their passage speeds at the rows' stations, m/s, with
            passage-velocity rows (``RowLikelihood.velocities``); else None.
        ll: (D,) the rows' summed simulated log-likelihood at each
            (``RowLikelihood.summed``).
        refined: (D,) bool, placed by a repair wave (where an emulated
            posterior sat), not by a design rule.
    """

    def __init__(self, forward, rows, tally, n: int, seed: int):
        """The first design: ``n`` points of ``forward.design`` (seed ``seed``)
        scored by ``rows`` (``calib.inference.likelihood.RowLikelihood``);
        ``tally`` records the unfinished blocks of every simulation (stage
        "design")."""
        self.forward, self.rows, self.tally = forward, rows, tally
        if rows.velocities is None:
            self.x, self.r = forward.design(n, seed=seed)
            self.v = None
        else:  # CRSP: the same points, simulated with their passage speeds
            theta = forward.design_points(n, seed=seed)
            self.r, self.v = rows.simulate(forward, theta)
            self.x = np.asarray(forward.to_input(theta))
        self.ll = rows.summed(self.r, self.v)
        tally("design", self.r)
        self.refined = np.zeros(len(self.x), bool)

    @property
    def theta(self) -> np.ndarray:
        """(D, d) the points in theta."""
        return self.forward.from_input(self.x)

    def add(self, theta, runs, speeds=None, refinement: bool = False) -> None:
        """Simulated points join the design (their runouts and, with velocity
        rows, passage speeds: ``RowLikelihood.simulate``; ``refinement``: a
        repair wave's)."""
        self.ll = np.concatenate([self.ll, self.rows.summed(runs, speeds)])
        self.x = np.concatenate([self.x, np.asarray(self.forward.to_input(theta))])
        self.r = np.concatenate([self.r, runs])
        if self.v is not None:
            self.v = np.concatenate([self.v, speeds])
        self.refined = np.concatenate([self.refined, np.full(len(runs), refinement)])

    def simulate(self, theta, refinement: bool = False) -> None:
        """Simulate the points theta (T, d) and add them."""
        runs, speeds = self.rows.simulate(self.forward, theta)
        self.tally("design", runs, theta)
        self.add(theta, runs, speeds, refinement)

    def inside(self, input_box) -> np.ndarray:
        """(D,) bool: the points inside ``input_box`` (emulator coordinates)."""
        return np.all((self.x >= input_box.lo - 1e-9) & (self.x <= input_box.hi + 1e-9), axis=1)

    def second_wave(self, n_levels: int, n: int, key: jax.Array) -> None:
        """``second_design``'s n points, its pilot posterior that of the runout
        quantile emulator (``n_levels`` levels) fitted on the design so far."""
        fw = self.forward
        ibox = fw.input_box
        emu = fit_emulator(self.x, self.r, ibox.lo, ibox.hi, n_levels)
        self.simulate(second_design(fw, self.rows.emulated(emu, fw.emulator_inputs, 1.0),
                                    self.theta, self.ll, n, key))

    def fill(self, input_box, box, n: int, key: jax.Array) -> None:
        """``focus_design``'s n points in ``input_box`` (``box``: its image in theta)."""
        self.simulate(focus_design(self.forward, input_box, box, n, key))

    def sir_wave(self, input_box, box, n_levels: int, n: int, key: jax.Array) -> None:
        """``sir_draws``' n points in ``input_box`` (``box``: its image in theta),
        from the posterior of the runout quantile emulator (``n_levels``
        levels) fitted on the design points inside it."""
        fw = self.forward
        keep = self.inside(input_box)
        emu = fit_emulator(self.x[keep], self.r[keep], input_box.lo, input_box.hi, n_levels)
        self.simulate(sir_draws(fw, self.rows.emulated(emu, fw.emulator_inputs, 1.0),
                                input_box, box, n, key))


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
