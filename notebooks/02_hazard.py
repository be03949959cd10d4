# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Rockfall hazard on the Postignano slope, with the calibration's uncertainty
#
# From `results/calibration.json` (written by `python -m calib.fit`) to
#
# 1. runout exceedance curves P(runout beyond x) with posterior bands,
# 2. energy and bounce-height envelopes along the profile,
# 3. a hazard zoning of the slope (Swiss intensity classes and intensity-frequency
#    matrix, see `calib/hazard/_intensity.py` for the sources and which part is
#    recalled rather than verified),
# 4. a barrier design check at the road (x = 230 m, an assumption of
#    `data/README.md`).
#
# Every posterior draw of the calibrated parameters is simulated with its own
# random numbers, so the bands carry the calibration's uncertainty plus the
# Monte Carlo noise of each draw. The command line does the same run:
# `python -m calib.hazard results/calibration.json`.
#
# Small-size switch: `HAZARD_NOTEBOOK_SMALL=1` (used by the tests).
# `HAZARD_CALIBRATION` overrides the calibration file.

# %%
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from IPython.display import Image, display  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from calib.files.site import load_site  # noqa: E402
from calib.hazard import (  # noqa: E402
    BINS,
    draw_parameters,
    exceedance_table,
    hazard_table,
    load_calibration,
    plot_envelopes,
    plot_exceedance,
    run_hazard,
    summary_text,
)
from solvers import load_profile  # noqa: E402

SMALL = os.environ.get("HAZARD_NOTEBOOK_SMALL") == "1"
CALIBRATION = os.environ.get("HAZARD_CALIBRATION", "results/calibration.json")
OUT = os.environ.get("HAZARD_NOTEBOOK_OUT", "results/hazard_notebook")
os.makedirs(OUT, exist_ok=True)

SIZES_M = [0.2, 0.5, 1.0, 2.0]          # average block diameters, m (the observed range)
N_POSTERIOR = 2 if SMALL else 40        # posterior draws
N_BLOCKS = 100 if SMALL else 5000       # blocks per draw and size
ROAD_X_M = load_site("data/postignano_profile.csv").station_x_m  # data/postignano_site.json
STATIONS_M = np.union1d(np.arange(0.0, 301.0, 20.0 if SMALL else 5.0), [ROAD_X_M])
SEED = 0
# ILLUSTRATIVE, NOT DATA: blocks of each size released per year. Nothing in the
# paper gives a release frequency; replace with the site's inventory.
RELEASE_RATE_PER_YEAR = 0.2

# %% [markdown]
# ## The calibration

# %%
cal = load_calibration(CALIBRATION, "crsp")
profile = load_profile(cal.profile_csv)
draws = draw_parameters(cal, N_POSTERIOR, SEED)
print(f"{cal.path}: model {cal.model}, point estimate "
      + ", ".join(f"{n} = {v:.3g}" for n, v in zip(cal.names, cal.point, strict=True)))
print(f"{len(draws.values)} draw(s) from the {draws.source}")
if len(draws.values) > 1:
    for n, col in zip(draws.names, draws.values.T, strict=True):
        print(f"  {n}: draws span {col.min():.3g} .. {col.max():.3g}")

# %% [markdown]
# ## Monte Carlo over the posterior
#
# Per draw, each block size runs `N_BLOCKS` blocks (CRSP sphere of radius D/2).
# Only integer counts and histograms leave the device (`calib/hazard/_stats.py`).

# %%
total = len(draws.values) * len(SIZES_M) * N_BLOCKS
with tqdm(total=total, unit="block") as bar:
    counts = run_hazard(cal, draws, profile, SIZES_M, STATIONS_M, N_BLOCKS, SEED,
                        progress=bar.update)
exc = exceedance_table(counts)
table = hazard_table(counts, profile, RELEASE_RATE_PER_YEAR)
print(summary_text(counts, table, ROAD_X_M, RELEASE_RATE_PER_YEAR))

# %% [markdown]
# ## Exceedance curves and envelopes

# %%
title = f"CRSP, {len(draws.values)} draw(s) x {N_BLOCKS} blocks per size"
plot_exceedance(exc, profile, ROAD_X_M, os.path.join(OUT, "exceedance.png"), title)
plot_envelopes(table, profile, ROAD_X_M, os.path.join(OUT, "envelopes.png"), title)
display(Image(os.path.join(OUT, "exceedance.png")))
display(Image(os.path.join(OUT, "envelopes.png")))

# %% [markdown]
# Where does the hazard zone end? The farthest station that a fraction
# `p` of the blocks passes, for the posterior mean and the pessimistic (95 %)
# band of the exceedance curve. With N blocks per draw a probability below
# about 1/N cannot be resolved.

