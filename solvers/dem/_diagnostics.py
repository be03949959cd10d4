"""Diagnostics of DEM states: mechanical energy and the deposit check.

Energy (per metre of thickness, J/m) of a state at time t: kinetic
(translation and rotation), potential m g z, and the elastic energy stored in
the linear contact springs: wall normal kn l_c delta^2 / 2 and shear
F_s^2 / (2 ks l_c) per corner, intact-joint (kn l_c u_n^2 + ks l_c u_s^2) / 2
per point, fragment-fragment kn l_c delta^2 / 2 per contact point and
F_s^2 / (4 ks l_c) per pair (its shear spring of 2 ks l_c, ``_contact``). Damping, friction
slip, a joint that breaks (its stored energy is lost) and a contact that
opens while its shear spring is loaded all remove energy; nothing in the
model adds any, so E(t) must not increase beyond the integrator's error.

Velocities live at half steps (central differences). With the velocities on
both sides of t the kinetic term is taken as m v(t - dt/2) . v(t + dt/2) / 2,
the form that the central-difference (leapfrog) scheme conserves exactly with
a linear spring (the oscillator's discrete invariant, e.g. Hairer, Lubich &
Wanner 2003, "Geometric numerical integration illustrated by the
Stormer-Verlet method", Acta Numerica 12); the energy is then exact up to the
switching of contacts on and off within a step.

Deposit check (our diagnostic): take a final, resting state, switch every
damping off (local alpha = 0 and no dashpot; friction stays), run it on for a
set time and report how far each fragment moves. A deposit held by friction
(contacts inside the Coulomb cone) stays within the elastic creep of its
springs; one held by damping (contacts at the Coulomb limit, net force
balanced by the damping force) slides away.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from solvers.dem._contact import pair_list_energy, pair_shear_stiffness
from solvers.dem._geometry import corner_offsets, joints_of, rotate, segment_lookup
from solvers.dem._integrate import Consts, State, consts, neighbours, step_with_stations
from solvers.dem._params import Block, Options, Params
from solvers.status import RUNNING

__all__ = ["DepositCheck", "Energy", "deposit_check", "mechanical_energy"]


class Energy(NamedTuple):
    """Energies of one state, J/m (scalars): kinetic, potential (m g z, from
    z = 0), elastic (contact and joint springs). ``total`` is their sum."""

    kinetic_J: jax.Array
    potential_J: jax.Array
    elastic_J: jax.Array

    @property
    def total_J(self) -> jax.Array:
        return self.kinetic_J + self.potential_J + self.elastic_J


def mechanical_energy(params: Params, c: Consts, st: State, st_next: State,
                      n_side: int) -> Energy:
    """Energy at the time of ``st.pos`` (t), given the state one step later.

    Args:
        params, c: parameters and the block's constants (``init``).
        st: state at t (positions at t, velocities at t - dt/2).
        st_next: ``step(st)`` (velocities at t + dt/2, the wall and
            fragment shear forces and joint flags computed at t).
        n_side: fragments per side (static).

    Returns:
        ``Energy`` in J/m. Exited fragments are left out. Elastic terms use the
        linear law (``Options.smooth`` is not accounted for).
    """
    keep = ~st.exited
    v2 = jnp.sum(st.vel * st_next.vel, axis=-1)
    w2 = st.omega * st_next.omega
    kinetic = 0.5 * jnp.sum(jnp.where(keep, c.mass * v2 + c.inertia * w2, 0.0))
    potential = jnp.sum(jnp.where(keep, c.mass * params.gravity * st.pos[:, 1], 0.0))
    cs, sn = jnp.cos(st.theta), jnp.sin(st.theta)
    p = st.pos[:, None, :] + rotate(corner_offsets(c.half)[None], cs[:, None], sn[:, None])
    xa, za, tx, tz, _ = segment_lookup(c.seg, p[..., 0])
    delta = jnp.maximum(-(-tz * (p[..., 0] - xa) + tx * (p[..., 1] - za)), 0.0)
    wall = 0.5 * c.kn_c * delta ** 2 + 0.5 * st_next.fs ** 2 / c.ks_c
    elastic = jnp.sum(jnp.where(keep[:, None], wall, 0.0))
    if n_side > 1:
        joints = joints_of(n_side)
        a, b = joints.a, joints.b
        ra = rotate(jnp.asarray(joints.qa) * c.half, cs[a][:, None], sn[a][:, None])
        rb = rotate(jnp.asarray(joints.qb) * c.half, cs[b][:, None], sn[b][:, None])
        d = (st.pos[b][:, None] + rb) - (st.pos[a][:, None] + ra)
        n_w = rotate(jnp.asarray(joints.normal), cs[a], sn[a])[:, None, :]
        t_w = jnp.stack([-n_w[..., 1], n_w[..., 0]], axis=-1)
        un, us = jnp.sum(d * n_w, -1), jnp.sum(d * t_w, -1)
        e_joint = 0.5 * c.kn_c * un ** 2 + 0.5 * c.ks_c * us ** 2
        elastic = elastic + jnp.sum(jnp.where(st_next.intact[:, None], e_joint, 0.0))
        n = n_side * n_side
        iu, ju = np.triu_indices(n, 1)
        jid = np.full((n, n), len(a), np.int32)
        jid[a, b] = jid[b, a] = np.arange(len(a))
        free = jnp.concatenate([~st_next.intact, jnp.ones((1,), bool)])[jid[iu, ju]]
        ok = free & keep[iu] & keep[ju]
        elastic = elastic + pair_list_energy(st.pos, cs, sn, jnp.asarray(iu), jnp.asarray(ju),
                                             ok, c.half, c.kn_c)
        elastic = elastic + jnp.sum(st_next.fs_pair ** 2) / (2.0 * pair_shear_stiffness(c.ks_c))
    return Energy(kinetic, potential, elastic)


class DepositCheck(NamedTuple):
    """Outcome of ``deposit_check`` for one block (fragments that left the
    profile are left out of the statistics).

    disp_m: (N,) centre displacement of each fragment over the check, m (to
        its exit point for a fragment that passed the profile end during it).
    max_disp_m, mean_disp_m: their maximum and mean, m.
    rot_rad: (N,) absolute rotation over the check, rad.
    n_left: fragments that passed the profile end during the check.
    relax_s: simulated time of the check, s.
    status: status at the end (RUNNING unless it turned INVALID or every
        fragment left the profile).
    state: the state at the end of the check.
    """

    disp_m: jax.Array
    max_disp_m: jax.Array
    mean_disp_m: jax.Array
    rot_rad: jax.Array
    n_left: jax.Array
    relax_s: jax.Array
    status: jax.Array
    state: State


def deposit_check(params: Params, block: Block, st: State, relax_s: float = 5.0,
                  options: Options = Options()) -> DepositCheck:
    """Relax a final state with every damping off and measure how far it moves.

    Local damping is set to alpha = 0 and the contact dashpots are removed
    (restitution 1); friction, joints (broken ones stay broken) and the wall
    shear springs carry over from ``st``. The state runs for
    ceil(relax_s / dt) steps (no rest test, no step budget) and the centre
    displacement of every fragment is reported. Pure; jit or vmap it.

    Args:
        params: the parameters the deposit was computed with.
        block: its block.
        st: its final ``State`` (``rollout``).
        relax_s: simulated time of the check, s (static).
        options: static options (``chunk`` and the pair search are used).

    Returns:
        ``DepositCheck``.
    """
    relaxed = params._replace(local_damping=0.0, restitution=1.0,
                              stop_hold_s=float("inf"))
    c = consts(relaxed, block)
    n = block.n_side
    k_nb = min(options.n_neighbors, n * n - 1)
    n_steps = jnp.ceil(relax_s / c.dt).astype(jnp.int32)
    s0 = st._replace(status=jnp.asarray(RUNNING, jnp.int32), n_steps=jnp.asarray(0, jnp.int32),
                     slow_s=jnp.zeros_like(st.slow_s))
    opts = options._replace(max_steps=np.iinfo(np.int32).max)

    def chunk(s):
        nbr = neighbours(s, k_nb, opts) if n > 1 else None
        if nbr is not None and opts.pair_search != "knn":
            nbr = (*nbr[:3], True)

        def one(_, x):
            y = step_with_stations(x, relaxed, c, nbr, opts, block)
            return jax.tree.map(lambda new, old: jnp.where(x.n_steps < n_steps, new, old), y, x)

        return lax.fori_loop(0, opts.chunk, one, s)

    end = lax.while_loop(lambda s: (s.n_steps < n_steps) & (s.status == RUNNING), chunk, s0)
    keep = ~st.exited
    disp = jnp.where(keep, jnp.sqrt(jnp.sum((end.pos - st.pos) ** 2, axis=-1)), 0.0)
    n_keep = jnp.maximum(jnp.sum(keep), 1)
    return DepositCheck(disp_m=disp, max_disp_m=jnp.max(disp),
                        mean_disp_m=jnp.sum(disp) / n_keep,
                        rot_rad=jnp.where(keep, jnp.abs(end.theta - st.theta), 0.0),
                        n_left=jnp.sum(end.exited & keep), relax_s=end.n_steps * c.dt,
                        status=end.status, state=end)

