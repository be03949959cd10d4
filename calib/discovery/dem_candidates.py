"""DEM candidates of the discrepancy workflow: one damping coefficient (baseline),
the size-dependent law alpha(L) = a L^-b, and bonded fragments.

A block of size d is a square of side L = d (``calib.files.observations``).

* ``none``: alpha the same for every size (theta = (alpha,)), the DEM the
  paper started from before it made alpha depend on size.
* ``size_dissipation``: alpha(L) = a L^-b (theta = (a, b)), the paper's remedy
  (Table 1).
* ``fragmentation``: one alpha and the block pre-split into 2 x 2 bonded
  fragments whose joints have cohesion = tensile strength = 10^s Pa (theta =
  (alpha, s)); joints break by the DEM's Mohr-Coulomb joint law (``solvers.dem``,
  paper eq. 2) and the fragments travel on. The runout of a block is that of
  its furthest fragment (the extent a survey of the deposit records); NaN
  when the block did not finish (``calib.model.unfinished``).

Each is fitted on a fixed grid design (``dem_grid`` of ``calib.model.effects.EFFECTS``):
the DEM is too expensive for adaptive designs on two cores; the fragmented
candidate, about 30 times dearer per block, gets a coarse grid and 4 blocks
per point.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from calib.discovery.candidate_fit import Candidate
from calib.model.alpha_law import alpha_of
from calib.model.dem_run import DEM_RUN, DemRun
from calib.model.effects import DEM_EFFECTS, EFFECTS, effect_box
from calib.model.forward import (
    DemForward,
    as_entries,
    dem_lanes,
    entry_blocks,
    gather_entries,
    lane_calls,
    split_by_profile,
    stack_trees,
)
from calib.model.unfinished import mask_unfinished
from solvers.profile import Profile

__all__ = ["DemEffectForward", "dem_candidates"]

N_FRAGMENTS = 4
# a 2 x 2 fragmented block costs about 30 single blocks (smaller dt, 4 bodies):
# its candidate runs 4 blocks per (design point, size)
FRAG_BLOCKS = 4


@dataclasses.dataclass
class DemEffectForward:
    """DEM runouts (T, S, n_blocks) of a candidate for theta (T, p), NaN for a
    block that did not finish; common random numbers (block j of every theta and
    size uses ``fold_in(key, j)``). ``run``: the DEM numerics (``calib.model.dem_run``),
    the fit's and the hazard run's. ``entries``: what is simulated
    (``calib.model.entries.Entries``, or an array of block sizes), as in
    ``calib.model.forward.DemForward``; each profile's entries run as their
    own forward."""

    profile: Profile
    entries: object
    n_blocks: int
    key: jax.Array
    effect: str = "none"
    run: DemRun = DEM_RUN

    def __post_init__(self):
        if self.effect not in DEM_EFFECTS:
            raise ValueError(f"effect {self.effect!r} is not available for the DEM")
        self.entries = as_entries(self.entries, self.profile)
        self._parts = split_by_profile(self)  # entries on other profiles: own forwards
        if self.effect != "fragmentation":
            form = "constant" if self.effect == "none" else "power"
            self._single = DemForward(self.profile, self.entries, self.n_blocks, self.key,
                                      form=form, run=self.run)

    @property
    def sizes_m(self) -> np.ndarray:
        """(S,) block size of each entry, m."""
        return self.entries.sizes_m

    @property
    def box(self):
        return effect_box(self.effect, self.profile, "dem")

    def runouts(self, theta) -> np.ndarray:
        theta = np.atleast_2d(np.asarray(theta, float))
        if self._parts is not None:
            return gather_entries(self._parts, len(self.sizes_m), lambda sub, _: sub.runouts(theta))
        if self.effect != "fragmentation":
            return self._single.runouts(theta)
        return np.stack([self._fragmented(a, s) for a, s in theta])

    def _fragmented(self, alpha: float, log10_strength: float) -> np.ndarray:
        strength = 10.0 ** float(log10_strength)
        e = self.entries
        params = self.run.params(self.profile, c_joint_pa=strength, t_joint_pa=strength,
                                 rho=e.density_kg_m3)
        sides = e.dem_side_m
        # the one clipping rule of calib.model.alpha_law (the box stops at ALPHA_MAX already)
        a = float(alpha_of("constant", [alpha], sides[:1])[0])
        blocks = entry_blocks(e, a, n_fragments=N_FRAGMENTS)
        options = self.run.options(params, sides, n_fragments=N_FRAGMENTS, adaptive=False,
                                   release_errors=e.has_release_errors)
        lanes = [b for b in blocks for _ in range(self.n_blocks)]
        lane_keys = np.tile(np.arange(self.n_blocks), len(blocks))
        # calls of one block side each, of one width (``lane_calls``, as
        # ``DemForward`` runs its lanes); a lane's result does not depend on the
        # lanes that share its call (``solvers.dem._sums``)
        calls = lane_calls(np.repeat(sides, self.n_blocks), a, DemForward.lane_batch)
        furthest = np.empty(len(lanes))
        for idx in calls:
            keys = jax.vmap(lambda j: jax.random.fold_in(self.key, j))(
                jnp.asarray(lane_keys[idx], jnp.uint32))
            res = dem_lanes(params, stack_trees([lanes[i] for i in idx]), keys, options)
            furthest[idx] = mask_unfinished(np.max(np.asarray(res.runout_m), axis=-1), res.status)
        return furthest.reshape(len(blocks), self.n_blocks)


def _grid(box, shape) -> np.ndarray:
    axes = [np.linspace(lo, hi, n) for lo, hi, n in zip(box.lo, box.hi, shape)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(shape))


def _forward(profile, effect, run, entries, n_blocks, key):
    return DemEffectForward(profile, entries, n_blocks, key, effect=effect, run=run)


def dem_candidates(profile, effects=DEM_EFFECTS, run: DemRun = DEM_RUN) -> list[Candidate]:
    """Baseline (one alpha) first, then size-dependent damping and fragmentation,
    each run with the DEM numerics ``run`` (the site's simulated time,
    ``calib.files.site``)."""
    names = ["none"] + [e for e in effects if e != "none"]
    out = []
    for e in names:
        box = effect_box(e, profile, "dem")
        out.append(Candidate(e, box, functools.partial(_forward, profile, e, run),
                             design=functools.partial(_grid, box, EFFECTS[e].dem_grid),
                             n_blocks=FRAG_BLOCKS if e == "fragmentation" else None))
    return out
