"""Design values at one barrier position from a hazard results Dataset
(``calib.files.hazard_results``): the characteristic percentiles of the simulated
passers, the partial factors applied (``_factors``), their posterior bands and
their Monte Carlo errors.

Conventions (ours, stated in every output):

* characteristic value v_p, h_p, E_p: the p-th percentile of the blocks of the
  design size that pass the barrier, all posterior draws pooled (the posterior
  predictive distribution; ``<q>_pct_pooled`` of the file); its band: the 5-95 %
  range over draws of each draw's p-th percentile (``<q>_pct``);
* passing height: the height of the block's TOP above the ground, vertical:
  the simulated clearance of its lowest point plus the block size D (a sphere's
  vertical extent; a rotated DEM square reaches up to sqrt(2) D: not modelled);
* design mass m_d = Vol_d rho gamma_VolF gamma_gamma, Vol_d the design volume
  (default: the sphere pi D^3 / 6 of the CRSP block; for the DEM, D^2 times the
  thickness ``--dem-thickness-m``: its energies are per metre of width);
* E_sd = 1/2 m_d v_d^2 (translational, the standard's); beside it the total
  (with rotation): the simulated p-th percentile of the energy per unit mass
  of the passers times m_d (gamma_Tr gamma_Dp)^2;
* without partial factors (``unfactored``): energies scaled from the simulated
  block to the design block by mass, Vol_d rho / m_sim (the lumped-mass
  kinematics do not depend on mass: RocFall FAQ, NOTES.md).

Monte Carlo error of each percentile: half the width of its distribution-free
95 % interval (``calib.hazard._stats.percentile_interval``), relative to the
value; it shrinks as 1 / sqrt(n), so a run of N blocks per draw reaches the
target relative half-width t with about N (r / t)^2 blocks per draw.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["MC_TARGET", "DesignBlock", "DesignValues", "band", "design_values", "station_index"]

MC_TARGET = 0.02  # relative half-width of a percentile's 95 % interval


@dataclasses.dataclass(frozen=True)
class DesignBlock:
    """The design block.

    Attributes:
        size_m: its size class D (a block size of the hazard run), m.
        volume_m3: Vol_d, m^3.
        volume_source: how Vol_d was set.
        density_kg_m3: rho, kg/m^3.
        density_source: where rho came from.
        simulated_mass_kg: mass of the simulated block of size D, kg.
    """

    size_m: float
    volume_m3: float
    volume_source: str
    density_kg_m3: float
    density_source: str
    simulated_mass_kg: float

    @property
    def energy_scale(self) -> float:
        """Unfactored design mass over the simulated mass, Vol_d rho / m_sim."""
        return self.volume_m3 * self.density_kg_m3 / self.simulated_mass_kg


def band(values: np.ndarray) -> tuple[float, float]:
    """5 and 95 % quantiles over draws of per-draw values (NaN draws left out;
    NaN where fewer than two draws have a value)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return math.nan, math.nan
    lo, hi = np.quantile(v, [0.05, 0.95])
    return float(lo), float(hi)


def station_index(ds, x_m: float) -> int | None:
    """Index of station ``x_m`` in the Dataset, or None where it is not a station."""
    xs = ds["x_m"].values
    hit = np.flatnonzero(np.isclose(xs, x_m, rtol=0.0, atol=1e-6))
    return int(hit[0]) if hit.size else None


@dataclasses.dataclass
class DesignValues:
    """Design values at one station for one design block (module docstring).

    ``characteristic`` and ``design`` map a name to a float; ``per_draw`` a name to
    a (D,) array; ``bands`` a name to its 5-95 % range over draws; ``mc`` a name
    to its Monte Carlo error record.
    """

    x_m: float
    percentile: float
    block: DesignBlock
    free_board_m: float
    n_passers: int
    n_draws: int
    n_blocks_per_draw: int
    reach_prob_mean: float
    reach_prob_band: tuple[float, float]
    characteristic: dict
    design: dict
    per_draw: dict
    bands: dict
    mc: dict


def _mc(value, lo, hi, n_blocks: int) -> dict:
    half = 0.5 * (hi - lo)
    rel = half / value if value > 0 else math.nan
    need = (n_blocks * (rel / MC_TARGET) ** 2 if math.isfinite(rel) else math.nan)
    return {"value": value, "lo95": lo, "hi95": hi, "half_width": half, "rel_half_width": rel,
            "target_rel_half_width": MC_TARGET, "met": bool(math.isfinite(rel) and
                                                          rel <= MC_TARGET),
            "blocks_per_draw_for_target": math.ceil(need) if math.isfinite(need) else None}


