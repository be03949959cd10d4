"""Hazard tables from a run's results Dataset (``calib.files.hazard_results``, built by
``_results.hazard_dataset``): exceedance curves with posterior bands, per-station
design values, intensity classes and annual frequencies. Every function also
takes a ``HazardCounts`` (and the profile), turned into the Dataset first.

Definitions (station x, block size D; draws d = 1..M, N blocks each):

* runout exceedance of draw d: p_d(x) = #{finished blocks with final abscissa
  > x} / N. Posterior mean = mean_d p_d; bands = 5/50/95 % quantiles of p_d over draws
  (NumPy's linear interpolation). The bands hold the calibration's parameter
  uncertainty plus each draw's Monte Carlo noise, sqrt(p (1 - p) / N). An
  unfinished block has no final abscissa and is not counted, so the true
  exceedance lies between p and p + p_unfinished.
* reach probability: the fraction of blocks that passed x moving downslope
  (the solvers' station records; ``solvers.stations``), invalid blocks left
  out. Undefined (NaN) at stations at or upslope of the release point, where
  blocks start.
* ``p_left_profile``: the fraction of the blocks of this size (all draws) that
  left the profile still moving (finished, their final abscissa censored at the
  profile's end: they exceed every station short of it); ``p_unfinished``: the
  fraction that did not finish, still moving when the solver's budget ran out
  or invalid (below the ground, non-finite), status BUDGET or INVALID of
  ``solvers.status``. Both are per size, repeated on each station row.
* energy p50/p95/p99, bounce-height p95 and velocity p95 of the blocks that
  pass x: quantiles of the posterior predictive distribution (the passers of
  all draws pooled), read from histograms (``_stats``: error < 1.2 %). Energies
  are kJ per block: the DEM's per-metre energy times the square's side
  (``_units``: a cube of side D, an assumption).
  ``energy_p95_kJ_q05`` / ``_q95``: 5/95 % quantiles over draws of each draw's
  p95 (the calibration's uncertainty on the design energy).
* P(E > 30 kJ | reach), P(E > 300 kJ | reach): pooled over draws.
* ``n_blocks_reached``: passers over all draws, the sample behind the design
  values (a p95 from a handful of blocks is not a design value);
  ``few_blocks``: True where 0 < n_blocks_reached < 20, the percentiles of the
  row rest on too few blocks (``solvers.percentiles.few_blocks``); ``summary_text``
  names those rows in a warning line.
* intensity class: Swiss class (``_intensity``) of the design energy, E p95
  (the percentile UNI 11211-4 designs on, per NOTES.md, checked via a
  secondary source).
* with a release rate R (blocks of this size per year): the annual frequencies
  R P(reach), R P(reach) P(E > 30 | reach), R P(reach) P(E > 300 | reach) and
  the hazard level of the intensity-frequency matrix (``_intensity``).

A run over volume classes (``calib.model.release``): one row per class and
station, ``block_size_m`` the class's representative size; every probability is
conditional on the class (each class simulated with N blocks per draw); R is
then the rate of the whole distribution and a class's frequencies use
``class_rate_per_yr`` = R P(class). Columns ``volume_class``,
``class_volume_min_m3``, ``class_volume_max_m3``, ``class_probability``,
``extrapolated`` (some of the class's blocks lie outside the block sizes the
calibration was fitted on) and ``extrapolated_fraction`` (how many, by the law)
follow ``block_size_m``; ``exceedance.csv`` gains ``volume_class``. A run of fixed
sizes has neither (its tables are those of a run without release conditions);
``summary_text`` names its extrapolated sizes.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from calib.files.hazard_results import json_attr, optional_attr
from calib.hazard._intensity import hazard_level, intensity_class
from calib.hazard._results import as_results
from calib.hazard._stats import BINS, hist_quantile
from solvers.percentiles import few_blocks, few_blocks_warning
from solvers.profile import Profile

__all__ = ["EXCEEDANCE_COLUMNS", "exceedance_table", "hazard_table", "summary_text"]

EXCEEDANCE_COLUMNS = ["model", "block_size_m", "x_m", "p_exceed_mean", "p_exceed_q05",
                      "p_exceed_q50", "p_exceed_q95"]


def _draw_quantiles(p: np.ndarray) -> np.ndarray:
    """(3, T, S) 5/50/95 % quantiles over the draw axis of (D, T, S)."""
    return np.quantile(p, [0.05, 0.5, 0.95], axis=0)


class _Run:
    """The arrays and attributes of a results Dataset the tables read, under the
    names of ``HazardCounts``."""

    def __init__(self, ds):
        self.model = str(ds.attrs["model"])
        self.sizes_m = ds["block_size_m"].values
        self.stations_x_m = ds["x_m"].values
        self.release_x_m = float(ds.attrs["release_x_m"])
        self.n_blocks = int(ds.attrs["n_blocks_per_draw"])
        self.n_draws = int(ds.sizes["draw"])
        self.draws_source = str(ds.attrs["draws_source"])
        self.exceed = ds["n_exceed"].values
        self.reach = ds["n_reach"].values
        self.e30 = ds["n_reach_E_gt_30kJ"].values
        self.e300 = ds["n_reach_E_gt_300kJ"].values
        self.n_unfinished = ds["n_unfinished"].values
        self.n_left_profile = ds["n_left_profile"].values
        self.hist = {q: ds[f"hist_{q}"].values for q in BINS}
        self.energy_p95_per_draw_kJ = ds["energy_p95_binned_kJ"].values
        self.zones = [str(z) for z in ds["zone"].values]
        self.classes = "class_probability" in ds
        if self.classes:
            self.class_label = [str(v) for v in ds["class_label"].values]
            self.class_min = ds["class_volume_min_m3"].values
            self.class_max = ds["class_volume_max_m3"].values
            self.class_p = ds["class_probability"].values
            self.extrapolated = ds["extrapolated_fraction"].values
        self.release = json_attr(ds, "release_json")
        self.shapes = ([str(v) for v in ds["block_shape"].values] if "block_shape" in ds
                       else None)
        fitted_shapes = optional_attr(ds, "fitted_block_shapes")
        self.fitted_shapes = (None if fitted_shapes is None
                              else [f.strip() for f in str(fitted_shapes).split(",")])
        self.design_block = json_attr(ds, "design_block_json")
        self.fitted = (None if optional_attr(ds, "fitted_block_size_min_m") is None else
                       (float(ds.attrs["fitted_block_size_min_m"]),
                        float(ds.attrs["fitted_block_size_max_m"])))
        self.barrier = (None if optional_attr(ds, "barrier_x_m") is None else
                        tuple(float(ds.attrs[k]) for k in ("barrier_x_m", "barrier_height_m",
                                                            "barrier_capacity_kJ")))

    def class_columns(self, t: int) -> dict:
        """The class columns of size index ``t`` (none for a run of sizes)."""
        if not self.classes:
            return {}
        frac = float(self.extrapolated[t])
        return {"volume_class": self.class_label[t],
                "class_volume_min_m3": float(self.class_min[t]),
                "class_volume_max_m3": float(self.class_max[t]),
                "class_probability": float(self.class_p[t]),
                "extrapolated": bool(frac > 0) if np.isfinite(frac) else None,
                "extrapolated_fraction": frac}


def exceedance_table(results, profile: Profile | None = None) -> pd.DataFrame:
    """Long-format exceedance curves, one row per block size and station.

    Args:
        results: the results Dataset (or a ``HazardCounts`` with its ``profile``).
        profile: only for a ``HazardCounts``.
    """
    c = _Run(as_results(results, profile))
    p = c.exceed / c.n_blocks
    mean = p.mean(axis=0)
    q = _draw_quantiles(p)
    t_idx, s_idx = np.meshgrid(np.arange(len(c.sizes_m)), np.arange(len(c.stations_x_m)),
                               indexing="ij")
    df = pd.DataFrame({
        "model": c.model,
        "block_size_m": c.sizes_m[t_idx.ravel()],
        "x_m": c.stations_x_m[s_idx.ravel()],
        "p_exceed_mean": mean.ravel(),
        "p_exceed_q05": q[0].ravel(),
        "p_exceed_q50": q[1].ravel(),
        "p_exceed_q95": q[2].ravel(),
    })
    if c.classes:
        df["volume_class"] = np.asarray(c.class_label, dtype=object)[t_idx.ravel()]
    return df


def hazard_table(results, profile: Profile | None = None,
                 release_rate_per_year: float | None = None) -> pd.DataFrame:
    """One row per block size and station with the quantities of the module
    docstring; column names carry units.

    Args:
        results: the results Dataset (or a ``HazardCounts`` with its ``profile``).
        profile: only for a ``HazardCounts`` (the zone of each station).
        release_rate_per_year: blocks of each size per year (default: the
            Dataset's ``release_rate_per_year``, if any).
    """
    ds = as_results(results, profile)
    if release_rate_per_year is None:
        release_rate_per_year = optional_attr(ds, "release_rate_per_year")
    c = _Run(ds)
    st = _table_stats(c)
    rows = []
    for t, size in enumerate(c.sizes_m):
        unfinished = c.n_unfinished[:, t].sum() / (c.n_draws * c.n_blocks)
        left = c.n_left_profile[:, t].sum() / (c.n_draws * c.n_blocks)
        pq = _draw_quantiles(st["p_ex"][:, t])
        rq = _draw_quantiles(st["reach"][:, t]) if np.any(st["downslope"]) else None
        for s, x in enumerate(c.stations_x_m):
            row = _station_row(c, st, t, s, size, x, pq, rq, left, unfinished)
            if release_rate_per_year is not None:
                _add_frequencies(row, c, st, t, s, release_rate_per_year)
            rows.append(row)
    return pd.DataFrame(rows)


def _table_stats(c: _Run) -> dict:
    """The (D, T, S) and (T, S) arrays the rows read: which stations lie downslope
    of the release, exceedance and reach probabilities per draw, blocks passing,
    P(E > 30 / 300 kJ | reach) pooled over the draws, the pooled energy
    (p50/p95/p99), bounce-height and speed p95 (binned) and the 5-95 % band of
    the per-draw energy p95."""
    downslope = c.stations_x_m > c.release_x_m            # (S,)
    reach = np.where(downslope, c.reach / c.n_blocks, np.nan)  # (D, T, S)
    n_pass = c.reach.sum(axis=0)                           # (T, S)
    with np.errstate(invalid="ignore", divide="ignore"):
        p30 = np.where(n_pass > 0, c.e30.sum(axis=0) / n_pass, np.nan)
        p300 = np.where(n_pass > 0, c.e300.sum(axis=0) / n_pass, np.nan)
    return {"downslope": downslope, "p_ex": c.exceed / c.n_blocks, "reach": reach,
            "n_pass": n_pass, "p30": p30, "p300": p300,
            "e_q": {q: hist_quantile(c.hist["energy_kJ"], q, BINS["energy_kJ"])
                    for q in (0.5, 0.95, 0.99)},
            "h95": hist_quantile(c.hist["bounce_height_m"], 0.95, BINS["bounce_height_m"]),
            "v95": hist_quantile(c.hist["velocity_m_s"], 0.95, BINS["velocity_m_s"]),
            "e95_band": _draw_band(c.energy_p95_per_draw_kJ)}


def _draw_band(e95_draws: np.ndarray) -> np.ndarray:
    """(2, T, S) 5 and 95 % quantiles over the draws of (D, T, S) per-draw values,
    over the draws that had passers (NaN in a draw without; NaN where none had)."""
    with np.errstate(invalid="ignore"):
        e95_band = np.full((2,) + e95_draws.shape[1:], np.nan)
        has = np.isfinite(e95_draws)
        for t in range(e95_draws.shape[1]):
            for s in range(e95_draws.shape[2]):
                col = e95_draws[has[:, t, s], t, s]
                if col.size:
                    e95_band[:, t, s] = np.quantile(col, [0.05, 0.95])
    return e95_band


def _station_row(c: _Run, st: dict, t: int, s: int, size, x, pq: np.ndarray,
                 rq: np.ndarray | None, left: float, unfinished: float) -> dict:
    """The row of size index ``t`` at station ``s`` (columns as in the module
    docstring; NaN for the quantities of blocks passing where the station is not
    downslope of the release)."""
    ok = bool(st["downslope"][s])
    reach, e_q, p30, p300 = st["reach"], st["e_q"], st["p30"], st["p300"]
    n_pass, e95_band = st["n_pass"], st["e95_band"]
    r_mean = float(reach[:, t, s].mean()) if ok else np.nan
    e95 = float(e_q[0.95][t, s]) if ok else np.nan
    return {
        "model": c.model,
        "block_size_m": float(size),
        **c.class_columns(t),
        "x_m": float(x),
        "zone": c.zones[s],
        "n_draws": c.n_draws,
        "n_blocks_per_draw": c.n_blocks,
        "p_exceed_mean": float(st["p_ex"][:, t, s].mean()),
        "p_exceed_q05": float(pq[0, s]),
        "p_exceed_q95": float(pq[2, s]),
        "reach_prob_mean": r_mean,
        "reach_prob_q05": float(rq[0, s]) if ok else np.nan,
        "reach_prob_q95": float(rq[2, s]) if ok else np.nan,
        "n_blocks_reached": int(n_pass[t, s]),
        "few_blocks": bool(ok and n_pass[t, s] > 0 and few_blocks(n_pass[t, s])),
        "energy_p50_kJ": float(e_q[0.5][t, s]) if ok else np.nan,
        "energy_p95_kJ": e95,
        "energy_p99_kJ": float(e_q[0.99][t, s]) if ok else np.nan,
        "energy_p95_kJ_q05": float(e95_band[0, t, s]) if ok else np.nan,
        "energy_p95_kJ_q95": float(e95_band[1, t, s]) if ok else np.nan,
        "bounce_height_p95_m": float(st["h95"][t, s]) if ok else np.nan,
        "velocity_p95_m_s": float(st["v95"][t, s]) if ok else np.nan,
        "p_E_gt_30kJ_given_reach": float(p30[t, s]) if ok else np.nan,
        "p_E_gt_300kJ_given_reach": float(p300[t, s]) if ok else np.nan,
        "intensity_class": intensity_class(e95),
        "p_left_profile": float(left),
        "p_unfinished": float(unfinished),
    }


def _add_frequencies(row: dict, c: _Run, st: dict, t: int, s: int,
                     release_rate_per_year: float) -> None:
    """Add the annual frequencies to ``row``: ``f0 = R P(reach)``, ``f30 = f0
    P(E > 30 kJ | reach)``, ``f300`` likewise (0 where no block reached a
    downslope station, NaN upslope of the release), and the hazard level from
    them; with volume classes R is the whole distribution's rate, so each
    class's is ``R p_class`` (``class_rate_per_yr``)."""
    ok = bool(st["downslope"][s])
    p30, p300 = st["p30"], st["p300"]
    rate = release_rate_per_year
    if c.classes:  # R is the whole distribution's rate
        rate = row["class_rate_per_yr"] = rate * float(c.class_p[t])
    f0 = rate * row["reach_prob_mean"]
    f30 = f0 * float(p30[t, s]) if ok and np.isfinite(p30[t, s]) else (
        0.0 if ok else np.nan)
    f300 = f0 * float(p300[t, s]) if ok and np.isfinite(p300[t, s]) else (
        0.0 if ok else np.nan)
    row["freq_reach_per_yr"] = f0
    row["freq_E_gt_30kJ_per_yr"] = f30
    row["freq_E_gt_300kJ_per_yr"] = f300
    row["hazard_level"] = hazard_level(f0, f30, f300)


def summary_text(results, table: pd.DataFrame, road_x_m: float,
                 release_rate_per_year: float | None = None, label: str = "road",
                 fitted: tuple | None = None) -> str:
    """Short text: probability of reaching the station of interest at ``road_x_m``
    (named ``label``: "road", or what the site file calls it) and the design
    values there (``results``: the results Dataset or a ``HazardCounts``).

    ``fitted``: (sizes, source) of the block sizes the calibration was fitted on
    (default: the range the Dataset records, if any); a size or class beyond
    their range says "extrapolation" on its line."""
    c = _Run(as_results(results))
    what = (f"{len(c.sizes_m)} volume class(es) of {c.release['volume_law']['source']}"
            if c.classes else f"{len(c.sizes_m)} size(s)")
    where = (f"released at x = {c.release_x_m:g} m" if c.release is None
             else "released " + _zone_text(c.release["zone"]))
    lines = [f"hazard ({c.model}): {c.n_draws} draw(s) from the "
             f"{c.draws_source} x {what} x {c.n_blocks} blocks {where}; {label} at x = "
             f"{road_x_m:g} m"]
    rng = (float(np.min(fitted[0])), float(np.max(fitted[0]))) if fitted is not None else (
        c.fitted)
    if c.release is not None and _state_text(c.release["state"]):
        lines.append("  release: " + _state_text(c.release["state"]))
    if c.shapes is not None:
        lines.append("  blocks: CRSP shape classes " + ", ".join(
            f"{f} (D = {d:.3g} m)" for f, d in zip(c.shapes, c.sizes_m, strict=True))
            + "; a cylinder is 2 r long and rolls on its curved face, a disc is r / 2 "
            "thick and rolls on its rim (solvers.crsp.make_block); " + _shape_text(c))
    if c.barrier is not None:
        x, h, e = c.barrier
        lines.append(f"  barrier at x = {x:g} m, height {_limit(h, 'm')}, capacity "
                     f"{_limit(e, 'kJ')} (solvers/crsp/_barrier.py)")
    at = table[np.isclose(table["x_m"], road_x_m)]
    for _, r in at.iterrows():
        name = (f"class {r.volume_class} (D = {r.block_size_m:.3g} m, "
                f"{100 * r.class_probability:.3g} % of the blocks)" if c.classes
                else f"D = {r.block_size_m:g} m")
        line = (f"  {name}: P(reach {label}) = {r.reach_prob_mean:.3g} "
                f"[5-95 %: {r.reach_prob_q05:.3g}-{r.reach_prob_q95:.3g}]")
        if np.isfinite(r.energy_p95_kJ):
            rough = " (fewer than 20: rough)" if r.few_blocks else ""
            line += (f"; from the {r.n_blocks_reached} blocks that reach it{rough}: "
                     f"E p95 = {r.energy_p95_kJ:.4g} kJ "
                     f"[{r.energy_p95_kJ_q05:.4g}-{r.energy_p95_kJ_q95:.4g}], "
                     f"E p99 = {r.energy_p99_kJ:.4g} kJ, bounce height p95 = "
                     f"{r.bounce_height_p95_m:.3g} m, v p95 = {r.velocity_p95_m_s:.3g} m/s, "
                     f"intensity {r.intensity_class}")
        else:
            line += f"; no simulated block reached the {label}"
        if release_rate_per_year is not None:
            line += (f"; {r.freq_reach_per_yr:.3g} blocks/yr reach it, level "
                     f"{r.hazard_level}")
        if r.p_left_profile > 0:
            line += f"; {r.p_left_profile:.2%} of blocks left the profile"
        if r.p_unfinished > 0:
            line += (f"; {r.p_unfinished:.2%} of blocks unfinished (still moving at the "
                     f"solver's budget, or invalid), not counted as runouts")
        line += _extrapolation(r, c.classes, rng)
        lines.append(line)
    if c.classes and rng is None:
        lines.append("  the block sizes the calibration was fitted on are not known (no "
                     "release_groups in it, its data_csv not found): extrapolation not checked")
    if c.design_block is not None:
        b = c.design_block
        lines.append(f"  design block of a {b['return_period_yr']:g}-year return period at "
                     f"{b['rate_per_year']:g} blocks/yr: V = {b['volume_m3']:.3g} m3 (D = "
                     f"{b['block_size_m']:.3g} m), in class {b['volume_class']} ({b['rule']})")
    few = table[table["few_blocks"]]
    warning = few_blocks_warning(
        [(f"D = {r.block_size_m:g} m at x = {r.x_m:g} m", r.n_blocks_reached)
         for r in few.itertuples()], what="the energy, bounce-height and speed percentiles")
    if warning:
        lines.append(warning + " (column few_blocks of hazard_table.csv)")
    return "\n".join(lines)


def _shape_text(c: _Run) -> str:
    """Whether the run's shape classes are among those the calibration's fit
    simulated (``fitted_block_shapes``): another shape extrapolates it."""
    if c.fitted_shapes is None:
        return ("the shapes the calibration was fitted on are not known: a shape it did "
                "not simulate extrapolates it")
    fitted = ", ".join(c.fitted_shapes)
    other = sorted(set(c.shapes) - set(c.fitted_shapes))
    if not other:
        return f"the fit simulated {fitted}: every shape here was fitted"
    return (f"the fit simulated {fitted} only: {', '.join(other)} extrapolates the "
            "calibration")


def _limit(v: float, unit: str) -> str:
    return "unlimited" if not np.isfinite(v) else f"{v:g} {unit}"


def _zone_text(z: dict) -> str:
    x = z["x_m"]
    if z["kind"] == "point":
        return f"at x = {x[0]:g} m"
    if z["kind"] == "uniform":
        return f"uniformly on x = {x[0]:g}-{x[1]:g} m"
    return "at x = " + ", ".join(f"{a:g} m ({w:.0%})" for a, w in zip(x, z["weights"],
                                                                     strict=True))


def _state_text(st: dict) -> str:
    parts = []
    for key, sd, unit, what in (("height_m", "height_sd_m", "m", "height"),
                                ("speed_m_s", "speed_sd_m_s", "m/s", "horizontal speed")):
        if st.get(key) is not None:
            spread = f" (sd {st[sd]:g}, clipped at 0)" if st.get(sd) else ""
            parts.append(f"{what} {st[key]:g} {unit}{spread}")
    return ", ".join(parts)


def _extrapolation(r, classes: bool, rng) -> str:
    """"; ... extrapolation" where the row's size or class reaches outside ``rng``."""
    if rng is None:
        return ""
    lo, hi = rng
    if classes:
        frac = r.extrapolated_fraction
        if not (np.isfinite(frac) and frac > 0):
            return ""
        return (f"; {100 * frac:.3g} % of the class's blocks lie outside the sizes the "
                f"calibration was fitted on ({lo:g}-{hi:g} m): extrapolation")
    if lo * (1 - 1e-9) <= r.block_size_m <= hi * (1 + 1e-9):
        return ""
    return f"; outside the sizes the calibration was fitted on ({lo:g}-{hi:g} m): extrapolation"
