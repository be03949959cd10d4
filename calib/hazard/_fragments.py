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
  needs whole fragments); the speed ratio is the solver's.
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
``fragments.csv`` (``fragment_table``: ``FRAGMENT_COLUMNS``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from calib.hazard._stats import ChunkStats, reduce_chunk
from solvers import crsp, dem
from solvers.status import (
    BUDGET,
    INVALID,
    LEFT_PROFILE,
    STOPPED,
    STOPPED_BY_BARRIER,
    finished,
)

__all__ = ["FRAGMENT_COLUMNS", "VARIABLES", "FragmentCounts", "Fragmentation",
           "add_options", "fragment_outputs", "fragment_table", "fragmentation_from_args"]

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
                                            "DEM: square side D / sqrt(N))"),
}

FRAGMENT_COLUMNS = {
    "fragmentation": "how the blocks broke (hazard.nc attribute fragmentation)",
    "block_size_m": "parent block size D, m",
    "fragment_size_m": "fragment size, m (frag_size_m)",
    "n_fragments_per_break": "fragments per broken block",
    "x_m": "station, m",
    "p_break_mean": "fraction of blocks that broke, mean over draws",
    "p_exceed_parent_mean": "fraction of blocks with a piece beyond x (a parent exceeds x "
                            "when any of its fragments does), mean over draws",
    "p_exceed_parent_q05": "its 5 % quantile over draws",
    "p_exceed_parent_q95": "its 95 % quantile over draws",
    "p_exceed_fragment": "fraction of the fragments that end beyond x, all draws pooled",
    "fragments_beyond_per_block_mean": "fragments beyond x per released block, mean over "
                                       "draws",
    "mass_fraction_beyond_mean": "fraction of the released mass that ends beyond x "
                                 "(whole blocks and fragments), mean over draws",
    "fragments_reach_per_block_mean": "fragments passing x per released block, mean over "
                                      "draws",
    "p_E_gt_30kJ_given_fragment_reach": "of the fragments passing x, the fraction with "
                                        "E > 30 kJ, pooled",
    "p_E_gt_300kJ_given_fragment_reach": "the same with E > 300 kJ",
    "p_fragment_unfinished": "fraction of the fragments that did not finish, pooled",
}


# ------------------------------------------------------------------ the options

class FragmentationError(ValueError):
    """A fragmentation option the run cannot take (one line naming the option)."""


def add_options(parser) -> None:
    """The command's option group for fragmentation (``python -m calib.hazard``)."""
    g = parser.add_argument_group(
        "fragmentation", "break the blocks and run every fragment as its own block; tables "
        "per parent block (a block exceeds x when any of its fragments does) and per "
        "fragment (fragments.csv, the frag_* variables of hazard.nc)")
    g.add_argument("--fragmentation", choices=("crsp",), default=None,
                   help="crsp: the CRSP break rule (at the first impact whose normal kinetic "
                        "energy exceeds E_f the block breaks into n = 1/rho^3 fragments of "
                        "radius rho r). E_f: each draw's fitted value where the calibration "
                        "fitted the fragmentation effect (crsp.effects), else "
                        "--frag-energy-kJ (default: off)")
    g.add_argument("--frag-energy-kJ", type=float, default=None,
                   help="CRSP what-if: break energy E_f, kJ per block (replaces a fitted "
                        "one; the summary says it is a what-if)")
    g.add_argument("--frag-radius-ratio", type=float, default=None,
                   help="CRSP: fragment radius / block radius rho in (0, 1), taken as "
                        "n^(-1/3) for the nearest whole n = 1/rho^3 (0.5: 8 fragments, "
                        "0.25: 64); a value other than the solver's makes the run a what-if "
                        f"(default: the solver's, {solver_defaults()[0]:g})")
    g.add_argument("--fragments", type=int, default=None,
                   help="DEM (--model dem): N bonded square fragments per block (4, 16, "
                        "64, ...), whose joints break by the DEM's joint strengths (default: "
                        "one unbroken block)")


@functools.cache
def solver_defaults() -> tuple[float, float]:
    """The CRSP solver's fragment radius ratio rho and speed ratio s (the defaults of
    ``solvers.crsp.params_from_profile``, which a fit of the effect runs with)."""
    from solvers.profile import MATERIAL_COLUMNS, make_profile

    flat = make_profile([0.0, 1.0], [1.0, 0.0], ["z"], {"z": dict.fromkeys(MATERIAL_COLUMNS,
                                                                          0.5)})
    p = crsp.params_from_profile(flat)
    return float(p.frag_radius_ratio), float(p.frag_speed_ratio)


