"""Checks of barrier kits against design values, and what the simulated distribution
says about a kit without partial factors: the probability per posterior draw that
a passing block exceeds its energy or its height, and (with a release rate) the
impacts per year and the chance of more than one SEL-level impact between
inspections.

Checks (``_factors``; sources there): energy E_sd <= E_kit / gamma_E with E_kit the
MEL or the SEL; height H_kit >= h_d + f_min; residual-height category no worse
than the one required; elongation: the distance to the protected object at least
max(1.2 e, e + 1 m) (ONR 24810). The smallest kit that passes: the first in order
of MEL, then nominal height.

Impacts (our model): blocks of the design size reach the barrier as a Poisson
process of rate lambda = R P(reach) per year (R: blocks of that size released per
year, the hazard run's ``--release-rate-per-year``), those above the SEL at rate
lambda_SEL = lambda P(E > SEL | reach); in an inspection interval T the number
N of SEL-level impacts is Poisson(lambda_SEL T), P(N > 1) = 1 - exp(-mu) (1 + mu),
mu = lambda_SEL T. Per posterior draw, hence a band.
"""

from __future__ import annotations

import math

import numpy as np

from calib.design._factors import min_protected_distance_m
from calib.design._kits import CATEGORIES, Kit
from calib.design._values import DesignValues, band, station_index
from calib.hazard import Bins, hist_exceedance

__all__ = ["check_kits", "impacts", "kit_probabilities", "smallest_passing"]


def _capacity(kit: Kit, level: str) -> float | None:
    return kit.mel_kJ if level == "MEL" else kit.sel_kJ


def check_kits(kits, dv: DesignValues, *, level: str, gamma_e: float,
               protected_distance_m: float, min_category: str = "A") -> list[dict]:
    """One record per kit: each check, and ``passes`` (all of them).

    Args:
        kits: ``_kits.Kit`` rows.
        dv: the design values.
        level: "MEL" or "SEL", the energy the check uses.
        gamma_e: gamma_E.
        protected_distance_m: distance from the barrier to the protected object, m.
        min_category: the worst residual-height category accepted.
    """
    rows = []
    for kit in kits:
        cap = _capacity(kit, level)
        limit = cap / gamma_e if cap is not None else math.nan
        need = min_protected_distance_m(kit.max_elongation_m)
        row = {"kit": kit.name, "mel_kJ": kit.mel_kJ, "sel_kJ": kit.sel_kJ,
               "nominal_height_m": kit.nominal_height_m,
               "residual_height_category": kit.residual_height_category,
               "max_elongation_m": kit.max_elongation_m,
               "energy_level": level, "energy_limit_kJ": limit,
               "energy_ok": bool(cap is not None and dv.design["E_sd_kJ"] <= limit),
               "energy_total_ok": bool(cap is not None and dv.design["E_total_kJ"] <= limit),
               "height_ok": bool(kit.nominal_height_m >= dv.design["design_height_m"]),
               "category_ok": CATEGORIES.index(kit.residual_height_category)
               <= CATEGORIES.index(min_category),
               "min_protected_distance_m": need,
               "elongation_ok": bool(protected_distance_m >= need)}
        if cap is None:
            row["note"] = f"no {level} declared"
        row["passes"] = all(row[k] for k in ("energy_ok", "height_ok", "category_ok",
                                              "elongation_ok"))
        rows.append(row)
    return rows


def smallest_passing(rows: list[dict]) -> dict | None:
    """The passing kit of least MEL, then least nominal height; None if none passes."""
    ok = [r for r in rows if r["passes"]]
    return min(ok, key=lambda r: (r["mel_kJ"], r["nominal_height_m"])) if ok else None


def _bins(ds, name: str) -> Bins:
    a = ds[name].attrs
    return Bins(float(a["v_min"]), float(a["v_max"]), int(a["per_decade"]))


def kit_probabilities(ds, dv: DesignValues, kit: Kit, level: str) -> dict:
    """Per posterior draw, without partial factors, for the passers of the design
    size at the barrier: P(E > the kit's energy at ``level``), P(E > MEL),
    P(h > nominal height) (h: the block's top above the ground; E scaled to the
    design block by mass, ``_values``). Read from each draw's histograms
    (``draw_hist_*``, 50 bins per decade, log-interpolated in the bin:
    ``calib.hazard._stats.hist_exceedance``).

    Returns:
        name -> {"per_draw": (D,) array, "mean": float, "q05": float, "q95": float}.
    """
    s = station_index(ds, dv.x_m)
    size = dv.block.size_m
    e_counts = ds["draw_hist_energy_kJ"].sel(block_size_m=size).values[:, s]
    h_counts = ds["draw_hist_bounce_height_m"].sel(block_size_m=size).values[:, s]
    scale = dv.block.energy_scale
    out = {}
    cap = _capacity(kit, level)
    for name, energy in ((f"P_E_gt_{level}", cap), ("P_E_gt_MEL", kit.mel_kJ)):
        if energy is not None and name not in out:
            out[name] = hist_exceedance(e_counts, energy / scale,
                                        _bins(ds, "draw_hist_energy_kJ"))
    clearance = kit.nominal_height_m - size
    h_bins = _bins(ds, "draw_hist_bounce_height_m")
    n = h_counts.sum(axis=-1)
    out["P_h_gt_nominal_height"] = (hist_exceedance(h_counts, clearance, h_bins)
                                    if clearance > 0 else np.where(n > 0, 1.0, np.nan))
    return {k: _summary(v) for k, v in out.items()}


def _summary(v: np.ndarray) -> dict:
    v = np.asarray(v, float)
    finite = v[np.isfinite(v)]
    lo, hi = band(v)
    return {"per_draw": v, "mean": float(finite.mean()) if finite.size else math.nan,
            "q05": lo, "q95": hi}


def impacts(ds, dv: DesignValues, kit: Kit, rate_per_year: float,
            inspection_interval_yr: float) -> dict:
    """Impacts per year on the barrier and P(more than one SEL-level impact in an
    inspection interval), per draw (module docstring).

    Returns:
        name -> summary (``_summary``): ``impacts_per_yr``, ``sel_impacts_per_yr``,
        ``mel_impacts_per_yr`` and ``P_more_than_one_sel_impact`` (absent where the
        kit has no SEL).
    """
    s = station_index(ds, dv.x_m)
    reach = ds["n_reach"].sel(block_size_m=dv.block.size_m).values[:, s]
    lam = rate_per_year * reach / float(ds.attrs["n_blocks_per_draw"])
    probs = kit_probabilities(ds, dv, kit, "SEL" if kit.sel_kJ is not None else "MEL")
    out = {"impacts_per_yr": _summary(lam),
           "mel_impacts_per_yr": _summary(lam * np.nan_to_num(probs["P_E_gt_MEL"]["per_draw"]))}
    if kit.sel_kJ is not None:
        lam_sel = lam * np.nan_to_num(probs["P_E_gt_SEL"]["per_draw"])
        mu = lam_sel * inspection_interval_yr
        out["sel_impacts_per_yr"] = _summary(lam_sel)
        out["P_more_than_one_sel_impact"] = _summary(1.0 - np.exp(-mu) * (1.0 + mu))
    return out
