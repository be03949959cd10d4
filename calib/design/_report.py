"""The design sheet's text: ``design.json`` (every number) and ``design.md`` (a short
report a colleague can read without the toolkit). No computation here: the record
comes from ``calib.design.__main__``."""

from __future__ import annotations

import json
import math

from calib.design._factors import REFERENCES, SOURCES
from solvers.jsonable import json_ready

__all__ = ["LIMITS", "SCHEMA", "design_json", "design_markdown"]

SCHEMA = "rockfall-design/1"

LIMITS = (
    "2D: the run follows one slope profile. The barrier's length, the lateral spread of "
    "the trajectories and blocks passing round the barrier's ends are not modelled: choose "
    "the length from the site (the width of the release area and of the runout fan), not "
    "from this sheet.",
    "The kits are generic energy classes (data/barrier_kits.csv), not products: replace "
    "them by the certified values (European Technical Assessment) of the kit chosen.",
    "Blocks are CRSP shape classes (spheres unless the hazard run gave --block-shape: "
    "cylinders, discs, each of the volume of the sphere of diameter D) or squares (DEM) "
    "of the run's size classes; the design block's volume and density enter through its "
    "mass only.",
    "Passing height is the height of the block's top above the ground (clearance + D), "
    "vertical; a design on the trajectory of the block's centre would be lower by D/2.",
    "Impacts and probabilities count the blocks as they pass the barrier's station in a "
    "run without the barrier; the residual hazard below it needs a run with the barrier "
    "element (--with-barrier).",
)


def design_json(record: dict) -> str:
    """``design.json``: the record, JSON-ready (NaN -> null)."""
    return json.dumps(json_ready(record), indent=1, allow_nan=False) + "\n"


def _g(v, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}g}"


def _band(b, digits: int = 3) -> str:
    return (f"{_g(b[0], digits)}-{_g(b[1], digits)}" if b and all(math.isfinite(x) for x in b)
            else "n/a")


def _check(ok: bool) -> str:
    return "ok" if ok else "FAILS"


def _coverage(check: dict) -> str:
    levels = ((check.get("coverage") or {}).get("levels") or {})
    parts = [f"{float(p):.0%} band: {c['n_covered']}/{c['n_rows']} rows"
             for p, c in levels.items() if isinstance(c, dict) and "n_covered" in c]
    return "; ".join(parts) or "no coverage recorded"


def _calibration_lines(check: dict | None) -> list[str]:
    if check is None:
        return ["The hazard file records no predictive check of its calibration: the "
                "calibration's adequacy is unknown.", ""]
    if check.get("ok"):
        return [f"No flag raised (calib.inference.adequacy): calibration rows inside their "
                f"predictive bands: {_coverage(check)} ({check.get('predictive', '')}); no "
                "parameter piles up on a prior bound.", ""]
    return ["**!!! THE CALIBRATION FAILED ITS OWN PREDICTIVE CHECK. The design values "
            "below rest on a model that may not reproduce this slope.**", "",
            f"> {check.get('message') or '; '.join(check.get('problems') or [])}", "",
            f"Coverage of the calibration rows: {_coverage(check)}.", ""]


def posterior_warning(check: dict | None) -> str | None:
    """The one loud line for a calibration whose posterior failed its diagnostics
    (``posterior_check``: ``ok`` and ``problems``), or None where it passed or
    none is recorded: printed by ``python -m calib.design`` and the protection
    notebook beside a design."""
    if check is None or check.get("ok"):
        return None
    return ("!!! THE CALIBRATION'S POSTERIOR FAILED ITS DIAGNOSTICS: "
            + "; ".join(check.get("problems") or []))


def _posterior_lines(check: dict | None) -> list[str]:
    """The verdict of the calibration's posterior diagnostics (R-hat, ESS, chains,
    mass at the bounds, the GP's realisation check), loud where it failed: the
    bands below are then not to be trusted."""
    if check is None:
        return []
    if check.get("ok"):
        return ["The calibration's posterior passed its diagnostics (R-hat, ESS, chains, "
                "mass at the prior bounds, the log-likelihood GP's realisations).", ""]
    return ["**!!! THE CALIBRATION'S POSTERIOR FAILED ITS DIAGNOSTICS. Its draws, and the "
            "5-95 % bands and probabilities below, may not represent the parameters' "
            "uncertainty.**", "", *(f"> {p}" for p in check.get("problems") or []), ""]


