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
# # Calibrating rockfall models against what was seen on site: Postignano
#
# This notebook is for an engineering geologist who has never seen the code. It
# shows how `python -m calib.fit` turns field observations of block runouts into
# calibrated model parameters **with their uncertainty**, and what the
# Postignano data can and cannot tell us.
#
# **The site** (paper in `../shared/seed/`): a limestone slope in central Italy,
# a near-vertical cliff (75°) above a 40° talus (the upper accumulation zone)
# and a gentle (< 10°) lower zone where a provincial road runs. The paper's only
# field statement: blocks of 0.2-2.0 m travelled 110-220 m, farther for bigger
# blocks. We encode it as two observations (`data/postignano.csv`): a 0.2 m
# block at 110 m and a 2.0 m block at 220 m, each ± 15 m (an assumption: these
# are ends of a range, not surveyed points).
#
# **The two models.**
# * CRSP (lumped mass): a sphere bouncing with restitution coefficients Kn
#   (normal) and Kt (tangential) on a slope of roughness S. The paper used
#   Kn = 0.41, Kt = 0.87, S = 2 m.
# * DEM (UDEC-like rigid blocks): a square block with local damping alpha. The
#   paper had to make alpha fall with block size (Table 1: 0.90, 0.43, 0.30 for
#   L = 0.2, 0.9, 1.8 m); we fit alpha(L) = a L^-b.
#
# **How the fit works** (details in `docs/calibration.md`):
# 1. Each observation is treated as one block drawn from the simulated runout
#    distribution of blocks of its size, seen with a ± tolerance.
# 2. *Gradient fit*: the optimiser (Adam) follows a smoothed gradient of that
#    likelihood, evaluated with the same random blocks for every parameter
#    value (common random numbers) so that differences are due to parameters.
# 3. *Bayesian fit*: a statistical emulator (Gaussian process) learns how the
#    runout distribution depends on the parameters from a few hundred
#    simulations; for CRSP a second emulator then learns the likelihood itself
#    inside the region those simulations do not rule out, and NUTS samples the
#    posterior there. Diagnostics (R-hat, effective
#    sample size, divergences) are checked and failures are reported loudly.

# %%
import json
import os
import sys

import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Image, display

ROOT = os.path.abspath(".")
if not os.path.isdir(os.path.join(ROOT, "calib")):  # run from notebooks/
    ROOT = os.path.dirname(ROOT)
os.chdir(ROOT)
sys.path.insert(0, ROOT)

from calib.files.calibration_file import CalibrationFile  # noqa: E402
from calib.files.observations import load_observations  # noqa: E402
from calib.files.site import load_site  # noqa: E402
from solvers import load_profile  # noqa: E402

# NOTEBOOK_RESULTS: reuse a finished `calib.fit` output folder (the test suite does);
# NOTEBOOK_QUICK=1: small budgets. By hand, leave both unset for the full run (~5 min).
RESULTS = os.environ.get("NOTEBOOK_RESULTS", "")
QUICK = os.environ.get("NOTEBOOK_QUICK", "0") == "1"

# %% [markdown]
# ## 1. The observations and the slope

# %%
obs = load_observations("data/postignano.csv")  # checked rows (calib.files.observations)
profile = load_profile("data/postignano_profile.csv")
print(pd.DataFrame({"block_size_m": obs.block_size_m, "runout_m": obs.runout_m,
                    "runout_sd_m": obs.runout_sd_m}))
fig, ax = plt.subplots(figsize=(8, 3))
ax.plot(profile.x_m, profile.z_m, "k-")
for y in obs.runout_m:
    ax.axvline(y, color="tab:red", ls="--", lw=1)
site = load_site("data/postignano_profile.csv")  # data/postignano_site.json
ax.axvline(site.station_x_m, color="tab:gray", lw=3, alpha=0.5,
           label=f"{site.station_label} (assumed x = {site.station_x_m:g} m)")
ax.set_xlabel("x, m")
ax.set_ylabel("z, m")
ax.set_aspect("equal")
ax.legend()
ax.set_title("Reconstructed Postignano profile; dashed: observed runouts")
plt.show()

