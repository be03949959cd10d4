"""Fragmentation in the hazard run: every fragment its own block, reported per
fragment and per parent block.

The seed paper (Sect. 4.2 and 5) breaks its 1.8 m DEM block into 16 fragments,
which stop 110-160 m down the slope, and into 64, which stop 40-110 m, and
concludes that fragmentation "should be taken into proper consideration in the
rockfall hazard evaluation". Two ways of breaking a block are offered:

* CRSP (``--fragmentation crsp``): the solver's break rule (``solvers.crsp._effects``:
  at the first impact whose normal kinetic energy exceeds E_f the block breaks
  into n = 1 / rho^3 fragments of radius rho r). The solver alone follows one
  representative fragment; here every fragment runs on as a block of its own
  (``solvers.crsp._break``): pass 1 runs the released blocks with the run ending
  at a break (``Settings.split_at_break``), pass 2 runs the n fragments of each
  broken block from the state its break record holds, each with its own key
  ``fragment_key(fold_in(K_d, j), i)`` (K_d the draw's key, j the block, i the
  fragment), so results do not depend on chunking. E_f is each draw's fitted
  value where the calibration fitted the ``fragmentation`` effect
  (``calib.model.effects``; its column ``log10_frag_energy_kJ``), or the
  ``--frag-energy-kJ`` of a what-if. rho: ``--frag-radius-ratio`` (default the
  solver's, which the fit ran with), taken as n^(-1/3) for the nearest whole n
  so that the n fragments have the block's mass (our choice: the hazard run
  needs whole fragments); the speed ratio is the solver's. Blocks with release
  conditions (a volume class, zone, heights, speeds) are drawn and run as
  ``_units.seeded_chunk`` runs them, one task per block, and broken alike
  (``seeded_fragment_chunk``).
* DEM (``--model dem --fragments N``): the block is N bonded square fragments
  (``solvers.dem.make_block(..., n_fragments=N)``) whose joints break when their
  strength is exceeded (the DEM's own fracture, paper eq. 2, the joint
  strengths of ``solvers.dem.Params``); each fragment's damping is the
  calibration's alpha law at the fragment's side, as the paper assigns alpha by
  fragment size (Sect. 4.2). Every one of the N fragments is counted, bonded or
  not. The DEM's energies are kJ per metre of slope width (2D); as in the
  plain run (``_units``) they are multiplied by the block's side D: each
  fragment is a prism D wide, a slice of the cube of side D the tables take the
  block to be, so the fragments' energies add up to the block's.

Per parent block (the standard variables of ``hazard.nc`` and the tables,
in a fragment run): a block exceeds x when any of its pieces (the block
itself if it did not break, else its fragments) ends beyond x, and reaches x
when it passed x before breaking or any fragment passed x; its energy, speed
and clearance at x are the largest among its pieces that pass x (each the
largest on its own: the envelope of the release, our choice); its status is
the worst of its pieces' (invalid, then unfinished, then left the profile,
then stopped), so a block with an unfinished fragment is unfinished.

Per fragment: the ``frag_*`` variables of ``hazard.nc`` (``VARIABLES``) and
``fragments.csv`` (``calib.hazard._fragment_tables``). The command's options and
the ``Fragmentation`` they make are ``calib.hazard._fragment_options``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from calib.hazard._stats import ChunkStats, reduce_chunk
from calib.hazard._units import seeded_dem_block, seeded_tasks
from solvers import crsp, dem
from solvers.status import (
    BUDGET,
    INVALID,
    LEFT_PROFILE,
    STOPPED,
    STOPPED_BY_BARRIER,
    finished,
)

if TYPE_CHECKING:
    from calib.hazard._fragment_options import Fragmentation

__all__ = ["FRAGMENT_BATCH", "VARIABLES", "FragmentCounts", "FragmentStats",
           "crsp_fragment_chunk", "dem_fragment_chunk", "dem_fragment_status", "dem_units",
           "fragment_keys", "seeded_fragment_chunk"]

# fragments run side by side in one vmapped call: at most this many (a power of
# two, at least 16: XLA:CPU's vector loop and scalar tail round differently)
FRAGMENT_BATCH = 512

_DTS = ("draw", "block_size_m", "x_m")
_DT = ("draw", "block_size_m")
# name -> (dims, units, meaning): the per-fragment variables of hazard.nc
VARIABLES = {
    "frag_n_broken": (_DT, "1", "blocks that broke (CRSP: at an impact above E_f; DEM: "
                                "at least one joint broken)"),
    "frag_n_fragments": (_DT, "1", "fragments simulated (CRSP: n per broken block; DEM: "
                                   "N per block, bonded or not)"),
    "frag_n_exceed": (_DTS, "1", "finished fragments whose final abscissa lies beyond x"),
    "frag_n_exceed_whole": (_DTS, "1", "finished blocks that did not break (CRSP) whose "
                                       "final abscissa lies beyond x (DEM: 0, every block "
                                       "runs as its fragments)"),
    "frag_n_reach": (_DTS, "1", "fragments that passed x moving downslope after their "
                                "break (invalid ones excluded)"),
    "frag_n_reach_E_gt_30kJ": (_DTS, "1", "of those, fragments with E > 30 kJ"),
    "frag_n_reach_E_gt_300kJ": (_DTS, "1", "of those, fragments with E > 300 kJ"),
    "frag_n_unfinished": (_DT, "1", "fragments still moving at the solver's budget, or "
                                    "invalid"),
    "frag_n_left_profile": (_DT, "1", "fragments that left the profile moving"),
    "frag_n_per_break": (("block_size_m",), "1", "fragments per broken block"),
    "frag_size_m": (("block_size_m",), "m", "fragment size (CRSP: sphere diameter rho D; "
                                            "DEM: square side D / sqrt(N)); over volume "
                                            "classes, of the class's representative D (each "
                                            "block breaks into rho times its own diameter)"),
}



# ------------------------------------------------------------------- the counts

class FragmentStats(NamedTuple):
    """A fragment unit's summaries: every ``_stats.ChunkStats`` field, per parent
    block (the run's ``on_result`` reads them), then the per-fragment counts of
    the T tasks (sizes): ``broken``, ``fragments``, ``unfinished``, ``left``
    (T,); ``exceed``, ``exceed_whole``, ``reach``, ``e30``, ``e300`` (T, S)
    (``VARIABLES``, without the prefix ``frag_n_``)."""

    n_blocks: np.ndarray
    n_unfinished: np.ndarray
    n_left_profile: np.ndarray
    exceed: np.ndarray
    reach: np.ndarray
    e30: np.ndarray
    e300: np.ndarray
    hist_energy_kJ: np.ndarray
    hist_velocity_m_s: np.ndarray
    hist_bounce_height_m: np.ndarray
    frag_broken: np.ndarray
    frag_fragments: np.ndarray
    frag_unfinished: np.ndarray
    frag_left: np.ndarray
    frag_exceed: np.ndarray
    frag_exceed_whole: np.ndarray
    frag_reach: np.ndarray
    frag_e30: np.ndarray
    frag_e300: np.ndarray


_PER_DRAW = ("broken", "fragments", "unfinished", "left", "exceed", "exceed_whole", "reach",
             "e30", "e300")
_NAME = {"broken": "frag_n_broken", "fragments": "frag_n_fragments",
         "unfinished": "frag_n_unfinished", "left": "frag_n_left_profile",
         "exceed": "frag_n_exceed", "exceed_whole": "frag_n_exceed_whole",
         "reach": "frag_n_reach", "e30": "frag_n_reach_E_gt_30kJ",
         "e300": "frag_n_reach_E_gt_300kJ"}


@dataclasses.dataclass
class FragmentCounts:
    """A run's per-fragment counts (``VARIABLES``; D draws, T sizes, S stations).

    Attributes:
        spec: the ``Fragmentation``.
        sizes_m: (T,) block sizes D, m.
        counts: name of ``VARIABLES`` -> (D, T) or (D, T, S) int64 counts.
    """

    spec: Fragmentation
    sizes_m: np.ndarray
    counts: dict

    @classmethod
    def empty(cls, spec, n_draws, n_sizes, n_stations, sizes_m):
        counts = {_NAME[k]: np.zeros((n_draws, n_sizes) + ((n_stations,) if k in (
            "exceed", "exceed_whole", "reach", "e30", "e300") else ()), np.int64)
            for k in _PER_DRAW}
        return cls(spec, np.asarray(sizes_m, np.float64), counts)

    def add(self, tag, out: FragmentStats) -> None:
        d, t_sl = tag
        for k in _PER_DRAW:
            self.counts[_NAME[k]][d, t_sl] += np.asarray(getattr(out, f"frag_{k}"))

    def variables(self) -> dict:
        """Every array of ``VARIABLES``."""
        n = np.full(len(self.sizes_m), self.spec.n_per_break, np.int64)
        return {**self.counts, "frag_n_per_break": n,
                "frag_size_m": self.sizes_m * self.spec.size_ratio}


# --------------------------------------------- per parent block, from its pieces

_RANK = {STOPPED: 0, STOPPED_BY_BARRIER: 0, LEFT_PROFILE: 1, BUDGET: 2, INVALID: 3}
_FROM_RANK = np.array([STOPPED, LEFT_PROFILE, BUDGET, INVALID], np.int32)


def _rank(status: np.ndarray) -> np.ndarray:
    """Severity of a status (0 stopped, 1 left the profile, 2 unfinished, 3 invalid)."""
    out = np.full(status.shape, 2, np.int32)  # RUNNING or BUDGET: unfinished
    for code, r in _RANK.items():
        out[status == code] = r
    return out


class _Parents:
    """Per-parent arrays (R parents, S stations) that fragments are folded into."""

    def __init__(self, stop_x, status, stations):
        self.stop_x = np.array(stop_x, np.float64)
        self.rank = _rank(np.asarray(status))
        self.passed = np.array(stations.passed, bool)
        self.values = [np.where(self.passed, np.asarray(v, np.float64), np.nan) for v in (
            stations.energy_kJ, stations.velocity_m_s, stations.bounce_height_m)]

    def reset(self, rows: np.ndarray) -> None:
        """Rows whose end is their fragments': no stop yet, status 'stopped'."""
        self.stop_x[rows] = np.nan
        self.rank[rows] = 0

    def fold(self, parent: np.ndarray, stop_x, status, stations, energy_kJ) -> None:
        """Fold fragments (F,) of rows ``parent`` into their parents (module docstring)."""
        status = np.asarray(status)
        done = finished(status)
        np.fmax.at(self.stop_x, parent, np.where(done, stop_x, np.nan))
        np.maximum.at(self.rank, parent, _rank(status))
        ok = np.asarray(stations.passed) & (status != INVALID)[:, None]
        np.logical_or.at(self.passed, parent, ok)
        for acc, v in zip(self.values, (energy_kJ, stations.velocity_m_s,
                                        stations.bounce_height_m), strict=True):
            np.fmax.at(acc, parent, np.where(ok, np.asarray(v, np.float64), np.nan))

    def status(self) -> np.ndarray:
        return _FROM_RANK[self.rank]


def _fragment_counts(t: np.ndarray, n_tasks: int, stop_x, status, stations, energy_kJ,
                     stations_x_m) -> dict:
    """Per-fragment counts of fragments (F,) of tasks ``t`` (``FragmentStats``)."""
    status = np.asarray(status)
    done = finished(status)
    ok = np.asarray(stations.passed) & (status != INVALID)[:, None]
    e = np.asarray(energy_kJ, np.float64)
    per_station = {"exceed": done[:, None] & (np.asarray(stop_x)[:, None] > stations_x_m),
                   "reach": ok, "e30": ok & (e > 30.0), "e300": ok & (e > 300.0)}
    out = {}
    for k, v in per_station.items():
        out[k] = np.zeros((n_tasks, v.shape[1]), np.int64)
        np.add.at(out[k], t, v)
    for k, v in (("unfinished", ~done), ("left", status == LEFT_PROFILE)):
        out[k] = np.bincount(t, weights=v, minlength=n_tasks).astype(np.int64)
    return out


@jax.jit
def _reduce(stop_x_m, status, passed, energy_kJ, velocity_m_s, bounce_height_m, valid,
            stations_x_m) -> ChunkStats:
    """``_stats.reduce_chunk`` under jit (the bins are computed as in the plain run)."""
    return reduce_chunk(stop_x_m, status, passed, energy_kJ, velocity_m_s, bounce_height_m,
                        valid, stations_x_m)


def _on_device_of(x):
    """``put(tree)``: ``tree`` committed to the device of the array ``x`` (a unit's
    arrays stay on the device ``_sharding`` gave it; committed arguments alike also
    share one compiled program)."""
    device = next(iter(x.devices()))
    return lambda tree: jax.device_put(tree, device)


def _stats(parents: _Parents, shape, valid, stations_x_m, frag: dict, put) -> FragmentStats:
    """The unit's ``FragmentStats``: the parents reduced as the plain run reduces its
    blocks (``_stats.reduce_chunk``, on the unit's device: ``put``), and the fragment
    counts ``frag``."""
    e, v, h = (a.reshape(shape + (-1,)) for a in parents.values)
    stats = jax.device_get(_reduce(*put((
        parents.stop_x.reshape(shape), parents.status().reshape(shape),
        parents.passed.reshape(shape + (-1,)), e, v, h, valid, np.asarray(stations_x_m)))))
    return FragmentStats(*stats, **{f"frag_{k}": frag[k] for k in _PER_DRAW})


# --------------------------------------------------------------------------- CRSP

@jax.jit
def fragment_keys(key, block_index, fragment_index):
    """Keys (F,) of fragments ``fragment_index`` of blocks ``block_index`` of the draw
    keyed ``key``: ``solvers.crsp.fragment_key(fold_in(key, j), i)``."""
    return jax.vmap(lambda j, i: crsp.fragment_key(jax.random.fold_in(key, j), i))(
        jnp.asarray(block_index, jnp.uint32), jnp.asarray(fragment_index, jnp.uint32))


def _batch_size(n_items: int) -> int:
    """Fragments per vmapped call: a power of two from 16 to ``FRAGMENT_BATCH``."""
    return int(min(FRAGMENT_BATCH, max(16, 1 << max(n_items - 1, 0).bit_length())))


def crsp_fragment_chunk(params, blocks, key, profile, stations_x_m, offset, n_valid, *,
                        n_chunk: int, pool: int, settings: crsp.Settings,
                        spec: Fragmentation) -> FragmentStats:
    """Blocks ``offset .. offset + n_chunk - 1`` of every task (size) broken into
    fragments, each run as its own block; reduced per parent and per fragment.

    The arguments are those of ``_units.crsp_chunk``. Pass 1 runs the blocks with
    ``split_at_break`` (a broken block's passages are its own up to the break);
    pass 2 runs the n fragments of every broken block (``fragment_keys``,
    ``solvers.crsp.simulate_fragments``) in batches of ``_batch_size``, folded
    into their parents as they come (host memory stays bounded by the chunk and
    the batch).
    """
    put = _on_device_of(stations_x_m)
    p = put(_break_params(params, spec))
    split = dataclasses.replace(settings, split_at_break=True)
    res = jax.device_get(crsp.simulate_tasks(p, blocks, key, profile, stations_x_m,
                                             n_per_task=n_chunk, pool=pool, settings=split,
                                             offset=offset))
    return _fragments_of_pass(res, p, blocks, key, profile, stations_x_m, offset, n_valid,
                              n_chunk=n_chunk, settings=settings, spec=spec, per_block=False)


def seeded_fragment_chunk(params, seeds, density_kg_m3, key, profile, stations_x_m, offset,
                          n_valid, *, n_chunk: int, pool: int, kinds: tuple[str, str],
                          settings: crsp.Settings, spec: Fragmentation) -> FragmentStats:
    """``crsp_fragment_chunk`` for blocks with release conditions: blocks ``offset ..
    offset + n_chunk - 1`` of one class (T = 1), each drawn and run as its own task
    (``_units.seeded_tasks``: its volume, sphere, release abscissa, height and speed
    from its key, as ``_units.seeded_chunk`` draws them), broken and fragmented as
    there. The arguments are those of ``_units.seeded_chunk``; a fragment of block j
    is keyed as in the fixed-size run (``fragment_keys``), so a point zone in the
    solver's release state breaks the blocks of the fixed-size run."""
    put = _on_device_of(stations_x_m)
    p = put(_break_params(params, spec))
    tasks, blocks = _seeded_tasks(p, seeds, density_kg_m3, key, offset, n_chunk=n_chunk,
                                  kinds=kinds)
    split = dataclasses.replace(settings, split_at_break=True)
    res = jax.device_get(crsp.simulate_tasks(
        tasks, blocks, key, profile, stations_x_m, n_per_task=1, pool=pool, settings=split,
        offset=offset, task_offsets=put(np.arange(n_chunk, dtype=np.int32))))
    # (n_chunk tasks, 1 block) -> (1 class, n_chunk blocks): the same flat order
    res = jax.tree_util.tree_map(lambda a: np.asarray(a).reshape((1, n_chunk) + a.shape[2:]),
                                 res)
    return _fragments_of_pass(res, tasks, blocks, key, profile, stations_x_m, offset, n_valid,
                              n_chunk=n_chunk, settings=settings, spec=spec, per_block=True)


_seeded_tasks = jax.jit(seeded_tasks, static_argnames=("n_chunk", "kinds"))


def _break_params(params, spec: Fragmentation):
    """``params`` (CRSP ``Params``, any leading axes) with the run's fragment radius
    ratio and, in a what-if, its break energy."""
    p = params._replace(frag_radius_ratio=np.full(np.shape(params.frag_radius_ratio),
                                                  spec.size_ratio))
    if spec.energy_kJ is not None:
        p = p._replace(frag_energy_kJ=np.full(np.shape(p.frag_energy_kJ), spec.energy_kJ))
    return p


def _fragments_of_pass(res, p, blocks, key, profile, stations_x_m, offset, n_valid, *,
                       n_chunk: int, settings: crsp.Settings, spec: Fragmentation,
                       per_block: bool) -> FragmentStats:
    """Pass 2 of a CRSP fragment chunk and the reduction: ``res`` the pass-1
    ``Result`` on the host, (T, n_chunk) blocks; ``p`` and ``blocks`` the tasks'
    ``Params`` and ``Block``: one per task T (``per_block`` False), or one per
    block of the chunk (True: block j's own, T = 1)."""
    put = _on_device_of(stations_x_m)
    st_x = np.asarray(stations_x_m)
    n_tasks, offset, n = res.status.shape[0], int(offset), spec.n_per_break
    valid = np.arange(n_chunk) < int(n_valid)
    # a block made invalid by the event that broke it stays invalid, unbroken
    broken = np.asarray(res.breakup.broken) & valid[None] & (res.status != INVALID)
    flat = jax.tree_util.tree_map(lambda a: np.asarray(a).reshape((-1,) + a.shape[2:]),
                                  (res.stop_x_m, res.status, res.stations))
    parents = _Parents(*flat)
    rows = np.flatnonzero(broken.reshape(-1))
    parents.reset(rows)
    whole = ~broken & valid[None] & finished(res.status)
    frag = _no_fragments(n_tasks, len(st_x))
    frag.update(broken=broken.sum(axis=1).astype(np.int64),
                fragments=n * broken.sum(axis=1).astype(np.int64),
                exceed_whole=np.sum(whole[..., None] & (res.stop_x_m[..., None] > st_x),
                                    axis=1).astype(np.int64))
    item_parent = np.repeat(rows, n)
    item_fragment = np.tile(np.arange(n, dtype=np.uint32), rows.size)
    batch = _batch_size(item_parent.size)
    for a in range(0, item_parent.size, batch):
        par = item_parent[a:a + batch]
        m = par.size
        par_pad = np.concatenate([par, np.repeat(par[-1:], batch - m)])
        t, j = par_pad // n_chunk, par_pad % n_chunk
        own = j if per_block else t  # the row of p and blocks
        keys = fragment_keys(key, *put((offset + j, np.concatenate(
            [item_fragment[a:a + batch], np.zeros(batch - m, np.uint32)]))))
        out = jax.device_get(crsp.simulate_fragments(
            *put((_take(p, own), _take(blocks, own), _take(res.breakup, t, j))), keys,
            put(_barrier_open(res.barrier, t, j)), profile, stations_x_m, settings))
        out = jax.tree_util.tree_map(lambda x: np.asarray(x)[:m], out)
        parents.fold(par, out.stop_x_m, out.status, out.stations, out.stations.energy_kJ)
        c = _fragment_counts(t[:m], n_tasks, out.stop_x_m, out.status, out.stations,
                             out.stations.energy_kJ, st_x)
        for k, v in c.items():
            frag[k] += v
    return _stats(parents, (n_tasks, n_chunk), valid, st_x, frag, put)


def _barrier_open(barrier, t, j) -> np.ndarray:
    """bool per fragment: its block had not met the barrier (every block, in a run
    without one: ``Result.barrier`` None), so the fragment still can."""
    if barrier is None:
        return np.ones(np.shape(t), bool)
    return ~np.asarray(barrier.reached)[t, j]


def _no_fragments(n_tasks: int, n_stations: int) -> dict:
    """Zero counts of every ``FragmentStats`` fragment field."""
    return {k: np.zeros((n_tasks, n_stations) if k in ("exceed", "exceed_whole", "reach",
                                                       "e30", "e300") else (n_tasks,),
                        np.int64) for k in _PER_DRAW}


def _take(tree, t, j=None):
    """Leaves of ``tree`` at task ``t`` (and block ``j``): (F, ...) NumPy arrays."""
    return jax.tree_util.tree_map(
        lambda a: np.asarray(a)[t] if j is None else np.asarray(a)[t, j], tree)


# ---------------------------------------------------------------------------- DEM

def dem_units(spec: Fragmentation, units, cal, draws, sizes_m, dem_run):
    """The plain DEM units (one size each) with every block split into N bonded
    fragments, each damped by the calibration's alpha law at the fragment's side
    (``_run.dem_alpha``), and the DEM numerics for fragments of the run's sizes
    (``DemRun.options``; under vmap the plain pair list, as the fit's fragment
    candidate runs it)."""
    from calib.hazard._run import dem_alpha

    options = None
    for (d, t_sl), make_args, fn in units:
        params, block, key, offset, n_valid, seeds = make_args()
        side = float(block.size_m)
        fragmented = dem.make_block(
            side, alpha=dem_alpha(cal, draws.values[d], side * spec.size_ratio),
            n_fragments=spec.n_per_break, release_x_m=float(block.release_x_m),
            stations=np.asarray(block.stations_x_m))
        if options is None:
            options = dem_run.options(params, sizes_m, n_fragments=spec.n_per_break,
                                      adaptive=False)
        args = (params, fragmented, key, offset, n_valid, seeds)
        yield (d, t_sl), (lambda args=args: args), functools.partial(
            dem_fragment_chunk, n_chunk=fn.keywords["n_chunk"], options=options,
            kinds=fn.keywords["kinds"])


@functools.partial(jax.jit, static_argnames=("n_chunk", "options", "kinds"))
def _dem_blocks(params, block, key, offset, seeds=None, *, n_chunk: int, options, kinds=None):
    """DEM blocks ``offset .. offset + n_chunk - 1`` (block j keyed fold_in(key, j)
    and released as ``seeds`` draw it, as ``_units.dem_chunk`` keys and releases
    them), not reduced."""
    keys = crsp.block_keys(key, offset, n_chunk)
    return jax.vmap(lambda k: dem.simulate(params, seeded_dem_block(block, seeds, kinds, k),
                                           k, options))(keys)


def dem_fragment_status(block_status, exited, stopped) -> np.ndarray:
    """(B, N) status of each fragment from the blocks' (B,) status and the
    fragments' (B, N) flags, as ``python -m solvers.dem`` reports fragments:
    INVALID for every fragment of an invalid block, else LEFT_PROFILE for one
    that passed the profile's end, STOPPED for one at rest in a finished block,
    else the block's (BUDGET)."""
    block = np.broadcast_to(np.asarray(block_status)[:, None], np.shape(exited))
    return np.where(block == INVALID, INVALID,
                    np.where(exited, LEFT_PROFILE, np.where(stopped, STOPPED, block)))


def dem_fragment_chunk(params, block, key, offset, n_valid, seeds=None, *, n_chunk: int,
                       options, kinds=None) -> FragmentStats:
    """DEM blocks of N bonded fragments, reduced per parent and per fragment (T = 1).

    The arguments are those of ``_units.dem_chunk``, ``block`` with N fragments
    (with ``seeds``, each block released where and how its key draws it).
    Energies: the DEM's kJ per metre of width times the block's side D (module
    docstring).
    """
    from solvers.stations import StationRecord

    res = jax.device_get(_dem_blocks(params, block, key, offset, seeds, n_chunk=n_chunk,
                                     options=options, kinds=kinds))
    st_x = np.asarray(block.stations_x_m)
    n_frag, n_st = np.asarray(block.alpha).shape[0], st_x.shape[0]
    valid = np.arange(n_chunk) < int(n_valid)
    status = dem_fragment_status(res.status, res.exited, res.stopped)[valid].reshape(-1)
    flat = jax.tree_util.tree_map(
        lambda a: np.asarray(a)[valid].reshape((-1,) + np.shape(a)[2:]),
        (res.stop_x_m, res.stations))
    energy_kJ = flat[1].energy_kJ * float(block.size_m)  # per metre -> per fragment prism
    nan = np.full((n_chunk, n_st), np.nan)
    parents = _Parents(np.full(n_chunk, np.nan), np.full(n_chunk, STOPPED),
                       StationRecord(np.zeros((n_chunk, n_st), bool), nan, nan, nan))
    parent = np.repeat(np.flatnonzero(valid), n_frag)
    parents.fold(parent, flat[0], status, flat[1], energy_kJ)
    frag = _no_fragments(1, n_st)
    frag.update(_fragment_counts(np.zeros(parent.size, np.int64), 1, flat[0], status,
                                 flat[1], energy_kJ, st_x))
    broken = (np.asarray(res.joints_broken) > 0.0) & valid
    frag.update(broken=np.array([broken.sum()], np.int64),
                fragments=np.array([n_frag * valid.sum()], np.int64))
    return _stats(parents, (1, n_chunk), valid, st_x, frag,
                  _on_device_of(block.stations_x_m))


# ------------------------------------------------------------ hazard.nc and tables
