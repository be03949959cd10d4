"""Command line: ``python -m calib.design HAZARD.nc --barrier-x-m X [options]``.

Reads a hazard results file (``python -m calib.hazard`` writes ``hazard.nc``) and
a kit catalogue, and writes into ``--out`` the design sheet of a flexible
barrier at X after UNI 11211-4 as practised in Italy (Peila & Ronco 2009):
``design.md``, ``design.json``, ``design_profile.png``,
``design_distributions.png``, ``design_exceedance.png`` (and with ``--scan-x-m``
``design_scan.csv``, ``design_scan.png``), all at once through temporary files
(``solvers.cli.write_outputs``). Bad input: one line naming the file, row and
column or the option, exit status 2, nothing written.
"""

from __future__ import annotations

import dataclasses
import math
import sys

from calib.design._factors import DEFAULTS, GAMMA_E, free_board_m
from calib.design._kits import CATEGORIES, KitError, load_kits
from calib.design._report import posterior_warning
from calib.files.provenance import command_args
from solvers.cli import (
    CliError,
    DefaultsHelpFormatter,
    OneLineParser,
    parse_stations,
    run_guarded,
)

PROG = "python -m calib.design"


def build_parser() -> OneLineParser:
    p = OneLineParser(
        prog=PROG, formatter_class=DefaultsHelpFormatter,
        description=(
            "Design a flexible rockfall barrier from a hazard run after UNI 11211-4 (Peila & "
            "Ronco 2009): v_d = v_p gamma_Tr gamma_Dp, h_d = h_p gamma_Tr gamma_Dp (h: "
            "height of the block's top), m_d = Vol rho gamma_VolF gamma_gamma, E_sd = 1/2 "
            "m_d v_d^2; checks E_sd <= E_kit/gamma_E, nominal height >= h_d + free board, "
            "residual-height category and elongation against each kit, and picks the "
            "smallest kit that passes. Also: posterior bands, Monte Carlo errors, "
            "probabilities without partial factors, impacts per year, the calibration's "
            "own predictive check. Writes design.md, design.json and figures."),
        epilog="Example: python -m calib.design results/hazard/hazard.nc --barrier-x-m 100 "
               "--kits data/barrier_kits.csv --out results/design/")
    p.add_argument("hazard", help="hazard.nc written by python -m calib.hazard")
    p.add_argument("--barrier-x-m", type=float, help="barrier position, a station of the "
                   "hazard run, m (default with --scan-x-m: the scanned position whose "
                   "smallest passing kit has the least MEL)")
    p.add_argument("--scan-x-m", help="scan positions 'start:stop:step' or 'x1,x2', m: the "
                   "design at each (stations of the hazard run)")
    p.add_argument("--kits", default="data/barrier_kits.csv",
                   help="kit catalogue CSV (the shipped one holds GENERIC energy classes)")
    p.add_argument("--kit", help="check this kit of the catalogue instead of choosing the "
                   "smallest that passes")
    p.add_argument("--protected-distance-m", type=float, help="distance from the barrier to "
                   "the protected object, m (default: the horizontal distance to the hazard "
                   "run's station of interest)")
    p.add_argument("--block-size-m", type=float, help="design block size class D (a block "
                   "size of the hazard run), m (default: its largest)")
    p.add_argument("--block-size-percentile", type=float, help="design block size: this "
                   "percentile of the run's block sizes (one of them)")
    p.add_argument("--design-volume-m3", type=float, help="design block volume from the "
                   "site's block survey, m^3 (default: sphere of diameter D; DEM: D^2 x "
                   "--dem-thickness-m); speeds and heights stay those of size D")
    p.add_argument("--density-kg-m3", type=float, help="rock density, kg/m^3 (default: the "
                   "hazard file's rock_density_kg_m3, else 2350 with a warning)")
    p.add_argument("--dem-thickness-m", type=float, help="DEM runs: block thickness across "
                   "the slope, m, that turns energies per metre of width into energies per "
                   "block (required for a DEM run)")
    p.add_argument("--percentile", type=float, choices=(95.0, 99.0), default=95.0,
                   help="characteristic percentile: 95 (UNI 11211-4) or 99 (ONR 24810)")
    p.add_argument("--energy-level", choices=("MEL", "SEL"), default="MEL",
                   help="kit energy the check uses")
    p.add_argument("--gamma-tr", type=float, default=DEFAULTS.gamma_Tr,
                   help="gamma_Tr, reliability of the trajectory simulation: 1.02 "
                        "back-analysed on site, 1.10 from the literature")
    p.add_argument("--gamma-dp", type=float, default=DEFAULTS.gamma_Dp,
                   help="gamma_Dp, quality of the topographic survey: 1.02 high, 1.10 low")
    p.add_argument("--gamma-volf", type=float, default=DEFAULTS.gamma_VolF,
                   help="gamma_VolF, precision of the block survey: 1.02 high, 1.10 low")
    p.add_argument("--gamma-gamma", type=float, default=DEFAULTS.gamma_gamma,
                   help="gamma_gamma, unit weight of the rock (>= 1.0)")
    p.add_argument("--gamma-e", type=float, help=f"gamma_E (default {GAMMA_E['MEL']:g} "
                   f"against the MEL, {GAMMA_E['SEL']:g} against the SEL: recalled, unverified)")
    p.add_argument("--free-board-m", type=float, help="free board above h_d, m (default and "
                   "least: max(0.5, D/2))")
    p.add_argument("--min-residual-category", choices=CATEGORIES, default="A",
                   help="worst residual-height category accepted")
    p.add_argument("--inspection-interval-yr", type=float, default=1.0,
                   help="years between barrier inspections (P of more than one SEL-level "
                        "impact in between)")
    p.add_argument("--with-barrier", help="hazard.nc of a run with the barrier at the design "
                   "position (python -m calib.hazard --barrier-x-m X --barrier-height-m H "
                   "--barrier-capacity-kJ E, same seed and draws): its exceedance and reach at "
                   "the station of interest, with bands, beside the run without it")
    p.add_argument("--calibration", help="calibration.json of the hazard run (CRSP): the "
                   "impact angle at the barrier from a run of the hazard file's draws with "
                   "the barrier element (default: no impact angle)")
    p.add_argument("--angle-blocks", type=int, default=2000,
                   help="blocks per draw of the impact-angle run (with --calibration; it "
                        "simulates with the hazard run's seed and event budget, "
                        "crsp_max_events in the hazard file; default 2000)")
    p.add_argument("--out", default="results/design/", help="output folder")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    with command_args(argv):
        return run_guarded(PROG, _checked, args)


