"""Parameters, block description and static options of the DEM solver.

Units are SI and per metre of thickness (2D plane strain, as in UDEC): masses
in kg/m, forces in N/m, joint stiffnesses kn, ks in Pa/m (stress per metre of
relative displacement, the paper's "50 GPa", Sect. 4.1).

Contact-length convention (turning kn in Pa/m into a spring in N/m per metre
of thickness): every corner-to-edge contact, and every bonded joint point,
represents half of the side of the fragment that owns it, l_c = s/2. A square
resting flat on a face therefore has two corner contacts and a total normal
stiffness kn * s, i.e. a normal stress kn * penetration over its whole base,
which is UDEC's convention of a contact length shared half-and-half between
the two contacts that bound an edge (Itasca UDEC theory, "contact length").
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from solvers.dem._alpha_law import DEFAULT_ALPHA_LAW, AlphaLawError, parse_alpha_law
from solvers.profile import Profile

__all__ = [
    "DAMPING_MODES",
    "Block",
    "Options",
    "Params",
    "STATUS_NAMES",
    "make_block",
    "make_params",
    "stable_dt",
]

# Status values (failures are values, not exceptions).
RUNNING, STOPPED, EXITED, MAX_STEPS, NONFINITE = 0, 1, 2, 3, 4
STATUS_NAMES = {RUNNING: "running", STOPPED: "stopped", EXITED: "left_profile",
                MAX_STEPS: "max_steps", NONFINITE: "nonfinite"}

# Local-damping modes: which force enters F_d = -alpha |F| sign(v).
#   "unbalanced": the whole unbalanced force, gravity included (Cundall's
#                 classic form; Itasca's codes, UDEC included) -- the default.
#   "contact":    contact forces only; a block in flight falls at g.
DAMPING_MODES = {"unbalanced": 1.0, "contact": 0.0}


class Params(NamedTuple):
    """Physical and numerical parameters (a pytree; every leaf may be traced).

    Attributes:
        profile: the slope (rigid wall); friction angle per zone ``phi_deg``.
        rho: block density, kg/m3 (paper: 2350).
        kn, ks: joint normal / shear stiffness, Pa/m (paper: 50e9).
        stiffness_scale: multiplies kn and ks (1 = paper). Lowering it by s
            raises the stable dt by 1/sqrt(s) and penetrations by 1/s.
        phi_joint_deg: friction angle of fragment-fragment contacts and joints.
        c_joint_pa, t_joint_pa: cohesion and tensile strength of intact joints
            between fragments, Pa (eq. 2). Zero after a joint breaks.
        gravity: m/s2.
        dt_frac: dt = dt_frac * 2 sqrt(m_eff / k_eff) (UDEC uses ~0.1).
        dt_s: if > 0, overrides the computed dt (tests of convergence).
        damp_gravity: 1 = damp the whole unbalanced force (UDEC), 0 = damp
            contact forces only. Values between blend the two.
        smooth_width: softplus width of the smooth contact law as a fraction
            of the static penetration m g / (kn l_c) (``Options.smooth``).
        sign_eps_m_s: velocity scale of tanh(v / eps) replacing sign(v) in the
            smooth mode and in fragment-fragment friction.
        stop_speed_m_s: a fragment is "slow" when sqrt(v^2 + (omega R)^2) is
            below this; it has stopped after ``stop_hold_s`` of being slow.
        release_jitter_m, release_speed_m_s: random release offset (uniform in
            [0, jitter] downslope of the cliff edge) and initial horizontal
            speed (uniform in [0, speed]); the orientation is uniform in
            [0, pi/2). These are what makes the blocks of a batch differ.
        release_gap_m: initial clearance of the block above the release point.
    """

    profile: Profile
    rho: float = 2350.0
    kn: float = 50e9
    ks: float = 50e9
    stiffness_scale: float = 1.0
    phi_joint_deg: float = 30.0
    c_joint_pa: float = 0.2e6
    t_joint_pa: float = 0.1e6
    gravity: float = 9.81
    dt_frac: float = 0.1
    dt_s: float = 0.0
    damp_gravity: float = 1.0
    smooth_width: float = 0.05
    sign_eps_m_s: float = 1e-3
    stop_speed_m_s: float = 0.05
    stop_hold_s: float = 1.0
    release_jitter_m: float = 0.5
    release_speed_m_s: float = 1.0
    release_gap_m: float = 0.01


class Block(NamedTuple):
    """One block, possibly pre-split into n x n bonded square fragments.

    Attributes:
        size_m: side L of the parent square, m (scalar).
        alpha: (N,) local damping coefficient of each fragment, N = n*n.
        release_x_m: abscissa of the release point (cliff edge), m.
        stations_x_m: (S,) station abscissae, m (may be empty).
    """

    size_m: jax.Array
    alpha: jax.Array
    release_x_m: jax.Array
    stations_x_m: jax.Array

    @property
    def n_fragments(self) -> int:
        return int(self.alpha.shape[-1])

    @property
    def n_side(self) -> int:
        return math.isqrt(self.n_fragments)


class Options(NamedTuple):
    """Static (hashable) options; changing one recompiles.

    Attributes:
        max_steps: bound on the number of steps; a block still moving then is
            flagged ``max_steps`` (not stopped).
        chunk: steps per iteration of the outer while loop; the fragment
            neighbour list is rebuilt once per chunk.
        n_neighbors: fragments tested against each fragment (nearest by centre).
        smooth: softplus normal force and tanh-smoothed friction/damping signs.
        segment_search: "local" (each corner tests only the segment below it)
            or "all" (each corner tests every segment; kept for benchmarks).
        pair_search: "list" (the n_neighbors N / 2 closest unordered pairs,
            both directions tested, one scatter) or "knn" (each fragment's
            corners against its n_neighbors nearest; the earlier, slower
            scheme, kept for benchmarks).
        adaptive: per chunk, use only the prefix of the pair list that can
            touch within the chunk and skip joint forces once all joints are
            broken (``lax.switch``; same forces). Under ``vmap`` a switch
            runs every branch, so batched callers should turn it off
            (``simulate_batch`` does for batches of more than one block).
    """

    max_steps: int = 2_000_000
    chunk: int = 64
    n_neighbors: int = 8
    smooth: bool = False
    segment_search: str = "local"
    pair_search: str = "list"
    adaptive: bool = True


def make_params(profile: Profile, *, damping: str = "unbalanced", **kw) -> Params:
    """Params with paper defaults; ``damping`` is "unbalanced" (UDEC) or "contact"."""
    if damping not in DAMPING_MODES:
        raise ValueError(f"damping: expected one of {', '.join(DAMPING_MODES)}, got {damping!r}")
    return Params(profile=profile, damp_gravity=DAMPING_MODES[damping], **kw)


def make_block(size_m: float, *, alpha: float | None = None, n_fragments: int = 1,
               alpha_law=None, release_x_m: float = 0.0, stations=()) -> Block:
    """Describe a block of side ``size_m`` split into ``n_fragments`` = n*n squares.

    The damping of each fragment is ``alpha`` if given, else ``alpha_law``
    (text or callable) evaluated at the fragment side L/n (default law
    ``0.40*L**-0.5``, the Table 1 trend).

    Raises:
        ValueError: on a non-square fragment count, a bad size, or alpha outside [0, 1).
    """
    n = math.isqrt(int(n_fragments))
    if n < 1 or n * n != int(n_fragments):
        raise ValueError(f"fragments: expected a perfect square (1, 4, 16, 64, ...), got "
                         f"{n_fragments}")
    if not (math.isfinite(size_m) and size_m > 0):
        raise ValueError(f"block size: expected a positive number of metres, got {size_m}")
    if alpha is not None and alpha_law is not None:
        raise ValueError("give either alpha or alpha_law, not both")
    if alpha is None:
        law = parse_alpha_law(alpha_law if alpha_law is not None else DEFAULT_ALPHA_LAW)
        value = float(np.asarray(law(jnp.asarray(size_m / n))))
    else:
        value = float(alpha)
    if not (math.isfinite(value) and 0.0 <= value < 1.0):
        raise AlphaLawError(f"alpha: local damping must lie in [0, 1), got {value:g} for "
                            f"fragment side {size_m / n:g} m")
    return Block(size_m=jnp.asarray(float(size_m)),
                 alpha=jnp.full((n * n,), value),
                 release_x_m=jnp.asarray(float(release_x_m)),
                 stations_x_m=jnp.asarray(np.asarray(stations, dtype=np.float64).reshape(-1)))


def stable_dt(params: Params, block: Block) -> jax.Array:
    """Stable explicit time step for this block, s.

    dt = dt_frac * 2 sqrt(m_eff / k_eff) with, for a fragment of side s,
    m = rho s^2, I = m s^2 / 6, m_eff = min(m, I / R^2) = m / 3 (R = s/sqrt 2,
    the rotational mode is the stiffest), and k_eff = n_c kn l_c with
    l_c = s/2 and n_c = 2 contacts for a single block (a face on the ground),
    n_c = 8 for a fragment (four bonded neighbours, two points each).
    Source: central-difference stability dt < 2/omega_max (Itasca UDEC theory,
    "time step"); NOTES.md "Explicit stability".
    """
    n = block.n_side
    s = block.size_m / n
    m = params.rho * s * s
    k = (2.0 if n == 1 else 8.0) * params.kn * params.stiffness_scale * 0.5 * s
    dt = params.dt_frac * 2.0 * jnp.sqrt((m / 3.0) / k)
    return jnp.where(params.dt_s > 0, params.dt_s, dt)
