"""One design, as a record: design values at a barrier position (``_values``), the kit
checks and the chosen kit (``_checks``), the probabilities without partial factors,
the impacts per year, the calibration's own predictive check and the residual
hazard, with the provenance of every input. ``scan_rows`` repeats the design
along a scan of positions. ``_report`` and ``_figures`` turn the record into the
sheet."""

from __future__ import annotations

import math

from calib.design._checks import check_kits, impacts, kit_probabilities, smallest_passing
from calib.design._factors import REFERENCES, SOURCES
from calib.design._inputs import DesignError, as_dict, check_barrier
from calib.design._report import LIMITS, SCHEMA
from calib.design._values import design_values
from calib.files.hazard_results import json_attr, optional_attr
from calib.files.provenance import file_sha256, provenance

__all__ = ["design_record", "scan_rows"]


def _distance(ds, x_m: float, requested: float | None) -> tuple[float, str]:
    if requested is not None:
        return float(requested), "--protected-distance-m"
    road = optional_attr(ds, "road_x_m")
    if road is None:
        raise DesignError("--protected-distance-m: needed, the hazard file names no station of "
                       "interest to measure it to")
    label = optional_attr(ds, "road_label") or "station of interest"
    return float(road) - x_m, f"horizontal distance to the {label} at x = {road:g} m"


def _design(ds, x_m: float, block, options: dict):
    """Design values and kit checks at ``x_m``: (values, rows, kit row, chosen by)."""
    args = options["args"]
    check_barrier(ds, args.hazard, x_m)
    dv = design_values(ds, x_m, block, options["factors"], args.percentile,
                       options["free_board"])
    distance, _ = _distance(ds, x_m, args.protected_distance_m)
    rows = check_kits(options["kits"], dv, level=args.energy_level,
                      gamma_e=options["factors"].gamma_E, protected_distance_m=distance,
                      min_category=args.min_residual_category)
    if args.kit is not None:
        return dv, rows, next(r for r in rows if r["kit"] == args.kit), "checked kit (--kit)"
    return dv, rows, smallest_passing(rows), "smallest kit of the catalogue that passes"


def scan_rows(ds, block, positions: list[float], options: dict) -> list[dict]:
    """The design at each scanned position: one row each (NaN where no block passes)."""
    out = []
    for x in positions:
        dv, _, kit, _ = _design(ds, x, block, options)
        out.append({"x_m": x, "reach_prob_mean": dv.reach_prob_mean,
                    "n_passers": dv.n_passers, "v_p_m_s": dv.characteristic["v_p_m_s"],
                    "h_p_m": dv.characteristic["h_p_m"], "v_d_m_s": dv.design["v_d_m_s"],
                    "E_sd_kJ": dv.design["E_sd_kJ"], "E_total_kJ": dv.design["E_total_kJ"],
                    "design_height_m": dv.design["design_height_m"],
                    "mc_rel_half_width_v": dv.mc["v_p_m_s"]["rel_half_width"],
                    "mc_rel_half_width_h": dv.mc["h_p_m"]["rel_half_width"],
                    "kit": kit["kit"] if kit else None,
                    "kit_mel_kJ": kit["mel_kJ"] if kit else None})
    return out


def _residual(ds, with_barrier) -> dict | None:
    """The residual hazard at the station of interest: for each size, P(runout beyond
    it) and P(reach it) with their 5-95 % bands over draws, without and with the
    barrier (``_residual.residual_exceedance``), and the barrier's description."""
    road = optional_attr(ds, "road_x_m")
    if with_barrier is None or road is None:
        return None
    from calib.design._residual import barrier_of, residual_exceedance

    t = residual_exceedance(ds, with_barrier)
    at = t[(t.x_m - road).abs() < 1e-6]
    label = optional_attr(ds, "road_label") or "station of interest"

    def banded(r, name, end=""):
        m, lo, hi = (getattr(r, f"{name}_{k}{end}") for k in ("mean", "q05", "q95"))
        return f"{m:.3g} [{lo:.3g}-{hi:.3g}]"

    x, h, e = barrier_of(with_barrier)
    lim = {"m": h, "kJ": e}
    what = ", ".join(f"{'height' if u == 'm' else 'capacity'} "
                     f"{'unlimited' if not math.isfinite(v) else f'{v:g} {u}'}"
                     for u, v in lim.items())
    parts = [f"D = {r.block_size_m:g} m: P(runout beyond) {banded(r, 'p_exceed')} without, "
             f"{banded(r, 'p_exceed', '_with_barrier')} with the barrier; P(reach) "
             f"{banded(r, 'reach_prob')} without, {banded(r, 'reach_prob', '_with_barrier')} "
             "with it" for r in at.itertuples()]
    return {"road_x_m": road, "barrier": {"x_m": x, "height_m": h, "capacity_kJ": e},
            "rows": at.to_dict(orient="records"),
            "text": f"Barrier at x = {x:g} m ({what}); at the {label}, x = {road:g} m "
                    "(mean [5-95 % over draws]): " + "; ".join(parts) + "."}


