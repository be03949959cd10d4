"""Smooth-contact rigid-block DEM in JAX, in the spirit of UDEC.

Rigid squares (optionally pre-split into n x n bonded fragments) fall down a
2D slope polyline; penalty contacts with Mohr-Coulomb friction (paper eqs.
1-2), Cundall local damping (eq. 3; the paper's UDEC) or, as a second mode of
our own, contact dashpots set from a restitution (``damping="viscous"``),
central-difference integration. Rest only where statically admissible; status
codes are ``solvers.status``'s. ``deposit_check`` relaxes a resting state with
damping off; ``mechanical_energy`` gives the energy of a state.

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
from solvers.dem._diagnostics import DepositCheck, Energy, deposit_check, mechanical_energy
from solvers.dem._integrate import (
    Pose,
    Result,
    State,
    init,
    rollout,
    simulate,
    simulate_batch,
    step,
    trajectory,
)
from solvers.dem._params import (
    DAMPING_MODES,
    RUN_STIFFNESS_SCALE,
    STATUS_NAMES,
    Block,
    Options,
    Params,
    check_run_numerics,
    contact_damping_ratio,
    make_block,
    make_params,
    max_steps_for,
    stable_dt,
)

__all__ = [
    "DAMPING_MODES",
    "DEFAULT_ALPHA_LAW",
    "RUN_STIFFNESS_SCALE",
    "STATUS_NAMES",
    "AlphaLawError",
    "Block",
    "DepositCheck",
    "Energy",
    "Options",
    "Params",
    "Pose",
    "Result",
    "State",
    "check_run_numerics",
    "contact_damping_ratio",
    "deposit_check",
    "init",
    "make_block",
    "make_params",
    "mechanical_energy",
    "parse_alpha_law",
    "rollout",
    "simulate",
    "simulate_batch",
    "max_steps_for",
    "stable_dt",
    "step",
    "trajectory",
]