# %%
for size, g in exc.groupby("block_size_m"):
    msg = []
    for p in (1e-1, 1e-2):
        mean_x = g.x_m[g.p_exceed_mean >= p].max()
        q95_x = g.x_m[g.p_exceed_q95 >= p].max()
        msg.append(f"P >= {p:g}: x <= {mean_x:g} m (95 % band: {q95_x:g} m)")
    print(f"D = {size:g} m: " + "; ".join(msg))

# %% [markdown]
# ## Hazard zoning
#
# With the (illustrative) release rate, each station gets the annual frequency of
# a block reaching it with E > 0, > 30 kJ and > 300 kJ, and the hazard level of
# the intensity-frequency matrix (most severe over the three classes).

# %%
level_colors = {"red": "#d62728", "blue": "#1f77b4", "yellow": "#ffdd44",
                "residual": "#fff7bc", "white": "#ffffff", "": "#bbbbbb"}
fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(8, 5), sharex=True,
                               gridspec_kw={"height_ratios": [2, 1]})
ax0.plot(np.asarray(profile.x_m), np.asarray(profile.z_m), "k-")
ax0.axvline(ROAD_X_M, color="k", ls="--", lw=1)
ax0.set_ylabel("z (m)")
ax0.set_title(f"hazard levels, release rate {RELEASE_RATE_PER_YEAR:g} blocks/yr per size "
              "(illustrative)", fontsize=9)
mids = 0.5 * (STATIONS_M[1:] + STATIONS_M[:-1])
cell_lo = np.concatenate([[STATIONS_M[0]], mids])   # each station colours the cell
cell_hi = np.concatenate([mids, [STATIONS_M[-1]]])  # between its neighbours' midpoints
for i, (size, g) in enumerate(table.groupby("block_size_m")):
    g = g.sort_values("x_m")
    ax1.barh(i, cell_hi - cell_lo, left=cell_lo, edgecolor="none",
             color=[level_colors[v] for v in g.hazard_level.fillna("")])
ax1.set_yticks(range(len(SIZES_M)), [f"D = {s:g} m" for s in sorted(SIZES_M)])
ax1.axvline(ROAD_X_M, color="k", ls="--", lw=1)
ax1.set_xlabel("x (m)")
fig.tight_layout()
fig.savefig(os.path.join(OUT, "zoning.png"), dpi=110)
plt.close(fig)
display(Image(os.path.join(OUT, "zoning.png")))
print(table[np.isclose(table.x_m, ROAD_X_M)][
    ["block_size_m", "freq_reach_per_yr", "freq_E_gt_30kJ_per_yr", "freq_E_gt_300kJ_per_yr",
     "hazard_level"]].to_string(index=False))

# %% [markdown]
# ## Barrier design check at the road
#
# Design values at the road: the 95th percentile of the kinetic energy and of
# the bounce height of the blocks that reach it (the percentile UNI 11211-4
# designs on), with the 5-95 % band of the energy percentile over posterior
# draws. The candidate barrier below is ILLUSTRATIVE (capacity and height are
# not from any product); the check compares its capacity with the upper band
# of the design energy and its height with the bounce-height p95, and reports
# the fraction of arriving blocks whose energy exceeds the capacity (read from
# the pooled energy histogram). UNI 11211-4's partial safety factors are not
# applied here.

# %%
CAPACITY_KJ = 1000.0
HEIGHT_M = 4.0

bins = BINS["energy_kJ"]
edges = bins.edges()
s_road = int(np.argmin(np.abs(counts.stations_x_m - ROAD_X_M)))
for t, size in enumerate(counts.sizes_m):
    r = table[(table.block_size_m == size) & np.isclose(table.x_m, ROAD_X_M)].iloc[0]
    h = counts.hist["energy_kJ"][t, s_road]
    n_pass = h.sum()
    if n_pass == 0:
        print(f"D = {size:g} m: no simulated block reaches the road "
              f"(P < ~1/{len(draws.values) * N_BLOCKS})")
        continue
    # counts in bins entirely above the capacity (a lower bound within one bin)
    above = h[1:-1][edges[:-1] >= CAPACITY_KJ].sum() + h[-1]
    ok_e = r.energy_p95_kJ_q95 <= CAPACITY_KJ
    ok_h = r.bounce_height_p95_m <= HEIGHT_M
    print(f"D = {size:g} m: P(reach) = {r.reach_prob_mean:.3g}; E p95 = "
          f"{r.energy_p95_kJ:.4g} kJ [{r.energy_p95_kJ_q05:.4g}, {r.energy_p95_kJ_q95:.4g}] "
          f"-> {'OK' if ok_e else 'EXCEEDS'} {CAPACITY_KJ:g} kJ; bounce p95 = "
          f"{r.bounce_height_p95_m:.3g} m -> {'OK' if ok_h else 'TOO HIGH for'} "
          f"{HEIGHT_M:g} m; P(E > capacity | reach) >= {above / n_pass:.3g}")
