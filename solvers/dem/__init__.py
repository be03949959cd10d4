"""Smooth-contact rigid-block DEM in JAX, in the spirit of UDEC (issue 3).

Rigid squares (optionally pre-split into n x n bonded fragments) fall down a
2D slope polyline; penalty contacts with Mohr-Coulomb friction (paper eqs.
1-2), Cundall local damping (eq. 3), central-difference integration.

Usage::

    params = make_params(load_profile("data/postignano_profile.csv"))
    block = make_block(0.9, alpha=0.43)
    keys = jax.random.split(jax.random.key(0), 256)
    res = jax.vmap(lambda k: simulate(params, block, k))(keys)

References:
    Itasca (1991) UDEC User's Manual, theory; Cundall (1987) "Distinct element
    models of rock and soil structure"; the paper in ../shared/seed (Sect. 3.2, 4).
"""

from solvers.dem._alpha_law import DEFAULT_ALPHA_LAW, AlphaLawError, parse_alpha_law
from solvers.dem._integrate import (
    Pose,
    Result,
    State,
    init,
    simulate,
    simulate_batch,
    step,
    trajectory,
)
from solvers.dem._params import (
    DAMPING_MODES,
    STATUS_NAMES,
    Block,
    Options,
    Params,
    make_block,
    make_params,
    stable_dt,
)

__all__ = [
    "DAMPING_MODES",
    "DEFAULT_ALPHA_LAW",
    "STATUS_NAMES",
    "AlphaLawError",
    "Block",
    "Options",
    "Params",
    "Pose",
    "Result",
    "State",
    "init",
    "make_block",
    "make_params",
    "parse_alpha_law",
    "simulate",
    "simulate_batch",
    "stable_dt",
    "step",
    "trajectory",
]