def _values_table(r: dict) -> list[str]:
    c, d, b, mc = r["characteristic"], r["design"], r["bands"], r["mc"]
    p = f"p{r['percentile']:g}"
    f = {x["factor"]: x["value"] for x in r["factors"]}
    speed = f["gamma_Tr"] * f["gamma_Dp"]
    total = speed**2 * f["gamma_VolF"] * f["gamma_gamma"]
    rows = [
        ("speed v (m/s)", c["v_p_m_s"], f"x {speed:.4g}", d["v_d_m_s"], b["v_d_m_s"],
         mc["v_p_m_s"]),
        ("passing height h, block top (m)", c["h_p_m"], f"x {speed:.4g}", d["h_d_m"],
         b["h_d_m"], mc["h_p_m"]),
        ("energy E, translational (kJ)", None, "1/2 m_d v_d^2", d["E_sd_kJ"], b["E_sd_kJ"],
         None),
        ("energy E, total with rotation (kJ)", c["E_p_kJ"], f"x {total:.4g}",
         d["E_total_kJ"], b["E_total_kJ"], mc["E_p_kJ"]),
        ("design height h_d + f_min (m)", None, f"+ {d['free_board_m']:g}",
         d["design_height_m"], b["design_height_m"], None),
    ]
    out = [f"| quantity | {p} simulated | factor | design value | design value, 5-95 % over "
           f"draws | Monte Carlo error of the {p}, all draws pooled | the same, one draw "
           "(median) |", "|---|---|---|---|---|---|---|"]
    for name, ch, fac, des, band, m in rows:
        err = draw = ""
        if name.startswith("energy E, translational"):  # E_sd ~ v_p^2: twice v_p's
            v = mc["v_p_m_s"]
            err = f"{_g(200 * v['rel_half_width'], 2)} % (twice the speed's: E_sd ~ v_p^2)"
            draw = f"{_g(200 * v['per_draw_median_rel_half_width'], 2)} %"
        if m is not None:
            err = f"{_g(100 * m['rel_half_width'], 2)} % " + (
                "(target 2 % met)" if m["met"] else
                f"(2 % needs about {m['blocks_per_draw_for_target'] or 'n/a'} blocks per draw)")
            r_d = m["per_draw_median_rel_half_width"]
            draw = f"{_g(100 * r_d, 2)} % " + (
                "(2 % met)" if math.isfinite(r_d) and r_d <= m["target_rel_half_width"] else
                f"(2 % needs about {m['per_draw_blocks_for_target'] or 'n/a'} blocks per draw)")
        out.append(f"| {name} | {_g(ch, 4)} | {fac} | **{_g(des, 4)}** | {_band(band, 4)} | "
                   f"{err} | {draw} |")
    out += ["", "Monte Carlo error: half the width of the distribution-free 95 % interval of the "
            "percentile (order statistics), relative to the value; the target is 2 %, and it "
            "shrinks as one over the square root of the blocks."]
    return out


