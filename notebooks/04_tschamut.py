# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # From an elevation raster and a field campaign to a checked calibration: Tschamut 2014
#
# This notebook is for an engineer who has run a rockfall campaign of their own:
# blocks of known mass released at known points and found where they stopped,
# on a slope with an elevation model. It walks the whole path with the real
# Tschamut experiment (Volkwein & Gerber 2018, EnviDat, doi 10.16904/envidat.34;
# ODbL with DbCL; provenance in `data/tschamut2014/README.md`):
#
# 1. cut a 2D slope profile from the raster along the mean fall line of the runs
#    (`python -m terrain.cut`; its library `terrain.raster`, `terrain.plan_line`);
# 2. turn the runs into observations: distance travelled along the profile,
#    each block's size from its mass, each run's own release point
#    (`python -m calib.field`; its library `calib.files.field_runs`);
# 3. calibrate CRSP on part of the runs, keeping the rest aside
#    (`python -m calib.fit --holdout-fraction`, `calib.fit.run_fit` here), with
#    the rolling resistance fitted as a fourth parameter;
# 4. ask whether the calibration earns its keep: does it predict the held-out
#    runs better than simply quoting the runouts seen so far
#    (`python -m calib.validate`, run at the end of the fit)?
#
# Every number below is computed by the same library functions the commands
# run, not typed in. With
# `NOTEBOOK_QUICK=1` the fit uses small budgets (a first look, about 2 minutes
# on 2 cores; its posterior diagnostics fail and say so); the default budgets
# take about 10-20 minutes. `NOTEBOOK_RESULTS=folder` reuses a finished fit.

# %%
import io
import os
import sys
import tempfile

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

ROOT = os.path.abspath(".")
if not os.path.isdir(os.path.join(ROOT, "calib")):  # run from notebooks/
    ROOT = os.path.dirname(ROOT)
os.chdir(ROOT)
sys.path.insert(0, ROOT)

from calib.files.calibration_file import CalibrationFile  # noqa: E402
from calib.files.field_runs import (  # noqa: E402
    load_runs,
    observations_csv_text,
    observations_on_profiles,
)
from calib.files.observations import load_observations  # noqa: E402
from calib.fit import run_fit, validate_heldout  # noqa: E402
from calib.validate import read_summary  # noqa: E402
from solvers import load_profile  # noqa: E402
from terrain.plan_line import read_fall_line  # noqa: E402
from terrain.raster import cut_profile, parse_zones, profile_csv_text, read_raster  # noqa: E402

QUICK = os.environ.get("NOTEBOOK_QUICK", "0") == "1"
RESULTS = os.environ.get("NOTEBOOK_RESULTS", "")
SITE = "data/tschamut2014"
WORK = os.environ.get("NOTEBOOK_WORK") or tempfile.mkdtemp(prefix="tschamut-")
HOLDOUT_FRACTION, SEED = 0.3, 1

# %% [markdown]
# ## 1. The raster and the runs
#
# The raster is a 5 m proxy built from the tracked ground points (the campaign's
# own elevation model is not public; `data/tschamut2014/README.md`). Each run
# gives a release and a stop point in the raster's coordinates.

# %%
grid = read_raster(os.path.join(SITE, "terrain_proxy.asc"))
runs = pd.read_csv(os.path.join(SITE, "runs.csv"))
print(f"raster {grid.shape[0]} x {grid.shape[1]} cells of {grid.cell_m:g} m; "
      f"{len(runs)} runs of {runs.block_id.nunique()} blocks "
      f"({', '.join(f'{m:g} kg' for m in sorted(runs.mass_kg.unique()))})")
e0, n0 = grid.east0_m, grid.north0_m
extent = (e0 - grid.cell_m / 2, e0 + (grid.shape[1] - 0.5) * grid.cell_m,
          n0 - grid.cell_m / 2, n0 + (grid.shape[0] - 0.5) * grid.cell_m)
fig, ax = plt.subplots(figsize=(6, 6))
im = ax.imshow(grid.z_m, origin="lower", extent=extent, cmap="terrain")
ax.contour(grid.z_m, origin="lower", extent=extent, colors="k", linewidths=0.3, levels=20)
ax.plot(runs.release_x_m, runs.release_y_m, "k^", ms=4, label="release")
ax.plot(runs.stop_x_m, runs.stop_y_m, "ro", ms=3, label="stop")
ax.set_xlabel("east, m")
ax.set_ylabel("north, m")
ax.legend()
fig.colorbar(im, ax=ax, label="elevation, m")
plt.show()

# %% [markdown]
# ## 2. A profile along the mean fall line
#
# The line runs from the mean release to the mean stop point, extended by 40 m
# at both ends so that every stop lies on it; heights are sampled bilinearly
# every metre. Two material zones split at 100 m along the line: the steep
# meadow and the flat run-out (the zone split is our reading of the terrain).