@dataclasses.dataclass(frozen=True)
class Fragmentation:
    """How a hazard run breaks its blocks (``fragmentation_from_args``).

    Attributes:
        model: "crsp" (the CRSP break rule, every fragment run on) or "dem"
            (bonded fragments).
        n_per_break: fragments per broken block: n = 1 / rho^3 (CRSP), N (DEM).
        energy_kJ: CRSP: the what-if break energy E_f, kJ; None: each draw's fitted
            one (the calibration's ``log10_frag_energy_kJ``).
        what_if: the break is not the calibration's (stated in the summary).
        description: one line for the summary and ``hazard.nc``.
    """

    model: str
    n_per_break: int
    energy_kJ: float | None = None
    what_if: bool = False
    description: str = ""

    @property
    def size_ratio(self) -> float:
        """Fragment size / block size: rho = n^(-1/3) (CRSP), 1 / sqrt(N) (DEM)."""
        if self.model == "crsp":
            return float(self.n_per_break) ** (-1.0 / 3.0)
        return 1.0 / math.isqrt(self.n_per_break)

    def plan(self, units, on_result, cal, draws, sizes_m, stations_x_m, dem_run):
        """The run's work units turned into fragment units, and ``on_result`` that
        also keeps the fragment counts (the hook of ``_run.run_hazard``).

        Args:
            units: the plain units of ``_run`` (``(tag, make_args, fn)``; ``fn`` a
                ``functools.partial`` of ``_units.crsp_chunk`` or ``dem_chunk``,
                whose arguments and static sizes the fragment units take).
            on_result: the run's ``on_result(tag, ChunkStats)``.
            cal, draws: the calibration and the draws (the DEM's alpha law).
            sizes_m, stations_x_m: (T,), (S,) the run's sizes and stations, m.
            dem_run: the DEM numerics (``calib.model.dem_run.DemRun``).

        Returns:
            (units, on_result, ``FragmentCounts`` filled as the units finish).
        """
        counts = FragmentCounts.empty(self, len(draws.values), len(sizes_m),
                                      len(stations_x_m), sizes_m)
        if self.model == "crsp":
            new = ((tag, make_args, functools.partial(crsp_fragment_chunk, spec=self,
                                                      **fn.keywords))
                   for tag, make_args, fn in units)
        else:
            new = _dem_units(self, units, cal, draws, sizes_m, dem_run)

        def collect(tag, out):
            on_result(tag, out)
            counts.add(tag, out)

        return new, collect, counts


def fragmentation_from_args(args, cal, draws, profile) -> Fragmentation | None:
    """The run's ``Fragmentation`` from the options of ``add_options``, or None.

    Raises:
        FragmentationError: one line naming the option and what was expected.
    """
    crsp_only = [f for f, v in (("--frag-energy-kJ", args.frag_energy_kJ),
                                ("--frag-radius-ratio", args.frag_radius_ratio)) if v is not None]
    if args.fragments is not None:
        if cal.model != "dem":
            raise FragmentationError(
                f"--fragments {args.fragments}: bonded fragments are the DEM's "
                "(--model dem); CRSP breaks its blocks with --fragmentation crsp")
        n = math.isqrt(max(args.fragments, 0))
        if args.fragments < 4 or n * n != args.fragments:
            raise FragmentationError(
                f"--fragments: expected a perfect square of at least 4 (4, 16, "
                f"64, ...), got {args.fragments}")
        if args.fragmentation or crsp_only:
            raise FragmentationError(
                f"{args.fragmentation and '--fragmentation' or crsp_only[0]}: the "
                "CRSP break rule; the DEM breaks its --fragments by its joints")
        strength = dem.Params._field_defaults
        return Fragmentation("dem", args.fragments, description=(
            f"DEM: each block is {args.fragments} bonded square fragments ({n} x {n}) whose "
            f"joints break at the DEM's joint strengths (solvers.dem.Params: cohesion "
            f"{strength['c_joint_pa'] / 1e6:g} MPa, tension {strength['t_joint_pa'] / 1e6:g} "
            f"MPa, x sqrt of the stiffness scale); alpha of each fragment from the "
            f"calibration's law at the fragment's side"))
    if args.fragmentation is None:
        if crsp_only:
            raise FragmentationError(
                f"{crsp_only[0]}: give --fragmentation crsp to break the blocks")
        return None
    if cal.model != "crsp":
        raise FragmentationError(
            "--fragmentation crsp: the CRSP break rule, and this run is the DEM's; "
            "the DEM breaks bonded fragments: --fragments N")
    return _crsp_fragmentation(args, cal, draws, profile)