def design_values(ds, x_m: float, block: DesignBlock, factors, percentile: float,
                  free_board_m: float) -> DesignValues:
    """Design values of ``block`` at station ``x_m`` (module docstring).

    Args:
        ds: hazard results Dataset.
        x_m: a station of ``ds``.
        block: the design block (its size a block size of ``ds``).
        factors: ``_factors.Factors``.
        percentile: 95 or 99 (a percentile of ``ds``).
        free_board_m: f_min, m.
    """
    s = station_index(ds, x_m)
    sel = {"block_size_m": block.size_m, "x_m": ds["x_m"].values[s], "percentile": percentile}
    d = block.size_m
    n_blocks = int(ds.attrs["n_blocks_per_draw"])

    def pooled(q):
        return tuple(float(ds[f"{q}{end}"].sel(sel)) for end in
                     ("_pct_pooled", "_pct_pooled_lo", "_pct_pooled_hi"))

    def per_draw(q, end=""):
        return ds[f"{q}_pct{end}"].sel(sel).values.astype(float)

    reach = ds["n_reach"].sel(block_size_m=block.size_m).values[:, s]
    v_p, v_lo, v_hi = pooled("velocity_m_s")
    h_p, h_lo, h_hi = (v + d for v in pooled("bounce_height_m"))
    e_p, e_lo, e_hi = (v * block.energy_scale for v in pooled("energy_kJ"))
    speed = factors.gamma_Tr * factors.gamma_Dp
    m_d = block.volume_m3 * block.density_kg_m3 * factors.gamma_VolF * factors.gamma_gamma
    mass_factor = factors.gamma_VolF * factors.gamma_gamma

    def e_sd(v):
        return 0.5 * m_d * (v * speed) ** 2 / 1000.0

    draws = {"v_p_m_s": per_draw("velocity_m_s"), "h_p_m": per_draw("bounce_height_m") + d,
             "E_p_kJ": per_draw("energy_kJ") * block.energy_scale}
    draws.update(v_d_m_s=draws["v_p_m_s"] * speed, h_d_m=draws["h_p_m"] * speed,
                 E_sd_kJ=e_sd(draws["v_p_m_s"]),
                 E_total_kJ=draws["E_p_kJ"] * mass_factor * speed**2)
    draws["design_height_m"] = draws["h_d_m"] + free_board_m
    h_d = h_p * speed
    design = {"v_d_m_s": v_p * speed, "h_d_m": h_d, "m_d_kg": m_d, "E_sd_kJ": e_sd(v_p),
              "E_total_kJ": e_p * mass_factor * speed**2, "free_board_m": free_board_m,
              "design_height_m": h_d + free_board_m}
    rel_draw = {}
    for name, q, shift, scale in (("v_p_m_s", "velocity_m_s", 0.0, 1.0),
                                  ("h_p_m", "bounce_height_m", d, 1.0),
                                  ("E_p_kJ", "energy_kJ", 0.0, block.energy_scale)):
        lo = (per_draw(q, "_lo") + shift) * scale
        hi = (per_draw(q, "_hi") + shift) * scale
        with np.errstate(invalid="ignore", divide="ignore"):
            rel_draw[name] = 0.5 * (hi - lo) / draws[name]
    mc = {"v_p_m_s": _mc(v_p, v_lo, v_hi, n_blocks), "h_p_m": _mc(h_p, h_lo, h_hi, n_blocks),
          "E_p_kJ": _mc(e_p, e_lo, e_hi, n_blocks)}
    for name, r in rel_draw.items():
        finite = r[np.isfinite(r)]
        med = float(np.median(finite)) if finite.size else math.nan
        mc[name]["per_draw_median_rel_half_width"] = med
        mc[name]["per_draw_blocks_for_target"] = (
            math.ceil(n_blocks * (med / MC_TARGET) ** 2) if math.isfinite(med) else None)
    with np.errstate(invalid="ignore"):
        p_reach = reach / n_blocks
    return DesignValues(
        x_m=float(ds["x_m"].values[s]), percentile=float(percentile), block=block,
        free_board_m=free_board_m, n_passers=int(reach.sum()), n_draws=int(ds.sizes["draw"]),
        n_blocks_per_draw=n_blocks, reach_prob_mean=float(p_reach.mean()),
        reach_prob_band=band(p_reach),
        characteristic={"v_p_m_s": v_p, "h_p_m": h_p, "h_clearance_p_m": h_p - d,
                        "E_p_kJ": e_p},
        design=design, per_draw=draws, bands={k: band(v) for k, v in draws.items()}, mc=mc)