# %%
ZONES = parse_zones("steep:0:100,flat:100:")
cut = cut_profile(grid, read_fall_line(os.path.join(SITE, "runs.csv"), 40.0), 1.0, ZONES)
ours = pd.read_csv(io.StringIO(profile_csv_text(cut)))  # the profile CSV terrain.cut writes
shipped = pd.read_csv(os.path.join(SITE, "profile.csv"))
print("same profile as the shipped one:", ours[["x_m", "z_m"]].equals(shipped[["x_m", "z_m"]]))
profile = load_profile(os.path.join(SITE, "profile.csv"))

# %% [markdown]
# The blocks were let go from three spots across the slope. Two lie within
# about 20 m of that line; the third lies 34 m to its left, where the line's
# ground is up to 1 m above the tracked release points: the line is not the
# ground those runs started on. That spot gets a profile of its own, along the
# mean fall line of the runs released within 10 m of it (`--fall-line-near`).

# %%
spot_cut = cut_profile(grid, read_fall_line(os.path.join(SITE, "runs.csv"), 40.0,
                                            near=(59.0, 257.5, 10.0)), 1.0, ZONES)
spot_ours = pd.read_csv(io.StringIO(profile_csv_text(spot_cut)))
spot_shipped = pd.read_csv(os.path.join(SITE, "east_spot_profile.csv"))
print("same spot profile as the shipped one:",
      spot_ours[["x_m", "z_m"]].equals(spot_shipped[["x_m", "z_m"]]))
spot = load_profile(os.path.join(SITE, "east_spot_profile.csv"))

# %% [markdown]
# ## 3. Field runs as observations
#
# Each release and stop point is projected onto the line; the runout is the
# distance between the two projections. A point far off the line (here more
# than 20 m: blocks fanned out across the slope) is kept and flagged. The block
# size is the diameter of the sphere of the block's mass at 2650 kg/m3 (an
# assumption, `calib/files/field_runs.py`). The first tracked point of a run
# also says how high above the ground the block was let go: its centre, less
# half the block size, above the profile's ground under it (`release_height_m`).
# With two profiles, each run goes on the one whose line passes nearest its
# release point, and a `profile` column says which.

# %%
obs_csv = os.path.join(WORK, "observations.csv")
field_rows = observations_on_profiles(
    load_runs(os.path.join(SITE, "runs.csv"), os.path.join(SITE, "blocks.csv")),
    [os.path.join(SITE, "profile.csv"), os.path.join(SITE, "east_spot_profile.csv")], WORK,
    source="Tschamut 2014 (Volkwein & Gerber 2018, EnviDat, doi:10.16904/envidat.34)")
with open(obs_csv, "w") as fh:  # what python -m calib.field writes
    fh.write(observations_csv_text(field_rows))
observed = load_observations(obs_csv)  # read back and checked (calib.files.observations)
obs = pd.DataFrame({k: getattr(observed, k) for k in ("block_size_m", "runout_m", "release_x_m",
                                                   "release_height_m", "profile")})
on_spot = obs.profile.str.endswith("east_spot_profile.csv").to_numpy()
print(obs.groupby("block_size_m").runout_m.describe()[["count", "min", "50%", "max"]])
print(f"release heights above the profile's ground: {obs.release_height_m.min():.2f} to "
      f"{obs.release_height_m.max():.2f} m (median {obs.release_height_m.median():.2f} m)")
fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
for ax, prof, rows, name in ((axes[0], profile, ~on_spot, "the mean fall line"),
                             (axes[1], spot, on_spot, "the left spot's own line")):
    sub = obs[rows]
    ax.plot(prof.x_m, prof.z_m, "k-")
    for x0, r in zip(sub.release_x_m, sub.runout_m, strict=True):
        ax.plot([x0 + r], [np.interp(x0 + r, prof.x_m, prof.z_m)], "r|", ms=10)
    ax.plot(sub.release_x_m, np.interp(sub.release_x_m, prof.x_m, prof.z_m), "k^", ms=4)
    ax.set_ylabel("z, m")
    ax.set_aspect("equal")
    ax.set_title(f"{len(sub)} runs on {name}: releases (triangles) and stops (red)")
axes[1].set_xlabel("distance along the profile, m")
plt.show()

# %% [markdown]
# The runouts spread over about 100 m for one block size: some blocks stop on
# the steep meadow, most on the flat run-out. A lumped-mass model with one
# parameter set for the slope must produce that spread from its random
# roughness alone; watch whether it can.
#
# ## 4. Calibrate on 70 % of the runs, predict the other 30 %
#
# `calib.fit` releases each calibration row from its own point and height (rows
# of one size whose releases lie within 1 m along the line and in height share
# one simulated release), fits Kn,
# Kt, the roughness S and the rolling resistance angle by gradient and by
# Bayesian inference, checks whether the model can fit the rows at all, then
# scores its predictions of the held-out rows.

# %%
if RESULTS:
    out = RESULTS
    calfile = CalibrationFile.from_json(os.path.join(out, "calibration.json"))
    val = read_summary(os.path.join(out, "validation", "validation.json"))
else:
    out = os.path.join(WORK, "fit")
    run = run_fit(obs_csv, out, profile=os.path.join(SITE, "profile.csv"), models=("crsp",),
                  holdout_fraction=HOLDOUT_FRACTION, seed=SEED, quick=QUICK, report=print)
    calfile = run.calibration
    # the posterior's predictive check (out/validation/) and the point estimate's
    val = validate_heldout(out, "crsp", SEED)[0][0]
