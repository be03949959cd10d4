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
# # What physics is my model missing? The discrepancy workflow
#
# A calibrated model can still be wrong in a systematic way. For example, it can send
# big blocks too far or let small blocks run past a forest. Engineers usually spot
# this by staring at plots. `python -m calib.discover` does it systematically:
#
# 1. **Fit the baseline model** and compare its predictions with every observation.
#    Each row gets a *quantile residual*: above 0, the block went further than
#    predicted.
# 2. **Locate the disagreement.** Test the residuals by block size and by where on
#    the slope the blocks stopped, each with a p-value (Bonferroni-corrected).
# 3. **Fit each candidate effect.** Each one is real physics inside the solver:
#    - size-dependent energy dissipation,
#    - fragmentation on a hard impact,
#    - rolling resistance,
#    - a vegetation belt.
#
#    Compare them by how well they predict rows they were not fitted to (5-fold
#    held-out log score). An effect is **named** only when its gain over the baseline
#    beats 4 nats and 2 standard errors. Otherwise the answer is `none`.
# 4. **Show the gap shrink.** The gap metric is the mean CRPS in metres per size
#    class, before and after the named effect is added.
#
# First we prove it on data where we hid an effect ourselves, then we apply it
# to Postignano.

# %%
import json
import os
import tempfile

from IPython.display import Image, display

from calib import discover, synth

SMALL = os.environ.get("NOTEBOOK_SMALL") == "1"  # the tests run this notebook at small size
work = tempfile.mkdtemp(prefix="discovery-")

# %% [markdown]
# ## 1. A hidden effect: blocks that roll with extra resistance
#
# `calib.synth` simulates 60 blocks (0.2-2.0 m) with CRSP, with rolling
# resistance switched on. The answer goes to a separate `synth.truth.json`, and the
# workflow only sees the CSV.

# %%
data = os.path.join(work, "synth.csv")
synth.main(["--effect", "rolling_resistance", "--strength", "1.5", "--seed", "21",
            "--n-obs", "30" if SMALL else "60", "--profile", "data/postignano_profile.csv",
            "--out", data])
print(open(data).read().splitlines()[:4])

# %%
out = os.path.join(work, "disc")
discover.main([data, "--out", out, "--no-progress"] + (["--quick"] if SMALL else []))
result = json.load(open(os.path.join(out, "discovery.json")))
truth = json.load(open(os.path.join(work, "synth.truth.json")))
print("hidden:", truth["effect"], "| named:", result["named_effect"])

# %% [markdown]
# **Where the baseline failed.** The small blocks stop *short*, some of them on the
# 40° talus, where the baseline never lets a block rest:

# %%
for line in result["where"]["flagged"][:5]:
    print("-", line)
display(Image(os.path.join(out, "residuals.png")))

# %% [markdown]
# **The candidates, ranked** by held-out score gain over the baseline. The effect
# was named only because its gain is large against its standard error.

# %%
display(Image(os.path.join(out, "candidates.png")))
display(Image(os.path.join(out, "before_after.png")))
print(f"gap before {result['gap_before']:.1f} m -> after {result['gap_after']:.1f} m")

# %% [markdown]
# ## 2. When runouts are not enough: a forest belt and passage speeds
#
# A belt of trees that slows blocks over a stretch of the slope shortens the
# runouts of big blocks. So does a lower tangential restitution Kt everywhere,
# and with runouts and sizes alone the baseline can mimic the belt that way
# (docs/studies.md, "Passage speeds"). The two differ *above* the belt: a lower
# Kt slows blocks there too, a belt does not. `calib.synth --velocity-stations-m 110` also
# writes the speeds of some blocks passing 110 m (the belt starts at 129 m), and
# `calib.discover --velocities` scores them together with the runouts.

# %%
data_b = os.path.join(work, "belt.csv")
synth.main(["--effect", "vegetation_belt", "--seed", "99", "--n-obs", "30" if SMALL else "60",
            "--profile", "data/postignano_profile.csv",
            "--velocity-stations-m", "110", "--n-velocity", "12" if SMALL else "30",
            "--out", data_b])
out_b = os.path.join(work, "belt")
discover.main([data_b, "--velocities", os.path.join(work, "belt_velocities.csv"),
               "--out", out_b, "--no-progress"] + (["--quick"] if SMALL else []))
belt = json.load(open(os.path.join(out_b, "discovery.json")))
for c in belt["candidates"]:
    if c["effect"] != "none":
        print(f"{c['effect']:18} gain {c['delta_vs_none']:+7.1f} +- {c['se_delta']:5.1f}, "
              f"of which from the speeds {c['delta_velocity_rows']:+6.1f}")
print("named:", belt["named_effect"])

# %% [markdown]
# At full size (60 runout rows, 30 speeds) this seed names the belt. Over five
# unseen seeds the speeds raised the belt's detection from 2 of 5 to 4 of 5
# (docs/studies.md). At the notebook's small test size the verdict printed
# above may be `none`: 30 rows and 12 speeds are little data.

# %% [markdown]
# ## 3. Postignano: is one damping coefficient enough for the DEM?
#
# The paper found that its UDEC model could not reproduce both the 0.2 m block
# stopping at 110 m and the 2.0 m block reaching 220 m with one local damping
# coefficient. It made alpha depend on block size (Table 1).
#
# Here the DEM baseline has **one alpha for all sizes**, and the candidate
# `size_dissipation` is alpha(L) = a L^-b. Postignano offers two observations
# only, so the held-out score is leave-one-out over two rows. Read what follows
# with that in mind.
#
# The default DEM run (`python -m calib.discover data/postignano.csv --model
# dem`) tries the size-dependent law. The fragmentation candidate (`--effects
# size_dissipation,fragmentation`) costs about 25 minutes on two cores. At small
# size the notebook uses the quick budget.

# %%
out_p = os.path.join(work, "postignano")
args = ["data/postignano.csv", "--model", "dem", "--out", out_p, "--no-progress"]
if SMALL:
    args += ["--quick"]
discover.main(args)
post = json.load(open(os.path.join(out_p, "discovery.json")))
for line in post["where"]["flagged"] or [post["where"]["summary"]]:
    print("-", line)
for c in post["candidates"]:
    print(f"{c['effect']:18} score {c['score']:7.2f}  gain {c['delta_vs_none']:+6.2f}  "
          f"gap {c['gap']:6.1f} m")
print("named:", post["named_effect"])

# %%
display(Image(os.path.join(out_p, "before_after.png")))

# %% [markdown]
# **Reading the Postignano result.** With two observations, the question is
# whether the size trend the paper described is visible at all. The baseline's
# residuals show it by sign: the 0.2 m block goes less far than one alpha
# predicts, and the 2.0 m block further.
#
# Whether it clears the naming threshold (4 nats and 2 standard errors) is
# printed above. Two rows cannot give a meaningful standard error, so with this
# little data the rule falls back on the 4-nat threshold alone.
#
# `docs/studies.md` reports the measured power studies (how often the workflow
# names each hidden effect, with the commands that reproduce them).
