"""One design, typed and as a record: design values at a barrier position (``_values``),
the kit checks and the chosen kit (``_checks``), the probabilities without partial
factors, the impacts per year, the calibration's own predictive check and the
residual hazard, with the provenance of every input.

``design_at`` gives a ``Design`` (what a notebook or a script holds);
``design_record`` turns it into the record ``design.json`` holds; ``scan_rows``
repeats the design along a scan of positions. ``_report`` and ``_figures`` turn
the record into the sheet."""

from __future__ import annotations

import dataclasses
import math

from calib.design._checks import check_kits, impacts, kit_probabilities, smallest_passing
from calib.design._factors import DEFAULTS, REFERENCES, SOURCES, Factors, free_board_m
from calib.design._inputs import DesignError, as_dict, check_barrier
from calib.design._kits import Kit
from calib.design._report import LIMITS, SCHEMA
from calib.design._values import DesignBlock, DesignValues, design_values
from calib.files.hazard_results import json_attr, optional_attr
from calib.files.provenance import file_sha256, provenance

__all__ = ["Design", "DesignOptions", "best_position", "design_at", "design_record",
           "scan_rows"]


@dataclasses.dataclass(frozen=True)
class DesignOptions:
    """The choices of one design (the command's options; module docstring of
    ``_factors`` for the rules and their sources).

    Attributes:
        kits: the kit catalogue (``load_kits``).
        factors: the partial factors.
        percentile: characteristic percentile, 95 (UNI 11211-4) or 99 (ONR 24810).
        energy_level: "MEL" or "SEL", the kit energy the check uses.
        free_board_m: f_min, m (None: the least, max(0.5 m, D/2)).
        kit: check this kit (a name of ``kits``) instead of choosing the smallest
            that passes; None: choose.
        protected_distance_m: barrier to protected object, m (None: the horizontal
            distance to the hazard run's station of interest).
        min_residual_category: worst residual-height category accepted.
        inspection_interval_yr: years between inspections (P of more than one
            SEL-level impact in between).
        hazard_name: how messages name the hazard file.
    """

    kits: tuple[Kit, ...]
    factors: Factors = DEFAULTS
    percentile: float = 95.0
    energy_level: str = "MEL"
    free_board_m: float | None = None
    kit: str | None = None
    protected_distance_m: float | None = None
    min_residual_category: str = "A"
    inspection_interval_yr: float = 1.0
    hazard_name: str = "the hazard results"

    def board_m(self, block_size_m: float) -> float:
        """The free board for blocks of size D (``_factors.free_board_m``)."""
        return free_board_m(block_size_m, self.free_board_m)


@dataclasses.dataclass
class Design:
    """The design at one barrier position.

    Attributes:
        values: the design values (``_values.DesignValues``).
        kits: one check record per kit (``_checks.check_kits``), each with
            ``P_E_gt_capacity_mean`` and ``P_h_gt_nominal_height_mean`` (mean over
            draws, no partial factors; None where the kit has no such energy).
        kit: the record of the checked or chosen kit, None where none passes.
        chosen_kit: that kit's catalogue row (``Kit``), None where none passes.
        chosen_by: how ``kit`` was chosen.
        unfactored: for ``kit``, name -> {"per_draw", "mean", "q05", "q95"}:
            P(E > capacity), P(E > MEL), P(h > nominal height) given reach.
        impacts: for ``kit`` with the run's release rate: impacts per year and
            P(more than one SEL-level impact between inspections) (``_checks.impacts``);
            None without a rate or a kit.
        release_rate_per_year: the hazard run's release rate, or None.
        protected_distance_m: barrier to protected object, m.
        protected_distance_source: where that distance came from.
    """

    values: DesignValues
    kits: list[dict]
    kit: dict | None
    chosen_kit: Kit | None
    chosen_by: str
    unfactored: dict
    impacts: dict | None
    release_rate_per_year: float | None
    protected_distance_m: float
    protected_distance_source: str

    @property
    def warnings(self) -> list[str]:
        """Few passers, and each Monte Carlo error above its 2 % target."""
        dv, out = self.values, []
        if dv.n_passers < 20:
            out.append(f"warning: the percentiles at x = {dv.x_m:g} m rest on {dv.n_passers} "
                       "blocks (fewer than 20): treat them as rough")
        for name, m in dv.mc.items():
            if not m["met"]:
                out.append(f"warning: the Monte Carlo error of {name} is "
                           f"{100 * m['rel_half_width']:.2g} % (target 2 %): about "
                           f"{m['blocks_per_draw_for_target']} blocks per draw would reach it")
        return out