def design_record(ds, x_m: float, block, options: dict, with_barrier=None) -> dict:
    """The record of the design at ``x_m`` (what ``design.json`` holds).

    Raises:
        DesignError: bad barrier position, or no simulated block passes it.
    """
    args, factors = options["args"], options["factors"]
    dv, rows, kit_row, chosen_by = _design(ds, x_m, block, options)
    if dv.n_passers == 0:
        raise DesignError(f"--barrier-x-m {x_m:g}: no simulated block of D = {block.size_m:g} m "
                       f"passes it in {args.hazard}: no basis for a design there (choose a "
                       "position upslope, or a larger run)")
    distance, distance_src = _distance(ds, x_m, args.protected_distance_m)
    kit = next((k for k in options["kits"] if kit_row and k.name == kit_row["kit"]), None)
    for k, row in zip(options["kits"], rows, strict=True):  # every kit, no partial factors
        p = kit_probabilities(ds, dv, k, args.energy_level)
        row["P_E_gt_capacity_mean"] = p.get(f"P_E_gt_{args.energy_level}", {}).get("mean")
        row["P_h_gt_nominal_height_mean"] = p["P_h_gt_nominal_height"]["mean"]
    rate = optional_attr(ds, "release_rate_per_year")
    warnings = []
    if dv.n_passers < 20:
        warnings.append(f"warning: the percentiles at x = {x_m:g} m rest on {dv.n_passers} "
                        "blocks (fewer than 20): treat them as rough")
    for name, m in dv.mc.items():
        if not m["met"]:
            warnings.append(f"warning: the Monte Carlo error of {name} is "
                            f"{100 * m['rel_half_width']:.2g} % (target 2 %): about "
                            f"{m['blocks_per_draw_for_target']} blocks per draw would reach it")
    run = {"model": str(ds.attrs["model"]), "n_draws": dv.n_draws,
           "n_blocks_per_draw": dv.n_blocks_per_draw,
           "draws_source": str(ds.attrs["draws_source"]),
           "release_x_m": float(ds.attrs["release_x_m"]),
           "road_x_m": optional_attr(ds, "road_x_m"), "road_label": optional_attr(ds, "road_label"),
           "block_sizes_m": [float(v) for v in ds["block_size_m"].values],
           "energy_basis": str(ds.attrs["energy_basis"]),
           "provenance": json_attr(ds, "provenance_json")}
    inputs = {"hazard": args.hazard, "kits": args.kits, "with_barrier": args.with_barrier}
    return {
        "schema": SCHEMA, "hazard_file": args.hazard, "hazard_sha256": file_sha256(args.hazard),
        "provenance": provenance("python -m calib.design", None, inputs),
        "run": run, "calibration_check": json_attr(ds, "adequacy_json"),
        "barrier_x_m": dv.x_m, "protected_distance_m": distance,
        "protected_distance_source": distance_src, "percentile": dv.percentile,
        "energy_level": args.energy_level, "factors": factors.table(),
        "rules": {k: SOURCES[k] for k in ("percentile", "formulas", "free_board",
                                          "elongation", "kits")},
        "references": REFERENCES,
        "design_block": as_dict(block), "n_passers": dv.n_passers,
        "reach_prob_mean": dv.reach_prob_mean, "reach_prob_band": dv.reach_prob_band,
        "characteristic": dv.characteristic, "design": dv.design,
        "bands": dv.bands, "mc": dv.mc,
        "per_draw": {k: v.tolist() for k, v in dv.per_draw.items()},
        "kits": rows, "kit_checked": kit_row, "kit_chosen_by": chosen_by,
        "unfactored": ({k: {"mean": v["mean"], "q05": v["q05"], "q95": v["q95"],
                            "per_draw": v["per_draw"].tolist()}
                        for k, v in kit_probabilities(ds, dv, kit, args.energy_level).items()}
                       if kit else {}),
        "release_rate_per_year": rate, "inspection_interval_yr": args.inspection_interval_yr,
        "impacts": ({k: {"mean": v["mean"], "q05": v["q05"], "q95": v["q95"]} for k, v in
                     impacts(ds, dv, kit, rate, args.inspection_interval_yr).items()}
                    if kit is not None and rate is not None else None),
        "residual": _residual(ds, with_barrier), "limits": list(LIMITS),
        "warnings": warnings,
    }