def _checked(args) -> int:
    """``_main``, the design library's refusals turned into the command's one line."""
    from calib.design._inputs import DesignError

    try:
        return _main(args)
    except DesignError as exc:
        raise CliError(str(exc)) from None


def _main(args) -> int:
    """The design sheet: the inputs read and checked, the barrier's position (given,
    or the best of a scan), the design there, its record written (``_write``)."""
    from calib.design._design import design_at, design_record

    ds, with_barrier, pairing, kits = _read_inputs(args)
    block, options, warnings = _design_options(ds, args, kits, pairing)
    x, rows = _position(ds, args, block, options, with_barrier)
    design = design_at(ds, x, block, options)
    inputs = {"hazard": args.hazard, "kits": args.kits, "with_barrier": args.with_barrier}
    angle = None
    if args.calibration is not None:
        angle, more = _impact_angle(ds, args, x, block.size_m)
        warnings += more
        inputs["calibration"] = args.calibration
    record = design_record(ds, design, options, hazard_path=args.hazard, inputs=inputs,
                           with_barrier=with_barrier, impact_angle=angle)
    record["scan"] = rows
    record["warnings"] = warnings + record["warnings"]
    _write(ds, record, with_barrier, args)
    return 0


def _read_inputs(args):
    """The hazard results, the run with the barrier (or None) with the warnings of
    pairing it with them, and the kit catalogue with ``--kit`` in it (``CliError``
    naming the file or the option)."""
    from calib.design._residual import check_compatible
    from calib.files.hazard_results import HazardResultsError, read_hazard_results

    try:
        ds = read_hazard_results(args.hazard)
        with_barrier = (None if args.with_barrier is None
                        else read_hazard_results(args.with_barrier))
        pairing = ([] if with_barrier is None else
                   check_compatible(ds, with_barrier, f"--with-barrier {args.with_barrier}"))
    except HazardResultsError as exc:
        raise CliError(str(exc)) from None
    try:
        kits = load_kits(args.kits)
    except KitError as exc:
        raise CliError(str(exc)) from None
    if args.kit is not None and args.kit not in {k.name for k in kits}:
        raise CliError(f"--kit {args.kit}: not in {args.kits} (kits: "
                       f"{', '.join(k.name for k in kits)})")
    return ds, with_barrier, pairing, kits