def _distance(ds, x_m: float, requested: float | None) -> tuple[float, str]:
    if requested is not None:
        return float(requested), "--protected-distance-m"
    road = optional_attr(ds, "road_x_m")
    if road is None:
        raise DesignError("--protected-distance-m: needed, the hazard file names no station of "
                          "interest to measure it to")
    label = optional_attr(ds, "road_label") or "station of interest"
    return float(road) - x_m, f"horizontal distance to the {label} at x = {road:g} m"


def _checked(ds, x_m: float, block: DesignBlock, o: DesignOptions):
    """Design values and kit checks at ``x_m``: (values, rows, kit row, chosen by,
    distance, its source)."""
    check_barrier(ds, o.hazard_name, x_m)
    dv = design_values(ds, x_m, block, o.factors, o.percentile, o.board_m(block.size_m))
    distance, source = _distance(ds, x_m, o.protected_distance_m)
    rows = check_kits(o.kits, dv, level=o.energy_level, gamma_e=o.factors.gamma_E,
                      protected_distance_m=distance, min_category=o.min_residual_category)
    if o.kit is not None:
        row = next((r for r in rows if r["kit"] == o.kit), None)
        if row is None:
            raise DesignError(f"--kit {o.kit}: not in the catalogue (kits: "
                              f"{', '.join(k.name for k in o.kits)})")
        return dv, rows, row, "checked kit (--kit)", distance, source
    return (dv, rows, smallest_passing(rows), "smallest kit of the catalogue that passes",
            distance, source)


def scan_rows(ds, block: DesignBlock, positions: list[float], options: DesignOptions
              ) -> list[dict]:
    """The design at each scanned position: one row each (NaN where no block passes)."""
    out = []
    for x in positions:
        dv, _, kit, _, _, _ = _checked(ds, x, block, options)
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


def best_position(rows: list[dict]) -> float | None:
    """The scanned position (``scan_rows``) whose smallest passing kit has the least MEL,
    then the least E_sd; where no kit passes anywhere, the one of least E_sd; None
    where no simulated block passes any position."""
    ok = [r for r in rows if r["kit"] is not None]
    pool = ok or [r for r in rows if math.isfinite(r["E_sd_kJ"])]
    if not pool:
        return None
    return min(pool, key=lambda r: (r.get("kit_mel_kJ") or 0.0, r["E_sd_kJ"]))["x_m"]


def design_at(ds, x_m: float, block: DesignBlock, options: DesignOptions) -> Design:
    """The design of a barrier at ``x_m`` for ``block`` from a hazard results Dataset
    (``calib.files.hazard_results``; ``calib.hazard.hazard_dataset`` of a run).

    Raises:
        DesignError: bad barrier position, unknown kit, no distance to the protected
            object, or no simulated block passes the position.
    """
    o = options
    dv, rows, kit_row, chosen_by, distance, source = _checked(ds, x_m, block, o)
    if dv.n_passers == 0:
        raise DesignError(f"--barrier-x-m {x_m:g}: no simulated block of D = {block.size_m:g} m "
                          f"passes it in {o.hazard_name}: no basis for a design there (choose "
                          "a position upslope, or a larger run)")
    for k, row in zip(o.kits, rows, strict=True):  # every kit, no partial factors
        p = kit_probabilities(ds, dv, k, o.energy_level)
        row["P_E_gt_capacity_mean"] = p.get(f"P_E_gt_{o.energy_level}", {}).get("mean")
        row["P_h_gt_nominal_height_mean"] = p["P_h_gt_nominal_height"]["mean"]
    kit = next((k for k in o.kits if kit_row and k.name == kit_row["kit"]), None)
    rate = optional_attr(ds, "release_rate_per_year")
    return Design(
        values=dv, kits=rows, kit=kit_row, chosen_kit=kit, chosen_by=chosen_by,
        unfactored=kit_probabilities(ds, dv, kit, o.energy_level) if kit else {},
        impacts=(impacts(ds, dv, kit, rate, o.inspection_interval_yr)
                 if kit is not None and rate is not None else None),
        release_rate_per_year=rate, protected_distance_m=distance,
        protected_distance_source=source)


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