def _kits_table(rows: list[dict]) -> list[str]:
    out = ["| kit | MEL (kJ) | SEL (kJ) | energy limit E_kit/gamma_E (kJ) | energy | nominal "
           "height (m) | height | category | max elongation (m) | needs distance (m) | "
           "elongation | passes | P(E > E_kit), no factors | P(h > height), no factors |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for k in rows:
        out.append(f"| {k['kit']} | {_g(k['mel_kJ'], 5)} | {_g(k['sel_kJ'], 5)} | "
                   f"{_g(k['energy_limit_kJ'], 4)} | {_check(k['energy_ok'])} | "
                   f"{_g(k['nominal_height_m'])} | {_check(k['height_ok'])} | "
                   f"{k['residual_height_category']} {_check(k['category_ok'])} | "
                   f"{_g(k['max_elongation_m'])} | {_g(k['min_protected_distance_m'])} | "
                   f"{_check(k['elongation_ok'])} | {'**yes**' if k['passes'] else 'no'} | "
                   f"{_g(k.get('P_E_gt_capacity_mean'))} | "
                   f"{_g(k.get('P_h_gt_nominal_height_mean'))} |")
    return out


_LABELS = {"P_E_gt_MEL": "P(E > MEL | reach)", "P_E_gt_SEL": "P(E > SEL | reach)",
           "P_h_gt_nominal_height": "P(h > nominal height | reach)",
           "impacts_per_yr": "impacts on the barrier per year",
           "mel_impacts_per_yr": "impacts above the MEL per year",
           "sel_impacts_per_yr": "impacts above the SEL per year",
           "P_more_than_one_sel_impact": "P(more than one impact above the SEL between "
                                         "inspections)"}


def _prob_lines(r: dict) -> list[str]:
    kit = r.get("kit_checked")
    if kit is None:
        return ["No kit of the catalogue passes: no probabilities for a chosen kit.", ""]
    out = [f"For kit **{kit['kit']}**, per posterior draw, of the blocks of D = "
           f"{r['design_block']['size_m']:g} m that reach the barrier (simulated values, no "
           "partial factors; energies scaled to the design block by mass):", "",
           "| probability | mean over draws | 5-95 % over draws |", "|---|---|---|"]
    for name, s in r["unfactored"].items():
        out.append(f"| {_LABELS.get(name, name)} | {_g(s['mean'])} | {_g(s['q05'])}-"
                   f"{_g(s['q95'])} |")
    out.append("")
    imp = r.get("impacts")
    if imp is None:
        out += ["No release rate in the hazard run (--release-rate-per-year): no impacts per "
                "year.", ""]
        return out
    out += [f"With the hazard run's release rate R = {r['release_rate_per_year']:g} blocks of "
            f"each size per year and an inspection every {r['inspection_interval_yr']:g} "
            "year(s) (Poisson arrivals, per draw):", "",
            "| quantity | mean over draws | 5-95 % over draws |", "|---|---|---|"]
    for name, s in imp.items():
        out.append(f"| {_LABELS.get(name, name)} | {_g(s['mean'])} | {_g(s['q05'])}-"
                   f"{_g(s['q95'])} |")
    return out + [""]


def _angle_lines(r: dict) -> list[str]:
    a = r.get("impact_angle")
    if a is None:
        return ["Not computed: the hazard results hold no velocity directions; give "
                "--calibration (the hazard run's calibration.json) to simulate them.", ""]
    h, g = a["below_horizontal_deg"], a["to_ground_deg"]
    return [f"Of {a['n_crossings']} blocks of D = {a['size_m']:g} m crossing x = "
            f"{a['x_m']:g} m ({a['n_draws']} draw(s) x {a['n_blocks_per_draw']} blocks, the "
            "hazard run's draws and seed): inclination of the velocity below the horizontal "
            f"p5 / p50 / p95 = {_g(h['p5'])} / {_g(h['p50'])} / {_g(h['p95'])} deg (median, "
            f"5-95 % over draws: {_band(a['median_band_deg'])} deg); to the ground, whose "
            f"slope there is {_g(a['ground_slope_deg'])} deg: {_g(g['p5'])} / {_g(g['p50'])} / "
            f"{_g(g['p95'])} deg (0: along the ground). Angles in the profile's vertical plane "
            "only (2D: the angle across the slope is not modelled). Kits are tested with "
            "impacts normal to the net (EAD 340059-00-0106).", ""]


def _scan_lines(scan: list | None) -> list[str]:
    """The scan's table (one row per position), or nothing without a scan."""
    if not scan:
        return []
    return (["## Scan of barrier positions", "",
             "| x (m) | P(reach) | E_sd (kJ) | design height (m) | smallest passing kit |",
             "|---|---|---|---|---|"]
            + [f"| {s['x_m']:g} | {_g(s['reach_prob_mean'])} | {_g(s['E_sd_kJ'], 4)} | "
               f"{_g(s['design_height_m'], 3)} | {s['kit'] or 'none'} |" for s in scan] + [""])


def design_markdown(r: dict) -> str:
    """``design.md`` from the record of ``calib.design.__main__``."""
    b, d = r["design_block"], r["design"]
    kit = r.get("kit_checked")
    lines = [f"# Rockfall barrier at x = {r['barrier_x_m']:g} m: design after UNI 11211-4",
             "",
             "Generic kits: every kit below is a generic energy class, NOT a product. "
             "Replace it by the certified values of the kit chosen before building.", "",
             "## The calibration's own predictive check", ""]
    lines += _calibration_lines(r.get("calibration_check"))
    lines += _posterior_lines(r.get("posterior_check"))
    run = r["run"]
    lines += ["## The hazard run", "",
              f"{run['model'].upper()}, {run['n_draws']} draw(s) ({run['draws_source']}) x "
              f"{run['n_blocks_per_draw']} blocks per block size, released at x = "
              f"{run['release_x_m']:g} m; {run.get('road_label') or 'station of interest'} at "
              f"x = {_g(run.get('road_x_m'), 5)} m. File {r['hazard_file']} (SHA-256 "
              f"{r['hazard_sha256'][:12]}...). At the barrier "
              f"{r['n_passers']} simulated blocks of D = {b['size_m']:g} m passed (P(reach) = "
              f"{_g(r['reach_prob_mean'])}, 5-95 % over draws {_band(r['reach_prob_band'])}).",
              ""]
    if r["n_passers"] < 20:
        lines += [f"**warning: the percentiles rest on {r['n_passers']} blocks (fewer than "
                  "20): treat them as rough.**", ""]
    lines += ["## Design block and partial factors", "",
              f"Size class D = {b['size_m']:g} m; volume {_g(b['volume_m3'], 4)} m^3 "
              f"({b['volume_source']}); density {b['density_kg_m3']:g} kg/m^3 "
              f"({b['density_source']}); design mass m_d = Vol rho gamma_VolF gamma_gamma "
              f"= {_g(d['m_d_kg'], 4)} kg. Characteristic values: the "
              f"{r['percentile']:g}th percentile of the passers of all draws pooled "
              f"({SOURCES['percentile']}). Formulas: {SOURCES['formulas']}.", "",
              "| factor | value | source |", "|---|---|---|"]
    lines += [f"| {f['factor']} | {f['value']:g} | {f['source']} |" for f in r["factors"]]
    lines += ["", f"Energy checked against the kit's {r['energy_level']}. Free board f_min = "
              f"{d['free_board_m']:g} m ({SOURCES['free_board']}). Protected object at "
              f"{r['protected_distance_m']:g} m from the barrier "
              f"({r['protected_distance_source']}); {SOURCES['elongation']}.", "",
              "## Design values", ""]
    lines += _values_table(r)
    lines += ["", "The design checks use the translational E_sd (UNI 11211-4, Peila & Ronco "
              "2009); the total with rotation is shown beside it.", "", "## Kits", ""]
    lines += _kits_table(r["kits"])
    lines += ["", "The last two columns: mean over posterior draws of the probability that a "
              "block reaching the barrier exceeds the kit's energy (at the level checked) or "
              "its nominal height, from the simulated distribution without partial factors.",
              ""]
    if kit is None:
        lines += ["**No kit of the catalogue passes every check at this position.**", ""]
    else:
        lines += [f"**{r['kit_chosen_by']}: {kit['kit']}** (MEL {kit['mel_kJ']:g} kJ, "
                  f"nominal height {kit['nominal_height_m']:g} m, max elongation "
                  f"{kit['max_elongation_m']:g} m).", ""]
    lines += ["## Impact angle", ""] + _angle_lines(r)
    lines += ["## Without partial factors", ""]
    lines += _prob_lines(r)
    lines += ["## Residual hazard behind the barrier", ""]
    res = r.get("residual")
    lines += ([res["text"], ""] if res else
              ["Not available: no hazard run with the barrier element was given "
               "(--with-barrier); the exceedance at the road is that of the run without it.",
               ""])
    lines += _scan_lines(r.get("scan"))
    lines += ["## Limits", ""] + [f"* {x}" for x in LIMITS]
    if r.get("warnings"):
        lines += ["", "## Warnings", ""] + [f"* {w}" for w in r["warnings"]]
    lines += ["", "## Sources", ""] + [f"* [{k}] {v}" for k, v in REFERENCES.items()]
    lines += ["", "## Figures", "", "* design_profile.png: the profile with the release, the "
              "barrier and the road; P(reach) along the slope.",
              "* design_distributions.png: energy and passing height at the barrier, design "
              "values and kit lines.",
              "* design_exceedance.png: runout exceedance along the slope, the barrier and the "
              "road marked."]
    if r.get("scan"):
        lines.append("* design_scan.png, design_scan.csv: design values along the scan.")
    return "\n".join(lines) + "\n"
