"""The checked inputs of one design command: barrier positions, the design block,
its density and the partial factors. Every refusal is a ``DesignError`` (the
command turns it into one line) whose text names the file or the option at
fault."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from calib.design._factors import GAMMA_E, Factors
from calib.design._values import DesignBlock, station_index
from calib.files.hazard_results import optional_attr

__all__ = ["DEFAULT_DENSITY_KG_M3", "as_dict", "check_barrier", "design_block",
           "factors_from_args", "profile_range", "scan_positions"]

# the toolkit's rock density where nothing says otherwise: the seed paper, Sect. 4.1
DEFAULT_DENSITY_KG_M3 = 2350.0



class DesignError(ValueError):
    """Bad design input; the message names the option or file, and what was expected."""

def profile_range(ds) -> tuple[float, float]:
    """(first, last) abscissa of the run's profile (its stations where the file has
    no vertices)."""
    xs = ds["profile_x_m"].values
    if xs.size < 2:
        xs = ds["x_m"].values
    return float(xs.min()), float(xs.max())


def check_barrier(ds, path: str, x_m: float, what: str = "--barrier-x-m") -> int:
    """The station index of a barrier at ``x_m``.

    Raises:
        DesignError: outside the profile, at or above the release, at or below the
            station of interest, not a station of the run.
    """
    lo, hi = profile_range(ds)
    release = float(ds.attrs["release_x_m"])
    road = optional_attr(ds, "road_x_m")
    label = optional_attr(ds, "road_label") or "station of interest"
    if not (math.isfinite(x_m) and lo <= x_m <= hi):
        raise DesignError(f"{what} {x_m:g}: outside the profile [{lo:g}, {hi:g}] m of {path}")
    if x_m <= release:
        raise DesignError(f"{what} {x_m:g}: at or above the release at x = {release:g} m "
                       f"({path}, attribute release_x_m): no block passes it")
    if road is not None and x_m >= road:
        raise DesignError(f"{what} {x_m:g}: at or below the {label} at x = {road:g} m "
                       f"({path}, attribute road_x_m) it is to protect")
    s = station_index(ds, x_m)
    if s is None:
        xs = ds["x_m"].values
        near = xs[np.argsort(np.abs(xs - x_m))[:2]]
        raise DesignError(f"{what} {x_m:g}: not a station of {path} (nearest: "
                       f"{', '.join(f'{v:g}' for v in sorted(near))} m); rerun python -m "
                       "calib.hazard with --stations including it")
    return s


def scan_positions(ds, path: str, xs) -> list[float]:
    """The scanned stations ``xs`` (``--scan-x-m A:B:STEP`` parsed), each one
    checked as a barrier position."""
    xs = list(xs)
    for x in xs:
        check_barrier(ds, path, x, "--scan-x-m: position")
    return xs


def _size(ds, path: str, size_m: float | None, percentile: float | None) -> float:
    sizes = np.sort(ds["block_size_m"].values)
    listed = ", ".join(f"{s:g}" for s in sizes)
    if size_m is not None and percentile is not None:
        raise DesignError("--block-size-m and --block-size-percentile: give one of them")
    if percentile is not None:
        if not (math.isfinite(percentile) and 0 < percentile <= 100):
            raise DesignError(f"--block-size-percentile {percentile:g}: expected a percentile "
                           "in (0, 100]")
        return float(np.percentile(sizes, percentile, method="inverted_cdf"))
    if size_m is None:
        return float(sizes[-1])
    hit = np.flatnonzero(np.isclose(sizes, size_m, rtol=0.0, atol=1e-9))
    if not hit.size:
        raise DesignError(f"--block-size-m {size_m:g}: not a block size of {path} ({listed} m)")
    return float(sizes[hit[0]])


def design_block(ds, path: str, *, size_m=None, size_percentile=None, volume_m3=None,
                 density_kg_m3=None, thickness_m=None) -> tuple[DesignBlock, list[str]]:
    """The design block and the warnings to print about it.

    Size: ``size_m`` (a size of the run), else the ``size_percentile``-th
    percentile of the run's sizes (NumPy's "inverted_cdf": one of them), else the
    largest. Volume: ``volume_m3``, else the CRSP block's pi D^3 / 6 (D the diameter of
    the sphere of its volume, in every shape: ``calib.model.entries``) or the DEM
    square's D^2 times ``thickness_m`` (required for the DEM: its energies are per
    metre of width). Density: ``density_kg_m3``, else the file's
    ``rock_density_kg_m3`` (the calibration's, the site's), else 2350 kg/m^3 with a
    warning.
    """
    model = str(ds.attrs["model"])
    d = _size(ds, path, size_m, size_percentile)
    warnings = []
    for name, v in (("--design-volume-m3", volume_m3), ("--density-kg-m3", density_kg_m3),
                    ("--dem-thickness-m", thickness_m)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise DesignError(f"{name} {v:g}: expected a positive number")
    if model == "dem" and thickness_m is None:
        raise DesignError(f"{path}: a DEM run's energies are per metre of slope width (here "
                       "taken per cube of side D); give --dem-thickness-m to convert them to "
                       "a block of that thickness")
    if model != "dem" and thickness_m is not None:
        raise DesignError(f"--dem-thickness-m: {path} is a {model.upper()} run, not a DEM one")
    shape = (str(ds["block_shape"].sel(block_size_m=d).item()) if "block_shape" in ds
             else "sphere")
    # the simulated block's volume: D is the diameter of the sphere of its volume, in
    # every CRSP shape (calib.model.entries)
    sim_vol = d**3 if model == "dem" else math.pi * d**3 / 6.0
    if volume_m3 is not None:
        vol, vol_src = float(volume_m3), "--design-volume-m3"
    elif model == "dem":
        vol, vol_src = d * d * thickness_m, f"D^2 x --dem-thickness-m {thickness_m:g} m"
    elif shape != "sphere":
        vol, vol_src = sim_vol, (f"CRSP {shape} of the volume of the sphere of diameter D, "
                                 "pi D^3 / 6 (calib.model.entries)")
    else:
        vol, vol_src = math.pi * d**3 / 6.0, "sphere of diameter D, pi D^3 / 6"
    if density_kg_m3 is not None:
        rho, rho_src = float(density_kg_m3), "--density-kg-m3"
    elif optional_attr(ds, "rock_density_kg_m3") is not None:
        rho = float(ds.attrs["rock_density_kg_m3"])
        rho_src = f"{path}: " + (optional_attr(ds, "rock_density_source")
                                 or "rock_density_kg_m3")
    else:
        rho, rho_src = DEFAULT_DENSITY_KG_M3, "toolkit default (the seed paper, Sect. 4.1)"
        warnings.append(f"warning: no rock density in {path} (its calibration has no "
                        f"rock_density_kg_m3) and no --density-kg-m3: using "
                        f"{DEFAULT_DENSITY_KG_M3:g} kg/m^3")
    mass = float(ds["block_mass_kg"].sel(block_size_m=d))
    simulated = mass / sim_vol
    if not math.isclose(simulated, rho, rel_tol=1e-6):
        warnings.append(f"warning: the run simulated blocks of {simulated:.6g} kg/m^3, the "
                        f"design uses {rho:g} kg/m^3 ({rho_src}): energies are scaled by mass, "
                        "which holds for CRSP's lumped-mass kinematics, not for the DEM's "
                        "contacts")
    return DesignBlock(d, vol, vol_src, rho, rho_src, mass), warnings


def factors_from_args(args) -> tuple[Factors, list[str]]:
    """The partial factors of the command line, checked, and the warnings to print."""
    gamma_e = GAMMA_E[args.energy_level] if args.gamma_e is None else args.gamma_e
    f = Factors(gamma_Tr=args.gamma_tr, gamma_Dp=args.gamma_dp, gamma_VolF=args.gamma_volf,
                gamma_gamma=args.gamma_gamma, gamma_E=gamma_e)
    opts = {"gamma_Tr": f"--gamma-tr {args.gamma_tr:g}", "gamma_Dp": f"--gamma-dp "
            f"{args.gamma_dp:g}", "gamma_VolF": f"--gamma-volf {args.gamma_volf:g}",
            "gamma_gamma": f"--gamma-gamma {args.gamma_gamma:g}",
            "gamma_E": f"--gamma-e {gamma_e:g}"}
    try:
        f.check({k: v.split()[0] for k, v in opts.items()})
    except ValueError as exc:
        raise DesignError(str(exc)) from None
    warnings = [f"warning: {opts[n]} is below 1: it lowers the design value"
                for n in f.below_one()]
    return f, warnings


def as_dict(block: DesignBlock) -> dict:
    """The design block as a JSON-ready record (with its energy scale)."""
    return dataclasses.asdict(block) | {"energy_scale": block.energy_scale}
