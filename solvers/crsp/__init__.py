"""CRSP: the Colorado Rockfall Simulation Program's lumped-mass impact model in JAX.

``simulate(params, block, key, profile=...)`` runs ONE block; ``jax.vmap`` or
``run_blocks`` run thousands. See ``_model`` for the event loop, ``_impact`` for
the impact law, ``_flight`` for the closed-form next impact and ``_contact`` for
the rolling phase, ``_barrier`` for the protection barrier (``Params.barrier_*``,
``Result.barrier``, status ``STOPPED_BY_BARRIER``), ``_break`` for a break
recorded so that every fragment can run on (``Result.breakup``,
``simulate_fragments``). ``python -m solvers.crsp --help`` for the command
line.
"""

import solvers  # noqa: F401  (enables float64)
from solvers.crsp._barrier import BarrierRecord
from solvers.crsp._batch import (
    block_keys,
    chunk_plan,
    default_pool,
    run_blocks,
    simulate_batch,
    simulate_pooled,
    simulate_tasks,
    task_slots,
)
from solvers.crsp._break import BreakRecord, fragment_key, simulate_fragment, simulate_fragments
from solvers.crsp._impact import ImpactOut, crsp_impact, roughness_tilt
from solvers.crsp._model import (
    BUDGET,
    CONTACT,
    FLIGHT,
    INVALID,
    LEFT_PROFILE,
    MAX_EVENTS,
    STOPPED,
    STOPPED_BY_BARRIER,
    Result,
    State,
    simulate,
)
from solvers.crsp._params import (
    ROLLING_THRESHOLD_M_S,
    ROLLING_THRESHOLD_RANGE_M_S,
    SHAPES,
    Block,
    Params,
    Settings,
    make_block,
    params_from_profile,
    shape_constants,
)

__all__ = [
    "ROLLING_THRESHOLD_M_S",
    "ROLLING_THRESHOLD_RANGE_M_S",
    "SHAPES",
    "BUDGET",
    "CONTACT",
    "FLIGHT",
    "INVALID",
    "LEFT_PROFILE",
    "MAX_EVENTS",
    "STOPPED",
    "STOPPED_BY_BARRIER",
    "BarrierRecord",
    "Block",
    "BreakRecord",
    "ImpactOut",
    "Params",
    "Result",
    "Settings",
    "State",
    "block_keys",
    "crsp_impact",
    "fragment_key",
    "make_block",
    "params_from_profile",
    "shape_constants",
    "roughness_tilt",
    "chunk_plan",
    "default_pool",
    "run_blocks",
    "simulate",
    "simulate_batch",
    "simulate_fragment",
    "simulate_fragments",
    "simulate_pooled",
    "simulate_tasks",
    "task_slots",
]
