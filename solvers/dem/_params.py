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
from solvers.material import ROCK_DENSITY_KG_M3
from solvers.profile import Profile
from solvers.status import BUDGET, INVALID, LEFT_PROFILE, RUNNING, STATUS_NAMES, STOPPED

__all__ = [
    "BUDGET",
    "DAMPING_MODES",
    "INVALID",
    "LEFT_PROFILE",
    "RUNNING",
    "STATUS_NAMES",
    "STOPPED",
    "RUN_STIFFNESS_SCALE",
    "Block",
    "Options",
    "Params",
    "check_run_numerics",
    "contact_damping_ratio",
    "make_block",
    "make_params",
    "stable_dt",
]

# Status values: the one set shared with CRSP (``solvers.status``; failures are
# values, not exceptions). The old DEM names stay importable as aliases until
# every consumer imports ``solvers.status`` (calib/hazard/_units.py).
EXITED, MAX_STEPS, NONFINITE = LEFT_PROFILE, BUDGET, INVALID

# Damping modes (``make_params(damping=...)``):
#   "unbalanced": Cundall local damping F_d = -alpha |F| sign(v) on the whole
#                 unbalanced force, gravity included (the classic form; Itasca's
#                 codes, UDEC included; the paper's model) -- the default.
#   "contact":    local damping on the contact forces only; a block in flight
#                 falls at g.
#   "viscous":    no local damping (alpha ignored); a linear dashpot in parallel
#                 with every contact spring, set from a target restitution e
#                 (``contact_damping_ratio``). Our addition, not the paper's.
DAMPING_MODES = ("unbalanced", "contact", "viscous")