def _crsp_fragmentation(args, cal, draws, profile) -> Fragmentation:
    """``fragmentation_from_args`` for ``--fragmentation crsp``."""
    from calib.model.effects import effect_box

    rho0, speed = solver_defaults()
    rho = rho0 if args.frag_radius_ratio is None else args.frag_radius_ratio
    if not (math.isfinite(rho) and 0.0 < rho < 1.0):
        raise FragmentationError(f"--frag-radius-ratio: expected a ratio in (0, 1), got {rho:g}")
    n = round(rho ** -3.0)
    if abs(rho ** -3.0 - n) > 0.01 * n:
        raise FragmentationError(
            f"--frag-radius-ratio {rho:g}: 1/rho^3 = {rho ** -3.0:.4g} is not a "
            f"whole number of fragments (within 1 %); e.g. 0.5 (8 fragments), "
            f"{16 ** (-1 / 3):.5f} (16), 0.25 (64)")
    e = args.frag_energy_kJ
    if e is not None and not (math.isfinite(e) and e > 0.0):
        raise FragmentationError(f"--frag-energy-kJ: expected a positive energy in kJ, got {e:g}")
    column = effect_box("fragmentation", profile).names[0]
    fitted = column in draws.names
    if e is None and not fitted:
        raise FragmentationError(
            f"--fragmentation crsp: {cal.path} has no fitted fragmentation effect "
            f"(crsp.effects does not list it: python -m calib.fit --effect "
            "fragmentation fits it); give --frag-energy-kJ E for a what-if")
    what_if = e is not None or args.frag_radius_ratio is not None and rho != rho0
    if e is None:
        col = np.asarray(draws.values)[:, list(draws.names).index(column)]
        energy = (f"E_f fitted (median over the draws {10.0 ** float(np.median(col)):.4g} kJ, "
                  f"{cal.path}: crsp.{column})")
    else:
        energy = f"E_f = {e:g} kJ (--frag-energy-kJ)"
    rho_used = n ** (-1.0 / 3.0)
    text = (f"CRSP{' WHAT-IF' if what_if else ''}: {energy}; at the first impact whose normal "
            f"kinetic energy exceeds E_f a block breaks into n = {n} fragments of radius "
            f"{rho_used:.4g} r (rho {rho:g} taken as n^(-1/3)), which leave the impact at "
            f"{speed:g} x the rebound speed; every fragment runs on as its own block")
    if what_if:
        text += " (a what-if: not the calibration's fitted break)"
    return Fragmentation("crsp", n, energy_kJ=e, what_if=what_if, description=text)


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
    p = params._replace(frag_radius_ratio=np.full(params.frag_radius_ratio.shape,
                                                  spec.size_ratio))
    if spec.energy_kJ is not None:
        p = p._replace(frag_energy_kJ=np.full(p.frag_energy_kJ.shape, spec.energy_kJ))
    p = put(p)
    split = dataclasses.replace(settings, split_at_break=True)
    res = jax.device_get(crsp.simulate_tasks(p, blocks, key, profile, stations_x_m,
                                             n_per_task=n_chunk, pool=pool, settings=split,
                                             offset=offset))
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
        keys = fragment_keys(key, *put((offset + j, np.concatenate(
            [item_fragment[a:a + batch], np.zeros(batch - m, np.uint32)]))))
        out = jax.device_get(crsp.simulate_fragments(
            *put((_take(p, t), _take(blocks, t), _take(res.breakup, t, j))), keys,
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

def _dem_units(spec: Fragmentation, units, cal, draws, sizes_m, dem_run):
    """The plain DEM units (one size each) with every block split into N bonded
    fragments, each damped by the calibration's alpha law at the fragment's side
    (``_run.dem_alpha``), and the DEM numerics for fragments of the run's sizes
    (``DemRun.options``; under vmap the plain pair list, as the fit's fragment
    candidate runs it)."""
    from calib.hazard._run import dem_alpha

    options = None
    for (d, t_sl), make_args, fn in units:
        params, block, key, offset, n_valid = make_args()
        side = float(block.size_m)
        fragmented = dem.make_block(
            side, alpha=dem_alpha(cal, draws.values[d], side * spec.size_ratio),
            n_fragments=spec.n_per_break, release_x_m=float(block.release_x_m),
            stations=np.asarray(block.stations_x_m))
        if options is None:
            options = dem_run.options(params, sizes_m, n_fragments=spec.n_per_break,
                                      adaptive=False)
        args = (params, fragmented, key, offset, n_valid)
        yield (d, t_sl), (lambda args=args: args), functools.partial(
            dem_fragment_chunk, n_chunk=fn.keywords["n_chunk"], options=options)


@functools.partial(jax.jit, static_argnames=("n_chunk", "options"))
def _dem_blocks(params, block, key, offset, *, n_chunk: int, options):
    """DEM blocks ``offset .. offset + n_chunk - 1`` (block j keyed fold_in(key, j),
    as ``_units.dem_chunk`` keys them), not reduced."""
    idx = (offset + jnp.arange(n_chunk)).astype(jnp.uint32)
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)
    return jax.vmap(lambda k: dem.simulate(params, block, k, options))(keys)


def dem_fragment_status(block_status, exited, stopped) -> np.ndarray:
    """(B, N) status of each fragment from the blocks' (B,) status and the
    fragments' (B, N) flags, as ``python -m solvers.dem`` reports fragments:
    INVALID for every fragment of an invalid block, else LEFT_PROFILE for one
    that passed the profile's end, STOPPED for one at rest in a finished block,
    else the block's (BUDGET)."""
    block = np.broadcast_to(np.asarray(block_status)[:, None], np.shape(exited))
    return np.where(block == INVALID, INVALID,
                    np.where(exited, LEFT_PROFILE, np.where(stopped, STOPPED, block)))


def dem_fragment_chunk(params, block, key, offset, n_valid, *, n_chunk: int,
                       options) -> FragmentStats:
    """DEM blocks of N bonded fragments, reduced per parent and per fragment (T = 1).

    The arguments are those of ``_units.dem_chunk``, ``block`` with N fragments.
    Energies: the DEM's kJ per metre of width times the block's side D (module
    docstring).
    """
    from solvers.stations import StationRecord

    res = jax.device_get(_dem_blocks(params, block, key, offset, n_chunk=n_chunk,
                                     options=options))
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

PER_PARENT = ("per parent block: n_exceed, n_reach, the energy / speed / clearance variables "
              "and the tables built from them count released blocks; a block exceeds "
              "(reaches) x when any of its pieces ends beyond (passes) x, and its values at x "
              "are the largest among its pieces that pass x (calib.hazard._fragments)")
_ENERGY = {"crsp": "kJ per fragment (mass rho^3 m)",
           "dem": "the 2D DEM's kJ per metre of width times the block's side D: kJ per "
                  "fragment taken as a prism D wide (a slice of the block's cube)"}


def add_variables(ds, counts: FragmentCounts) -> None:
    """Add the ``VARIABLES`` and the fragmentation attributes to a results Dataset
    (in place): ``fragmentation`` (how the blocks broke), ``fragmentation_what_if``
    (1 where not the calibration's break), ``fragmentation_per_parent``,
    ``fragment_energy_basis``."""
    import xarray as xr

    values = counts.variables()
    for name, (dims, units, meaning) in VARIABLES.items():
        ds[name] = xr.Variable(dims, np.asarray(values[name]),
                               attrs={"units": units, "long_name": meaning})
    spec = counts.spec
    ds.attrs.update(fragmentation=spec.description, fragmentation_what_if=int(spec.what_if),
                    fragmentation_per_parent=PER_PARENT,
                    fragment_energy_basis=_ENERGY[spec.model])


def fragment_table(ds) -> pd.DataFrame:
    """``fragments.csv``: one row per block size and station, ``FRAGMENT_COLUMNS``
    (from a results Dataset with ``add_variables``' variables)."""
    n = int(ds.attrs["n_blocks_per_draw"])
    x = ds["x_m"].values
    c = {k: ds[k].values.astype(np.float64) for k in VARIABLES if k.startswith("frag_n")}
    p_parent = ds["n_exceed"].values / n                      # (D, T, S)
    q = np.quantile(p_parent, [0.05, 0.95], axis=0)
    per = c["frag_n_per_break"][None, :, None]
    mass = (c["frag_n_exceed_whole"] + c["frag_n_exceed"] / per) / n
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled_frag = c["frag_n_fragments"].sum(axis=0)[:, None]
        p_frag = c["frag_n_exceed"].sum(axis=0) / pooled_frag
        reach = c["frag_n_reach"].sum(axis=0)
        p30 = c["frag_n_reach_E_gt_30kJ"].sum(axis=0) / reach
        p300 = c["frag_n_reach_E_gt_300kJ"].sum(axis=0) / reach
        unfinished = c["frag_n_unfinished"].sum(axis=0) / c["frag_n_fragments"].sum(axis=0)
    rows = []
    for t, size in enumerate(ds["block_size_m"].values):
        for s, xs in enumerate(x):
            rows.append({
                "model": str(ds.attrs["model"]),
                "fragmentation": str(ds.attrs["fragmentation"]),
                "block_size_m": float(size),
                "fragment_size_m": float(ds["frag_size_m"].values[t]),
                "n_fragments_per_break": int(ds["frag_n_per_break"].values[t]),
                "x_m": float(xs),
                "p_break_mean": float(np.mean(c["frag_n_broken"][:, t]) / n),
                "p_exceed_parent_mean": float(p_parent[:, t, s].mean()),
                "p_exceed_parent_q05": float(q[0, t, s]),
                "p_exceed_parent_q95": float(q[1, t, s]),
                "p_exceed_fragment": float(p_frag[t, s]),
                "fragments_beyond_per_block_mean": float(c["frag_n_exceed"][:, t, s].mean()
                                                         / n),
                "mass_fraction_beyond_mean": float(mass[:, t, s].mean()),
                "fragments_reach_per_block_mean": float(c["frag_n_reach"][:, t, s].mean() / n),
                "p_E_gt_30kJ_given_fragment_reach": float(p30[t, s]),
                "p_E_gt_300kJ_given_fragment_reach": float(p300[t, s]),
                "p_fragment_unfinished": float(unfinished[t]),
            })
    return pd.DataFrame(rows, columns=["model"] + list(FRAGMENT_COLUMNS))


def fragment_summary(ds, table: pd.DataFrame, road_x_m: float, label: str = "road") -> str:
    """The summary's fragmentation lines: how the blocks broke, and at the station of
    interest per size: P(break), the parent exceedance, fragments and mass beyond."""
    lines = [f"fragmentation: {ds.attrs['fragmentation']}",
             "  the lines above, exceedance.csv and hazard_table.csv are per parent block: a "
             "block exceeds (reaches) x when any of its pieces ends beyond (passes) x "
             "(hazard.nc attribute fragmentation_per_parent)",
             f"  per fragment (fragments.csv, frag_* of hazard.nc), energies "
             f"{ds.attrs['fragment_energy_basis']}:"]
    at = table[np.isclose(table["x_m"], road_x_m)]
    for r in at.itertuples():
        line = (f"  D = {r.block_size_m:g} m ({r.n_fragments_per_break} fragments of "
                f"{r.fragment_size_m:.3g} m): P(break) = {r.p_break_mean:.3g}; P(a piece "
                f"beyond the {label} at x = {road_x_m:g} m) = {r.p_exceed_parent_mean:.3g} "
                f"[5-95 %: {r.p_exceed_parent_q05:.3g}-{r.p_exceed_parent_q95:.3g}]; "
                f"fragments beyond it per block {r.fragments_beyond_per_block_mean:.3g}")
        if np.isfinite(r.p_exceed_fragment):
            line += f" ({r.p_exceed_fragment:.3g} of the fragments)"
        line += f"; share of the released mass beyond it {r.mass_fraction_beyond_mean:.3g}"
        if r.p_fragment_unfinished > 0:
            line += (f"; {r.p_fragment_unfinished:.2%} of the fragments unfinished, not "
                     "counted as runouts")
        lines.append(line)
    return "\n".join(lines)


def fragment_outputs(counts: FragmentCounts | None, results, writers: dict, text: str,
                     road_x_m: float, label: str = "road") -> str:
    """A fragment run's outputs (the command's one call): ``add_variables`` on
    ``results`` (written as ``hazard.nc``), ``fragments.csv`` added to ``writers``,
    the summary ``text`` with ``fragment_summary``'s lines. Without fragments
    (``counts`` None) nothing changes."""
    if counts is None:
        return text
    add_variables(results, counts)
    table = fragment_table(results)
    writers["fragments.csv"] = lambda p: table.to_csv(p, index=False)
    return text + "\n" + fragment_summary(results, table, road_x_m, label)