crsp = calfile.summary("crsp")  # the typed CRSP section

# %% [markdown]
# ## 5. What the calibration says, and whether to trust it

# %%
print(pd.DataFrame([{"parameter": n, "estimate": s.map, "mean": s.mean,
                     "90 % interval": f"{s.q05:.3g} - {s.q95:.3g}",
                     "prior": f"{crsp.prior[n][0]:g} - {crsp.prior[n][1]:g}"}
                    for n, s in crsp.parameters.items()]).to_string(index=False))
print("\nposterior diagnostics ok:", crsp.diagnostics_ok)
for p in crsp.problems:
    print("  -", p)
ad = crsp.adequacy
print("\ncan the model fit these rows?", "yes" if ad["ok"] else "NO")
for p in ad["problems"]:
    print("  -", p)

# %% [markdown]
# Read the two checks before any number above. The diagnostics say whether the
# sampler explored the posterior (R-hat near 1 in every chain) and whether the
# intervals are as wide as the emulator's own uncertainty requires (the
# posterior medians of 32 realisations of the log-likelihood GP, which should
# lie inside each 90 % interval; while they do not, the fit simulates one
# point from each realisation's posterior and samples again, three times at
# most, and when they still do not, another seed or more simulations may move
# the posterior that far); the adequacy
# check says whether the calibrated model reproduces the rows it was fitted
# to: posterior mass piled on a prior bound means the data push a parameter
# out of its published range, and too few rows inside their predictive bands
# means the model's spread is wrong. Either one says: this model, with one
# parameter set for the slope, does not describe this campaign. A third
# check names release groups whose simulated blocks stall at the release
# while the observed ones did not.
#
# ## 6. Prediction of the held-out runs against climatology
#
# Climatology is the forecast anyone can make without a model: the runouts of
# the calibration rows themselves. The continuous ranked probability score
# (CRPS, m; lower is better) scores a whole predictive distribution against
# one observed runout; skill = 1 - CRPS / CRPS_climatology (1 perfect, 0 no
# better than climatology, negative worse).

# %%
print(f"held-out rows scored: {val['n_scored']}")
print(f"mean CRPS {val['mean_crps_m']:.2f} m against climatology "
      f"{val['mean_crps_climatology_m']:.2f} m: skill {val['skill_vs_climatology']:.2f}")
print(f"90 % interval coverage {val['coverage_90']:.0%} (nominal 90 %), "
      f"50 % coverage {val['coverage_50']:.0%}; {val['n_above_90']} rows above the 90 % "
      f"band, {val['n_below_90']} below")
print(f"error of the predictive mean {val['mean_error_of_mean_m']:+.1f} m on average "
      "(positive: the model overshoots)")

# %%
for name in ("runout_vs_size.png", "crsp_pairs.png", os.path.join("validation", "intervals.png"),
             os.path.join("validation", "pit_histogram.png")):
    img = plt.imread(os.path.join(out, name))
    plt.figure(figsize=(7, 5))
    plt.imshow(img)
    plt.axis("off")
    plt.title(name)
    plt.show()

# %% [markdown]
# ## 7. What to do with your own campaign
#
# * Cut the profile along the mean fall line of your runs, check that every
#   stop lies on it and look at the lateral offsets `calib.field` reports: a
#   2D profile cannot represent blocks that fan out across the slope.
# * Look at the ground the releases land on: `adequacy.stalls` in
#   `calibration.json` gives, per release group, the slope just below the
#   release and how many simulated blocks stop within 1 m of it. Here the
#   releases project onto a 21-26 deg shoulder above a 44 deg slope. Blocks
#   let go from above the ground (`release_height_m`) fall onto it and run on.
#   On one line for all runs, the runs from the spot 34 m left of it started
#   below the line's ground, were released on it, and stalled under a rolling
#   resistance steeper than the shoulder; the posterior split into modes that
#   did and did not let them start. Runs from spots far apart need a profile
#   along each spot's own fall line, as above.
# * Keep 30 % of the runs aside and run the predictive check. Use the
#   calibration only if its skill against climatology is positive and its
#   90 % intervals cover about 90 % of the held-out runs; the adequacy check
#   in `calibration.json` says the same for the calibration rows.
# * When the check fails, as it may on a campaign like this one, the honest
#   answers are the ones the outputs give: which parameter piles on its
#   bound, which rows fall outside their bands, and `python -m calib.discover
#   observations.csv --rolling-resistance fit` to look for the missing effect.
# * If your slope's materials differ (rock face above, soil or scree below),
#   give the profile one zone each (`--zones` of `terrain.cut`) and
#   fit one rolling-resistance angle per zone (`calib.fit
#   --rolling-resistance zones`). Here both zones are one meadow: the zoned
#   fit passes its checks but leaves both angles barely determined and
#   predicts no better than one angle (docs/studies.md, "one rolling
#   resistance per zone").
#   A hazard table made from a calibration that fails its own check is a
#   number without a warrant.