# %% [markdown]
# ## 2. Run the calibration
#
# The same as typing `python -m calib.fit data/postignano.csv --out results/`:
# `calib.fit.run_fit` reads and checks the rows and their profile
# (`calib.files.inputs`), calibrates each model (`calib.inference.calibrate.fit_model`),
# writes the outputs and hands back the typed results. A finished output folder is
# read back with the one reader of the calibration file.

# %%
if RESULTS and os.path.isfile(os.path.join(RESULTS, "calibration.json")):
    out = RESULTS
    calfile = CalibrationFile.from_json(os.path.join(out, "calibration.json"))
else:
    from calib.fit import run_fit

    out = "results"
    calfile = run_fit("data/postignano.csv", out, quick=QUICK, report=print).calibration
print("run:", calfile.command, "| quick:", calfile.quick)
crsp, dem = calfile.summary("crsp"), calfile.summary("dem")  # typed model sections

# %% [markdown]
# ## 3. CRSP: Kn, Kt, S (and the rolling resistance angle) against the paper
#
# The paper gives Kn, Kt and S; the rolling resistance angle (fitted by default)
# is the profile's 30 deg there, an assumption of the reconstruction.

# %%
rows = []
PAPER = {"Kn": 0.41, "Kt": 0.87, "roughness_m": 2.0, "rolling_friction_deg": None}
for name, s in crsp.parameters.items():
    rows.append({"parameter": name, "estimate": s.map, "posterior mean": s.mean,
                 "90% interval": f"{s.q05:.2f} - {s.q95:.2f}",
                 "paper": PAPER.get(name)})
crsp_table = pd.DataFrame(rows)
print(crsp_table.to_string(index=False))
print("diagnostics ok:", crsp.diagnostics_ok, "|", "; ".join(crsp.problems) or "all passed")

# %% [markdown]
# ## 4. DEM: the damping law alpha(L) against Table 1

# %%
print("law:", dem.alpha_form, {k: round(v.map, 3) for k, v in dem.parameters.items()})
print(pd.DataFrame([{"L (m)": f"{L:g}", "alpha fitted": v.map,
                     "90% interval": f"{v.q05:.2f} - {v.q95:.2f}",
                     "Table 1": dem.alpha_reference.get(L)} for L, v in dem.alpha_at_L.items()])
      .to_string(index=False))

# %%
for name in ("runout_vs_size.png", "alpha_law.png", "crsp_pairs.png"):
    with open(os.path.join(out, name), "rb") as fh:
        display(Image(fh.read()))

# %% [markdown]
# ## 5. How well does each model reproduce each observation?
#
# PIT is the probability that a simulated observation (block + tolerance) falls
# below the observed value: near 0.5 is a good fit, below 0.05 or above 0.95
# means the observation lies outside the model's 90 % band.

# %%
for model, sec in (("crsp", crsp), ("dem", dem)):
    q = pd.DataFrame(sec.fit_quality)
    print(model.upper())
    print(q[["block_size_m", "observed_m", "sim_q05_m", "sim_median_m", "sim_q95_m", "pit"]]
          .round(2).to_string(index=False))

# %% [markdown]
# ## 6. What the Postignano data do and do not constrain
#
# Two observations cannot pin down three or four CRSP parameters. The posterior shows
# which combinations they do constrain: the pair plot above. A parameter whose
# 90 % interval spans most of its prior range is NOT constrained by the data.

# %%
for name, s in crsp.parameters.items():
    lo, hi = crsp.prior[name]
    frac = (s.q95 - s.q05) / (hi - lo)
    verdict = "constrained" if frac < 0.5 else "weakly constrained" if frac < 0.8 else \
        "NOT constrained"
    print(f"{name:12} 90% interval covers {100 * frac:4.0f} % of the prior range -> {verdict}")
for name, s in dem.parameters.items():
    lo, hi = dem.prior[name]
    frac = (s.q95 - s.q05) / (hi - lo)
    print(f"DEM {name:8} 90% interval covers {100 * frac:4.0f} % of the prior range")

# %% [markdown]
# ## 7. Stage timings

# %%
print(json.dumps(calfile.timings_s, indent=1))