def _design_options(ds, args, kits, pairing: list[str]):
    """The design block and the ``DesignOptions`` of the options, checked, with the
    warnings so far: the partial factors', ``pairing``, a hazard run that had a
    barrier or broke its blocks, the design block's and an extrapolated design
    class."""
    from calib.design._design import DesignOptions
    from calib.design._inputs import design_block, factors_from_args
    from calib.design._residual import barrier_of

    factors, warnings = factors_from_args(args)
    warnings += pairing
    if barrier_of(ds) is not None:
        warnings.append(f"warning: {args.hazard} is a run with a barrier at x = "
                        f"{barrier_of(ds)[0]:g} m: its blocks downslope of it are those that "
                        "passed that barrier")
    if "fragmentation" in ds.attrs:  # calib.hazard._fragments: values per parent block
        warnings.append(f"warning: {args.hazard} broke its blocks ({ds.attrs['fragmentation']})"
                        ": its speeds, heights and energies at the barrier are per parent "
                        "block, the largest among its pieces that pass, and the design mass "
                        "is the unbroken block's, so E_sd bounds the energy of any one piece "
                        "from above; the run without breaking gives the unbroken block's")
    for name in ("protected_distance_m", "inspection_interval_yr"):
        v = getattr(args, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise CliError(f"--{name.replace('_', '-')} {v:g}: expected a positive number")
    if args.barrier_x_m is None and args.scan_x_m is None:
        raise CliError("give --barrier-x-m or --scan-x-m")
    block, more = design_block(ds, args.hazard, size_m=args.block_size_m,
                               size_percentile=args.block_size_percentile,
                               volume_m3=args.design_volume_m3,
                               density_kg_m3=args.density_kg_m3, thickness_m=args.dem_thickness_m)
    warnings += more
    if "extrapolated_fraction" in ds:  # a run over volume classes
        frac = float(ds["extrapolated_fraction"].sel(block_size_m=block.size_m))
        if frac > 0:
            warnings.append(f"warning: {100 * frac:.3g} % of the blocks of the design class "
                            f"(D = {block.size_m:g} m) lie outside the block sizes the "
                            "calibration was fitted on: extrapolation")
    try:
        free_board_m(block.size_m, args.free_board_m)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    options = DesignOptions(
        kits=kits, factors=factors, percentile=args.percentile, energy_level=args.energy_level,
        free_board_m=args.free_board_m, kit=args.kit,
        protected_distance_m=args.protected_distance_m,
        min_residual_category=args.min_residual_category,
        inspection_interval_yr=args.inspection_interval_yr, hazard_name=args.hazard)
    return block, options, warnings


def _position(ds, args, block, options, with_barrier):
    """The barrier's abscissa: ``--barrier-x-m``, else the best scanned position;
    with the scan's rows (None without ``--scan-x-m``). The run with the barrier
    must have it there."""
    from calib.design._design import best_position, scan_rows
    from calib.design._inputs import profile_range, scan_positions
    from calib.design._residual import barrier_of

    scan = (scan_positions(ds, args.hazard, parse_stations(args.scan_x_m, profile_range(ds),
                                                           "--scan-x-m"))
            if args.scan_x_m else [])
    rows = scan_rows(ds, block, scan, options) if scan else None
    x = args.barrier_x_m
    if x is None:
        x = best_position(rows)
        if x is None:
            raise CliError("--scan-x-m: no simulated block passes any scanned position")
    if with_barrier is not None and not math.isclose(barrier_of(with_barrier)[0], x,
                                                     rel_tol=0.0, abs_tol=1e-6):
        raise CliError(f"--with-barrier {args.with_barrier}: its barrier stands at x = "
                       f"{barrier_of(with_barrier)[0]:g} m, the design at x = {x:g} m: rerun "
                       "python -m calib.hazard with --barrier-x-m there, or design there")
    return x, rows


def _impact_angle(ds, args, x_m: float, size_m: float) -> tuple[dict, list[str]]:
    """The impact-angle record at the barrier (``_angles``) from ``--calibration``, and
    the warnings: its inputs differ from the hazard run's, or the run had release
    conditions the angle run does not repeat."""
    from calib.design._angles import impact_angles
    from calib.files.calibration_file import CalibrationError, load_calibration
    from calib.files.hazard_results import crsp_event_budget, json_attr
    from calib.files.provenance import file_sha256
    from calib.hazard import HAZARD_SETTINGS
    from solvers import load_profile

    if not args.angle_blocks > 0:
        raise CliError(f"--angle-blocks {args.angle_blocks}: expected a positive integer")
    if str(ds.attrs["model"]) != "crsp":
        raise CliError(f"--calibration: impact angles need a CRSP run, {args.hazard} is "
                       f"{str(ds.attrs['model']).upper()}")
    try:
        cal = load_calibration(args.calibration, "crsp")
    except CalibrationError as exc:
        raise CliError(str(exc)) from None
    names = tuple(str(n) for n in ds["parameter"].values)
    if tuple(cal.names) != names:
        raise CliError(f"--calibration {args.calibration}: parameters "
                       f"{', '.join(cal.names)}, {args.hazard} drew {', '.join(names)}")
    warnings = []
    recorded = ((json_attr(ds, "provenance_json") or {}).get("inputs") or {}).get("calibration")
    if recorded and recorded.get("sha256") != file_sha256(args.calibration):
        warnings.append(f"warning: --calibration {args.calibration} is not the file the hazard "
                        f"run read ({recorded.get('path')}): the angles come from its draws "
                        "only")
    if "fragmentation" in ds.attrs:
        warnings.append("warning: the hazard run broke its blocks; the impact-angle run "
                        "follows unbroken blocks")
    shape = (str(ds["block_shape"].sel(block_size_m=size_m).item()) if "block_shape" in ds
             else "sphere")
    if "release_json" in ds.attrs:
        warnings.append("warning: the hazard run had release conditions; the impact-angle run "
                        f"releases blocks of D = {size_m:g} m at x = "
                        f"{float(ds.attrs['release_x_m']):g} m, the solver's release state")
    recorded_budget, max_events = crsp_event_budget(ds)
    if not recorded_budget:
        max_events = HAZARD_SETTINGS.max_events
        warnings.append(f"warning: {args.hazard} does not record its CRSP event budget "
                        f"(crsp_max_events); the impact-angle run uses {max_events} events "
                        "per block, the hazard command's default")
    a = impact_angles(cal, ds["parameter_value"].values, names, load_profile(cal.profile_csv),
                      x_m, size_m, args.angle_blocks, int(ds.attrs["seed"]),
                      float(ds.attrs["release_x_m"]),
                      dataclasses.replace(HAZARD_SETTINGS, max_events=max_events), shape)
    return a.record(), warnings


def _write(ds, record: dict, with_barrier, args) -> None:
    import pandas as pd

    from calib.design._figures import (
        distributions_figure,
        exceedance_figure,
        profile_figure,
        scan_figure,
    )
    from calib.design._report import design_json, design_markdown
    from calib.design._residual import residual_exceedance
    from solvers.cli import write_outputs

    table = residual_exceedance(ds, with_barrier)
    figs = {"design_profile.png": profile_figure(ds, record),
            "design_distributions.png": distributions_figure(ds, record),
            "design_exceedance.png": exceedance_figure(table, record)}
    files = {"design.md": design_markdown(record), "design.json": design_json(record)}
    if record["scan"]:
        figs["design_scan.png"] = scan_figure(record["scan"], record["kits"],
                                              record["energy_level"])
        files["design_scan.csv"] = pd.DataFrame(record["scan"]).to_csv(index=False)
    try:
        written = write_outputs(args.out, files, figs)
    except OSError as exc:
        raise CliError(f"cannot write to {args.out}: {exc.strerror or exc}") from None
    finally:
        import matplotlib.pyplot as plt

        for f in figs.values():
            plt.close(f)
    _print(record, written, args.out)


def _print(r: dict, written: list[str], out: str) -> None:
    import os

    check = r.get("calibration_check")
    if check is not None and not check.get("ok"):
        print(f"!!! THE CALIBRATION FAILED ITS OWN PREDICTIVE CHECK: {check.get('message')}",
              file=sys.stderr)
    post = posterior_warning(r.get("posterior_check"))
    if post is not None:
        print(post, file=sys.stderr)
    for w in r["warnings"]:
        print(w, file=sys.stderr)
    d, kit = r["design"], r.get("kit_checked")
    print(f"barrier at x = {r['barrier_x_m']:g} m, D = {r['design_block']['size_m']:g} m, "
          f"p{r['percentile']:g}: v_d = {d['v_d_m_s']:.3g} m/s, E_sd = {d['E_sd_kJ']:.4g} kJ "
          f"(total {d['E_total_kJ']:.4g} kJ), h_d + f = {d['design_height_m']:.3g} m; "
          + (f"{r['kit_chosen_by']}: {kit['kit']}" if kit else "no kit of the catalogue passes"))
    a = r.get("impact_angle")
    if a is not None:
        h = a["below_horizontal_deg"]
        print(f"impact angle below the horizontal p5/p50/p95: {h['p5']:.3g}/{h['p50']:.3g}/"
              f"{h['p95']:.3g} deg ({a['n_crossings']} crossings)")
    print(f"wrote {', '.join(os.path.basename(w) for w in written)} to {out}")


if __name__ == "__main__":
    sys.exit(main())
