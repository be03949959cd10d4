"""The fragmentation options of the hazard run (``python -m calib.hazard``
``--fragmentation``, ``--frag-energy-kJ``, ``--frag-radius-ratio``,
``--fragments``) and the ``Fragmentation`` they make; how fragments are run and
counted is ``calib.hazard._fragments``."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from solvers import crsp, dem

__all__ = ["Fragmentation", "FragmentationError", "add_options", "fragmentation_from_args",
           "solver_defaults"]

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
                ``functools.partial`` of ``_units.crsp_chunk``, ``seeded_chunk`` or
                ``dem_chunk``, whose arguments and static sizes the fragment units
                take).
            on_result: the run's ``on_result(tag, ChunkStats)``.
            cal, draws: the calibration and the draws (the DEM's alpha law).
            sizes_m, stations_x_m: (T,), (S,) the run's sizes and stations, m.
            dem_run: the DEM numerics (``calib.model.dem_run.DemRun``).

        Returns:
            (units, on_result, ``FragmentCounts`` filled as the units finish).
        """
        from calib.hazard._fragments import (
            FragmentCounts,
            crsp_fragment_chunk,
            dem_units,
            seeded_fragment_chunk,
        )
        from calib.hazard._units import seeded_chunk

        counts = FragmentCounts.empty(self, len(draws.values), len(sizes_m),
                                      len(stations_x_m), sizes_m)
        if self.model == "crsp":  # each CRSP chunk's fragment twin, on its arguments
            twin = {seeded_chunk: seeded_fragment_chunk}
            new = ((tag, make_args, functools.partial(twin.get(fn.func, crsp_fragment_chunk),
                                                      spec=self, **fn.keywords))
                   for tag, make_args, fn in units)
        else:
            new = dem_units(self, units, cal, draws, sizes_m, dem_run)

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
