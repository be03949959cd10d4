#!/usr/bin/env python3
"""How far off is a terrain raster's ground? Tracked rest points against the raster.

A tracked block at rest lies ON the ground: its tracked centre less half its
size is the ground's height there. Comparing that with the raster at the same
plan point measures the raster's vertical error where blocks stopped:

    e = (z_stop - d / 2) - raster(east_stop, north_stop),   m

(positive: the tracked ground lies above the raster). The same for the
release points gives the tracked release height above the raster,

    h = (z_release - d / 2) - raster(east_release, north_release),   m,

what ``python -m calib.field`` records as ``release_height_m`` on a profile cut
from the raster (there the profile's ground at the projected point, here the
raster at the point itself). A true release height is >= 0 (a block cannot be
released inside the ground), so a negative h is the raster's error, not the
rock's. d is the volume-equivalent sphere diameter from the mass at the given
density (``calib.files.field_runs.sphere_diameter_m``, as ``calib.field``);
the raster is sampled bilinearly (``terrain.raster.Raster.sample``). The
raster's slope at a point is the magnitude of its central-difference gradient
over one cell.

It also reports the release velocity's components (the first tracked sample):
their mean along the line from the mean release to the mean stop, with its
standard error, and their robust spread (1.4826 x the median absolute
deviation).

Usage (the Tschamut 2014 numbers in docs/studies.md)::

    python scripts/raster_height_error.py data/tschamut2014/runs.csv \\
        --blocks data/tschamut2014/blocks.csv --raster data/tschamut2014/terrain_proxy.asc

Prints a plain-text report on stdout.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import pandas as pd
from scipy import stats

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.files.field_runs import (  # noqa: E402
    DEFAULT_DENSITY_KG_M3,
    load_runs,
    sphere_diameter_m,
)
from terrain.raster import read_raster  # noqa: E402

QUANTILES = (0.0, 0.05, 0.16, 0.25, 0.5, 0.75, 0.84, 0.95, 1.0)


def describe(v: np.ndarray) -> dict:
    """Mean, its standard error, sd, robust sd (1.4826 MAD), RMS and quantiles."""
    v = np.asarray(v, float)
    n = v.size
    return {"n": n, "mean": v.mean(), "se_mean": v.std(ddof=1) / np.sqrt(n),
            "sd": v.std(ddof=1), "robust_sd": stats.median_abs_deviation(v, scale="normal"),
            "rms": np.sqrt(np.mean(v * v)), "q": np.quantile(v, QUANTILES)}


def line(name: str, d: dict) -> str:
    q = " ".join(f"{100 * p:g}%:{x:+.2f}" for p, x in zip(QUANTILES, d["q"], strict=True))
    return (f"  {name}: n {d['n']}, mean {d['mean']:+.3f} (se {d['se_mean']:.3f}), sd "
            f"{d['sd']:.3f}, robust sd {d['robust_sd']:.3f}, rms {d['rms']:.3f} m\n"
            f"    quantiles {q}")


def slope_deg(raster, east, north) -> np.ndarray:
    """Raster slope (deg) from central differences over one cell (inside the data area)."""
    c = raster.cell_m
    (w, ea), (s, no) = raster.east_range_m, raster.north_range_m
    e0, e1 = np.maximum(east - c / 2, w), np.minimum(east + c / 2, ea)
    n0, n1 = np.maximum(north - c / 2, s), np.minimum(north + c / 2, no)
    gx = (raster.sample(e1, north) - raster.sample(e0, north)) / (e1 - e0)
    gy = (raster.sample(east, n1) - raster.sample(east, n0)) / (n1 - n0)
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", help="runs CSV (release/stop east, north, z; mass; velocity)")
    p.add_argument("--blocks", default=None, help="blocks CSV joined on block_id (masses)")
    p.add_argument("--raster", required=True, help="the terrain raster (.asc or .tif)")
    p.add_argument("--density-kg-m3", type=float, default=DEFAULT_DENSITY_KG_M3,
                   help=f"rock density of d (default {DEFAULT_DENSITY_KG_M3:g}, calib.field's)")
    p.add_argument("--steep-deg", type=float, default=10.0,
                   help="raster slope that splits gentle from steep ground, deg (default 10)")
    a = p.parse_args(argv)

    runs = load_runs(a.runs, a.blocks)
    table = pd.read_csv(a.runs)
    raster = read_raster(a.raster)
    d = sphere_diameter_m(runs.mass_kg, a.density_kg_m3)
    se, sn, sz = (table[c].to_numpy(float) for c in ("stop_x_m", "stop_y_m", "stop_z_m"))
    re_, rn = runs.release_east_m, runs.release_north_m
    e_stop = sz - d / 2 - raster.sample(se, sn)
    h_rel = runs.release_z_m - d / 2 - raster.sample(re_, rn)
    s_stop, s_rel = slope_deg(raster, se, sn), slope_deg(raster, re_, rn)
    steep = s_stop >= a.steep_deg

    print(f"{runs.n_runs} runs of {a.runs}; raster {a.raster} ({raster.cell_m:g} m cells); "
          f"d/2 = {d.min() / 2:.3f}-{d.max() / 2:.3f} m at {a.density_kg_m3:g} kg/m^3")
    print("tracked ground at the stops less the raster, e = (z_stop - d/2) - raster:")
    print(line("all stops", describe(e_stop)))
    print(line(f"stops on raster slope < {a.steep_deg:g} deg", describe(e_stop[~steep])))
    print(line(f"stops on raster slope >= {a.steep_deg:g} deg", describe(e_stop[steep])))
    sign = stats.binomtest(int(np.sum(e_stop < 0)), e_stop.size).pvalue
    print(f"  sign test of median 0 over all stops: {int(np.sum(e_stop < 0))} of {e_stop.size} "
          f"below, p = {sign:.2f}")
    rho = stats.spearmanr(s_stop, np.abs(e_stop))
    print(f"  |e| against the raster slope at the stop: Spearman {rho.statistic:+.2f} "
          f"(p = {rho.pvalue:.1g}); stop slopes {s_stop.min():.1f}-{s_stop.max():.1f} deg")
    print("tracked release height above the raster, h = (z_release - d/2) - raster:")
    print(line("all releases", describe(h_rel)))
    below = h_rel < 0
    print(f"  {int(below.sum())} of {h_rel.size} releases lie below the raster's ground (down "
          f"to {h_rel.min():+.2f} m): the raster lies at least that far above the true ground "
          f"there; release slopes {s_rel.min():.1f}-{s_rel.max():.1f} deg (median "
          f"{np.median(s_rel):.1f})")

    v = table[["release_vx_m_s", "release_vy_m_s", "release_vz_m_s"]].to_numpy(float)
    u = np.array([np.mean(se) - np.mean(re_), np.mean(sn) - np.mean(rn)])
    u /= np.linalg.norm(u)
    along = v[:, :2] @ u
    mad = stats.median_abs_deviation(v, axis=0, scale="normal")
    print("first tracked velocity (release):")
    print(f"  speed {np.quantile(np.linalg.norm(v, axis=1), [0, 0.5, 1]).round(2)} m/s "
          f"(min, median, max); mean along the fall line {along.mean():+.3f} m/s (se "
          f"{along.std(ddof=1) / np.sqrt(along.size):.3f}); components' mean "
          f"{np.round(v.mean(axis=0), 3)} m/s, sd {np.round(v.std(axis=0, ddof=1), 3)} m/s, "
          f"robust sd {np.round(mad, 3)} m/s (vx, vy, vz)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