def _summaries(d: dict | None) -> dict | None:
    if d is None:
        return None
    return {k: {"mean": v["mean"], "q05": v["q05"], "q95": v["q95"]} for k, v in d.items()}


def design_record(ds, design: Design, options: DesignOptions, *, hazard_path: str,
                  inputs: dict, with_barrier=None, impact_angle: dict | None = None) -> dict:
    """The record of ``design`` (what ``design.json`` holds).

    Args:
        ds: the hazard results the design read.
        design: ``design_at``'s result.
        options: its options.
        hazard_path: the hazard file (hashed into the record).
        inputs: name -> path of every input file (provenance).
        with_barrier: the results of the run with the barrier, or None.
        impact_angle: ``ImpactAngles.record()`` at the barrier, or None.
    """
    dv, o = design.values, options
    run = {"model": str(ds.attrs["model"]), "n_draws": dv.n_draws,
           "n_blocks_per_draw": dv.n_blocks_per_draw,
           "draws_source": str(ds.attrs["draws_source"]),
           "release_x_m": float(ds.attrs["release_x_m"]),
           "road_x_m": optional_attr(ds, "road_x_m"), "road_label": optional_attr(ds, "road_label"),
           "block_sizes_m": [float(v) for v in ds["block_size_m"].values],
           "energy_basis": str(ds.attrs["energy_basis"]),
           "provenance": json_attr(ds, "provenance_json")}
    return {
        "schema": SCHEMA, "hazard_file": hazard_path, "hazard_sha256": file_sha256(hazard_path),
        "provenance": provenance("python -m calib.design", None, inputs),
        "run": run, "calibration_check": json_attr(ds, "adequacy_json"),
        "posterior_check": json_attr(ds, "posterior_check_json"),
        "barrier_x_m": dv.x_m, "protected_distance_m": design.protected_distance_m,
        "protected_distance_source": design.protected_distance_source,
        "percentile": dv.percentile, "energy_level": o.energy_level,
        "factors": o.factors.table(),
        "rules": {k: SOURCES[k] for k in ("percentile", "formulas", "free_board",
                                          "elongation", "kits")},
        "references": REFERENCES,
        "design_block": as_dict(dv.block), "n_passers": dv.n_passers,
        "reach_prob_mean": dv.reach_prob_mean, "reach_prob_band": dv.reach_prob_band,
        "characteristic": dv.characteristic, "design": dv.design,
        "bands": dv.bands, "mc": dv.mc,
        "per_draw": {k: v.tolist() for k, v in dv.per_draw.items()},
        "kits": design.kits, "kit_checked": design.kit, "kit_chosen_by": design.chosen_by,
        "unfactored": {k: {"mean": v["mean"], "q05": v["q05"], "q95": v["q95"],
                           "per_draw": v["per_draw"].tolist()}
                       for k, v in design.unfactored.items()},
        "release_rate_per_year": design.release_rate_per_year,
        "inspection_interval_yr": o.inspection_interval_yr,
        "impacts": _summaries(design.impacts),
        "impact_angle": impact_angle,
        "residual": _residual(ds, with_barrier), "limits": list(LIMITS),
        "warnings": design.warnings,
    }