# The stiffness scale the runs use (``Params.stiffness_scale`` keeps the paper's
# 1): the calibration, its DEM candidates and the hazard run
# (``calib.model.dem_run``), and ``python -m solvers.dem`` by default, so that a
# block is simulated alike by all of them. Our choice, not the paper's: at 0.01
# the stable time step grows 10x (dt ~ 1/sqrt(k)), and the stiffness check of
# ``scripts/dem_reproduce.py`` found runouts unchanged within Monte Carlo noise;
# joint strengths follow with its square root (``Params``).
RUN_STIFFNESS_SCALE = 0.01


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
            between fragments, Pa (eq. 2), at the paper's stiffness. Zero after
            a joint breaks. Under the stiffness shortcut the strengths used are
            c, t x stiffness_scale ** joint_strength_exponent (see below).
        joint_strength_exponent: 0.5 (default) scales the joint strengths with
            sqrt(stiffness_scale) so that breakage does not change with the
            shortcut. Why: a penalty contact hit at speed v peaks at
            F = v sqrt(k m_eff) (linear spring), so every impact force, and the
            joint forces it drives, scale as sqrt(k); scaling the strengths the
            same way keeps the ratio load / strength of an impact. Static loads
            (self-weight) do not scale with k, so under the shortcut a joint
            resists static loads sqrt(stiffness_scale) times less (x0.1 at
            0.01): our choice, exact for impacts only. Measured: a 1.8 m block
            of 64 fragments placed at rest on a 25 deg slope at x0.01 with the
            default strengths loses all its joints under its own weight (16
            fragments: 8 %; x1 or unscaled: none; tests/test_dem.py). 0 =
            unscaled strengths.
        gravity: m/s2.
        dt_frac: dt = dt_frac * 2 sqrt(m_eff / k_eff) (UDEC uses ~0.1).
        dt_s: if > 0, overrides the computed dt (tests of convergence).
        damp_gravity: 1 = damp the whole unbalanced force (UDEC), 0 = damp
            contact forces only. Values between blend the two.
        local_damping: multiplies every fragment's alpha (1 = Cundall local
            damping on, 0 = off; the "viscous" mode sets 0).
        restitution: target normal restitution e of the contact dashpots
            (``contact_damping_ratio``); 1 = no dashpot (the local-damping
            modes); a value < 0 takes each fragment's e from its alpha,
            e = sqrt((1 - alpha) / (1 + alpha)), the restitution local damping
            gives a one-degree-of-freedom normal impact (NOTES.md), so that the
            two modes dissipate alike at a normal impact.
        smooth_width: softplus width of the smooth contact law as a fraction
            of the static penetration m g / (kn l_c) (``Options.smooth``).
        sign_eps_m_s: velocity scale of tanh(v / eps) replacing sign(v) in the
            smooth mode's local damping.
        stop_speed_m_s, stop_hold_s, rest_cone_margin, rest_disp_m,
            rest_slip_m_s: the rest test (our rule, not UDEC's). A fragment is
            *held* in a step when
            (1) it is slow, sqrt(v^2 + (omega R)^2) < stop_speed_m_s;
            (2) none of its wall or fragment contacts slid in that step: the trial shear
                force did not exceed the Coulomb limit by more than
                ks l_c rest_slip_m_s dt (a slip rate of rest_slip_m_s; the
                tolerance keeps rounding from flagging as sliding a contact
                that sits at the limit while a neighbour holds the fragment);
            (3) either (a) it touches the wall or another fragment and every
                such contact transmits a force inside the Coulomb cone with a
                margin, |F_s| <= (1 - rest_cone_margin) tan(phi) max(F_n, 0),
                or (b) it has moved less than rest_disp_m (centre displacement
                plus R times rotation) since the hold began.
            It is at rest after ``stop_hold_s`` of being held without a break;
            the block has stopped when all its fragments are at rest. A block
            sliding where tan(beta) > tan(phi) keeps its wall contacts at the
            limit and slipping, so it is never at rest, however slowly local
            damping lets it slide, unless it slips slower than
            rest_slip_m_s for the whole hold (beta within ~5e-5 deg of phi at
            alpha 0.9). Intact joints do not count as contacts in (a).
        release_jitter_m, release_speed_m_s: random release offset (uniform in
            [0, jitter] downslope of the cliff edge) and initial horizontal
            speed (uniform in [0, speed]); the orientation is uniform in
            [0, pi/2). These are what makes the blocks of a batch differ.
        release_gap_m: initial clearance of the block above the release point.
    """

    profile: Profile
    rho: float = ROCK_DENSITY_KG_M3
    kn: float = 50e9
    ks: float = 50e9
    stiffness_scale: float = 1.0
    phi_joint_deg: float = 30.0
    c_joint_pa: float = 0.2e6
    t_joint_pa: float = 0.1e6
    joint_strength_exponent: float = 0.5
    gravity: float = 9.81
    dt_frac: float = 0.1
    dt_s: float = 0.0
    damp_gravity: float = 1.0
    local_damping: float = 1.0
    restitution: float = 1.0
    smooth_width: float = 0.05
    sign_eps_m_s: float = 1e-3
    stop_speed_m_s: float = 0.05
    stop_hold_s: float = 1.0
    rest_cone_margin: float = 0.05
    rest_disp_m: float = 1e-3
    rest_slip_m_s: float = 1e-6
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
        release_speed_m_s: horizontal release speed, m/s; NaN: the release
            rule's (uniform in [0, ``Params.release_speed_m_s``]).
        release_height_m: clearance of the block's lowest possible point (a
            corner, half a diagonal below its centre) above the ground at the
            release point, m, any sign (a tracked release that a raster puts
            below its ground is negative); NaN: ``Params.release_gap_m``. A
            tracked field run's release (``calib.files.field_runs``), as CRSP
            takes it.
        release_height_sd_m: sd of the release height's error, m (0: exact).
        release_speed_sd_m_s: sd of the release speed's error, m/s (0: exact).
            With an sd positive the release draws the height (speed) from a
            normal about the given one truncated to >= 0, as CRSP does
            (``solvers.truncated_normal``; only in programs compiled with
            ``Options.release_errors``); with sd 0 the height is the given
            one, on the ground where it is negative.
    """

    size_m: jax.Array
    alpha: jax.Array
    release_x_m: jax.Array
    stations_x_m: jax.Array
    release_speed_m_s: jax.Array
    release_height_m: jax.Array
    release_height_sd_m: jax.Array
    release_speed_sd_m_s: jax.Array

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
            flagged ``BUDGET`` (not stopped).
        chunk: steps per pass of the outer while loop; the fragment
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
        release_errors: compile the draws of the release errors
            (``Block.release_height_sd_m``, ``release_speed_sd_m_s``). The
            truncated normal's inverse CDF adds about 1.2 s to the compilation
            of a single-block program (measured: 4.2-4.8 s against 3.1-3.3 s,
            32 lanes), so programs of exact releases leave it out; there a
            block with a positive sd is released at a NaN height and ends
            ``INVALID``, never with its errors silently dropped.
    """

    max_steps: int = 2_000_000
    chunk: int = 64
    n_neighbors: int = 8
    smooth: bool = False
    segment_search: str = "local"
    pair_search: str = "list"
    adaptive: bool = True
    release_errors: bool = False


def make_params(profile: Profile, *, damping: str = "unbalanced",
                restitution: float | None = None, **kw) -> Params:
    """Params with paper defaults and one of the damping modes.

    Args:
        profile: the slope.
        damping: "unbalanced" (Cundall local damping of the whole unbalanced
            force, UDEC's form and the paper's; default), "contact" (local
            damping of the contact forces only) or "viscous" (local damping
            off, a dashpot at every contact; our addition).
        restitution: "viscous" only: target normal restitution e in (0, 1] of
            the dashpots; None (default) takes e from each fragment's alpha,
            e = sqrt((1 - alpha) / (1 + alpha)).
        **kw: any other ``Params`` field.

    Raises:
        ValueError: on an unknown mode, a restitution outside (0, 1], or a
            restitution given with a local-damping mode.
    """
    if damping not in DAMPING_MODES:
        raise ValueError(f"damping: expected one of {', '.join(DAMPING_MODES)}, got {damping!r}")
    if damping != "viscous":
        if restitution is not None:
            raise ValueError(f"restitution: only used with damping='viscous', not {damping!r}")
        return Params(profile=profile, damp_gravity=1.0 if damping == "unbalanced" else 0.0,
                      local_damping=1.0, restitution=1.0, **kw)
    if restitution is not None and not (math.isfinite(restitution) and 0.0 < restitution <= 1.0):
        raise ValueError(f"restitution: expected a value in (0, 1], got {restitution}")
    return Params(profile=profile, damp_gravity=0.0, local_damping=0.0,
                  restitution=-1.0 if restitution is None else float(restitution), **kw)


def check_run_numerics(stiffness_scale: float | None = None, max_time_s: float | None = None,
                       names: dict[str, str] | None = None) -> None:
    """Check the two numerics a user sets for a DEM run: the stiffness scale
    (``Params.stiffness_scale``) and the simulated time every block gets (the
    caller turns it into ``Options.max_steps`` with the stable step). The one
    copy of the check, used by ``python -m solvers.dem``, calib's DEM run
    configuration (``calib.model.dem_run``) and ``python -m calib.hazard``.

    Args:
        stiffness_scale: multiplies kn and ks; in (0, 1] (1: the paper's
            stiffness). None: not given, not checked.
        max_time_s: simulated time, s; finite and > 0. None: not checked.
        names: the name of each value in the message, by argument name (a
            command passes its options, e.g. ``{"stiffness_scale":
            "--stiffness-scale"}``); default the argument names.

    Raises:
        ValueError: ``"<name>: expected a value in (0, 1], got <v>"`` or
            ``"<name>: expected a positive time, got <v>"``.
    """
    names = {"stiffness_scale": "stiffness_scale", "max_time_s": "max_time_s", **(names or {})}
    if stiffness_scale is not None and not (math.isfinite(stiffness_scale)
                                            and 0.0 < stiffness_scale <= 1.0):
        raise ValueError(f"{names['stiffness_scale']}: expected a value in (0, 1], got "
                         f"{stiffness_scale:g}")
    if max_time_s is not None and not (math.isfinite(max_time_s) and max_time_s > 0):
        raise ValueError(f"{names['max_time_s']}: expected a positive time, got {max_time_s:g}")


def max_steps_for(max_time_s: float, params: Params, block: Block) -> int:
    """Steps that give ``block`` at least ``max_time_s`` of simulated time at its
    stable step: ceil(max_time_s / stable_dt). The one copy of this bound, used
    by ``python -m solvers.dem`` and calib's DEM run configuration."""
    return int(math.ceil(max_time_s / float(stable_dt(params, block))))


def contact_damping_ratio(e):
    """Damping ratio zeta of a linear spring-dashpot contact of restitution e.

    zeta = -ln(e) / sqrt(pi^2 + ln(e)^2); the dashpot is c = 2 zeta sqrt(m_eff k).
    For the linear spring-dashpot m x'' + c x' + k x = 0 started at the touch
    (x = 0) and ended when the overlap returns to 0, the restitution is
    e = exp(-zeta pi / sqrt(1 - zeta^2)), whose inverse is this formula.

    The relation holds only if the dashpot may pull at the end of the contact
    (total normal force k x + c x' < 0 while x > 0): ending the contact when
    the force reaches zero instead raises e (0.5 -> 0.55, 0.23 -> 0.35;
    Schwager & Poeschel 2007). We keep the classic unclipped law so that the
    target e is what a normal impact gives; the friction limit uses
    max(F_n, 0).

    Args:
        e: restitution in (0, 1] (any shape).

    Returns:
        zeta, dimensionless, same shape (0 at e = 1).

    References:
        Cundall & Strack (1979) Geotechnique 29(1) 47-65 (spring-dashpot
        contacts); Tsuji, Tanaka & Ishida (1992) Powder Technol. 71 239-250
        (damping from a restitution); Schwager & Poeschel (2007) Granular
        Matter 9 465-469 (the force-zero end of contact).
    """
    le = jnp.log(e)
    return -le / jnp.sqrt(jnp.pi ** 2 + le * le)


def make_block(size_m: float, *, alpha: float | None = None, n_fragments: int = 1,
               alpha_law=None, release_x_m: float = 0.0, stations=(),
               release_speed_m_s: float = math.nan, release_height_m: float = math.nan,
               release_height_sd_m: float = 0.0, release_speed_sd_m_s: float = 0.0) -> Block:
    """Describe a block of side ``size_m`` split into ``n_fragments`` = n*n squares.

    The damping of each fragment is ``alpha`` if given, else ``alpha_law``
    (text or callable) evaluated at the fragment side L/n (default law
    ``0.40*L**-0.5``, the Table 1 trend).

    Raises:
        ValueError: on a non-square fragment count, a bad size, alpha outside [0, 1),
            or a release error's sd that is not a finite number >= 0.
    """
    for name, sd in (("release_height_sd_m", release_height_sd_m),
                     ("release_speed_sd_m_s", release_speed_sd_m_s)):
        if not (math.isfinite(sd) and sd >= 0.0):
            raise ValueError(f"{name}: expected a finite sd >= 0, got {sd}")
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
                 stations_x_m=jnp.asarray(np.asarray(stations, dtype=np.float64).reshape(-1)),
                 release_speed_m_s=jnp.asarray(float(release_speed_m_s)),
                 release_height_m=jnp.asarray(float(release_height_m)),
                 release_height_sd_m=jnp.asarray(float(release_height_sd_m)),
                 release_speed_sd_m_s=jnp.asarray(float(release_speed_sd_m_s)))


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
