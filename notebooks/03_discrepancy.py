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
# to Postignano. Last, back on the data with the hidden effect, the named effect
# joins the model that is calibrated, checked on rows it never saw and run for
# the hazard (section 4).

# %%
import io
import os
import tempfile
import warnings

import jax
import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Image, display

from calib.discovery.candidates import candidate_set
from calib.discovery.discrepancy import discover
from calib.discovery.synthetic import (
    compare_exceedance,
    observations_csv_text,
    synthesize_effect,
    synthesize_velocities,
    truth_exceedance,
    velocities_csv_text,
)
from calib.files.inputs import load_inputs
from calib.files.observations import load_velocities
from calib.files.site import load_site
from calib.fit import run_fit, validate_heldout
from calib.hazard import draw_parameters, exceedance_table, load_calibration, run_hazard
from calib.inference.budget import discovery_budget
from calib.model.unfinished import UnfinishedBlocksWarning
from calib.plots.discovery_figures import discovery_figures
from solvers import load_profile

SMALL = os.environ.get("NOTEBOOK_SMALL") == "1"  # the tests run this notebook at small size
work = tempfile.mkdtemp(prefix="discovery-")
PROFILE_CSV = "data/postignano_profile.csv"
slope = load_profile(PROFILE_CSV)


def write(path, text):
    with open(path, "w") as fh:
        fh.write(text)


def run_discovery(data, model="crsp", velocities=None):
    """The workflow as `python -m calib.discover DATA --model MODEL` runs it (seed 0,
    each row from its own release, rows within 1 m grouped), on the checked rows of
    DATA and PROFILE_CSV: the rows, and the typed `Discovery`."""
    inputs = load_inputs(data, PROFILE_CSV, work)
    cands, combine = candidate_set(model, None, inputs.profile)
    with warnings.catch_warnings():  # counted in each fit's record instead
        warnings.simplefilter("ignore", UnfinishedBlocksWarning)
        d = discover(cands, inputs.obs, inputs.profile, jax.random.key(0),
                     discovery_budget(model, SMALL), velocities=velocities,
                     release_tolerance_m=1.0, release_errors=inputs.release_errors,
                     combine=combine)
    return inputs.obs, d


def show(fig):
    """A figure as the command writes it (PNG, 120 dpi)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    display(Image(buf.getvalue()))

# %% [markdown]
# ## 1. A hidden effect: blocks that roll with extra resistance
#
# `calib.discovery.synthetic` (the library of `python -m calib.synth`) simulates
# 60 blocks (0.2-2.0 m) with CRSP, with rolling resistance switched on. The answer
# stays in `truth`, and the workflow only sees the CSV.

# %%
data = os.path.join(work, "synth.csv")
synth_obs, truth = synthesize_effect(slope, "rolling_resistance", 1.5, 30 if SMALL else 60, 21)
write(data, observations_csv_text(synth_obs, 21))
print(open(data).read().splitlines()[:4])

# %%
obs, result = run_discovery(data)
print("hidden:", truth["effect"], "| named:", result.named_effect)
figs = discovery_figures(obs, result, "crsp")

# %% [markdown]
# **Where the baseline failed.** The small blocks stop *short*, some of them on the
# 40° talus, where the baseline never lets a block rest:

# %%
for line in result.where_before["flagged"][:5]:
    print("-", line)
show(figs["residuals.png"])

# %% [markdown]
# **The candidates, ranked** by held-out score gain over the baseline. The effect
# was named only because its gain is large against its standard error.

# %%
show(figs["candidates.png"])
show(figs["before_after.png"])
print(f"gap before {result.gap_before:.1f} m -> after {result.gap_after:.1f} m")

# %% [markdown]
# ## 2. When runouts are not enough: a forest belt and passage speeds
#
# A belt of trees that slows blocks over a stretch of the slope shortens the
# runouts of big blocks. So does a lower tangential restitution Kt everywhere,
# and with runouts and sizes alone the baseline can mimic the belt that way
# (docs/studies.md, "Passage speeds"). The two differ *above* the belt: a lower
# Kt slows blocks there too, a belt does not. `calib.synth --velocity-stations-m 110` also
# writes the speeds of some blocks passing 110 m (the belt starts at 129 m)
# (`synthesize_velocities` here), and `calib.discover --velocities` scores them
# together with the runouts.

# %%
data_b = os.path.join(work, "belt.csv")
belt_obs, belt_truth = synthesize_effect(slope, "vegetation_belt", 1.0, 30 if SMALL else 60,
                                        99)
write(data_b, observations_csv_text(belt_obs, 99))
speeds_csv = os.path.join(work, "belt_velocities.csv")
write(speeds_csv, velocities_csv_text(
    synthesize_velocities(slope, "vegetation_belt", 1.0, 12 if SMALL else 30, 99, [110.0]), 99))
_, belt = run_discovery(data_b, velocities=load_velocities(speeds_csv))
for c in belt.table:
    if c["effect"] != "none":
        print(f"{c['effect']:18} gain {c['delta_vs_none']:+7.1f} +- {c['se_delta']:5.1f}, "
              f"of which from the speeds {c['delta_velocity_rows']:+6.1f}")
print("named:", belt.named_effect)

# %% [markdown]
# At full size (60 runout rows, 30 speeds) this seed names the belt. Over five
# unseen seeds the speeds raised the belt's detection from 2 of 5 to 4 of 5
# (docs/studies.md). At the notebook's small test size the verdict printed
# above may be `none`: 30 rows and 12 speeds are little data.
#
# The model with the belt is then calibrated on the runouts and the speeds
# together: the `calib.fit` command `discover` prints carries `--velocities`, and
# `run_fit(..., velocities=...)` is its library call. The belt's parameters
# against the truth:

# %%
with warnings.catch_warnings():  # counted in the calibration file instead
    warnings.simplefilter("ignore", UnfinishedBlocksWarning)
    belt_run = run_fit(data_b, os.path.join(work, "belt_fit"), profile=PROFILE_CSV,
                       models=("crsp",), rolling_resistance="profile",
                       effects=("vegetation_belt",), velocities=speeds_csv, quick=SMALL, seed=0)
belt_doc = belt_run.calibration.doc
print(f"fitted with {belt_doc['velocities']['n_observations']} passage speeds "
      f"(methods: {', '.join(belt_doc['methods'])})")
for name, true in belt_truth["parameters"].items():
    p = belt_doc["crsp"][name]
    print(f"{name:14} truth {true:8.3f}   fitted mean {p['mean']:8.3f}  "
          f"90 % [{p['q05']:.3f}, {p['q95']:.3f}]")

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
post_obs, post = run_discovery("data/postignano.csv", model="dem")
for line in post.where_before["flagged"] or [post.where_before["summary"]]:
    print("-", line)
for c in post.table:
    print(f"{c['effect']:18} score {c['score']:7.2f}  gain {c['delta_vs_none']:+6.2f}  "
          f"gap {c['gap']:6.1f} m")
print("named:", post.named_effect)

# %%
show(discovery_figures(post_obs, post, "dem")["before_after.png"])

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

# %% [markdown]
# ## 4. Closing the loop: the named effect in the calibration, the prediction and the hazard
#
# Naming an effect is only useful if the model that carries it is the one that is
# then calibrated, checked and run for the hazard. `calib.discover` ends its summary
# with the `python -m calib.fit ... --effect NAME` command that does that; here the
# same steps run through the library, on the site and hidden effect of section 1:
#
# 1. a fresh synthetic data set from the same truth (other blocks, other noise), a
#    third of its rows held back (`run_fit(..., holdout_fraction=...)`, one split for
#    both fits);
# 2. the baseline, and the baseline with the effects discovery named, each fitted on
#    the other two thirds (`run_fit(..., effects=...)`, which records the effects in
#    `calibration.json`);
# 3. each scored on the held-back rows (`validate_heldout`: CRPS against the rows'
#    climatology, coverage of the 90 % interval);
# 4. each run through the hazard (`run_hazard`: the effect is simulated because the
#    calibration file names it), against the truth's own exceedance: the hidden
#    model's blocks, simulated without observation noise.
#
# `scripts/hidden_effect_chain.py` runs the same chain on 180 rows per effect;
# `docs/studies.md` ("The loop closed on a known truth") holds its measured results.

# %%
named = tuple(result.named_effects)
if SMALL and not named:
    # at the tests' small size (30 rows) discovery may name nothing; the hidden
    # effect is then fitted instead, so that every step below still runs
    named = (truth["effect"],)
loop_csv = os.path.join(work, "loop.csv")
loop_obs, _ = synthesize_effect(slope, truth["effect"], truth["strength"],
                                45 if SMALL else 90, 22)
write(loop_csv, observations_csv_text(loop_obs, 22))
models = {"baseline": ()}  # label: effects; nothing named: the baseline is the final model
if named:
    models["baseline + " + ", ".join(named)] = named
fits = {}
for label, effects in models.items():
    out = os.path.join(work, "loop_effect" if effects else "loop_baseline")
    with warnings.catch_warnings():  # counted in the calibration file instead
        warnings.simplefilter("ignore", UnfinishedBlocksWarning)
        run_fit(loop_csv, out, profile=PROFILE_CSV, models=("crsp",),
                rolling_resistance="profile", effects=effects, quick=SMALL,
                holdout_fraction=1 / 3, seed=0)
    fits[label] = out, validate_heldout(out, "crsp", 0)[0][0]
for label, (out, val) in fits.items():
    print(f"{label:34} held-out CRPS {val['mean_crps_m']:5.1f} m (climatology "
          f"{val['mean_crps_climatology_m']:.1f} m, skill {val['skill_vs_climatology']:+.2f}), "
          f"90 % coverage {val['coverage_90']:.2f}")

# %% [markdown]
# **The hazard, with and without the effect.** Exceedance: the fraction of blocks
# released at the top that pass each station, posterior mean and 90 % band over the
# calibration's draws, against the truth's (`truth_exceedance`: the hidden model, no
# observation noise). `compare_exceedance` measures the distance over the stations
# that any of them reaches with probability above 0.005.

# %%
HAZARD_SIZES_M = [0.2, 1.0, 2.0]
ROAD_X_M = load_site(PROFILE_CSV).station_x_m  # the road (data/postignano_site.json)
stations = np.arange(0.0, float(slope.x_m[-1]) + 1.0, 10.0)
tables = {}
for label, (out, _) in fits.items():
    cal = load_calibration(os.path.join(out, "calibration.json"), "crsp")
    counts = run_hazard(cal, draw_parameters(cal, 4 if SMALL else 40, 0), slope,
                        HAZARD_SIZES_M, stations, 100 if SMALL else 2000, 0,
                        release_x_m=float(slope.x_m[0]))
    tables[label] = exceedance_table(counts)
truth_p = truth_exceedance(slope, truth["effect"], truth["strength"], HAZARD_SIZES_M,
                           stations, 200 if SMALL else 5000, 1)
close = compare_exceedance(tables, truth_p, HAZARD_SIZES_M, stations, ROAD_X_M)
fig, axes = plt.subplots(1, len(HAZARD_SIZES_M), figsize=(12, 3.6), sharey=True)
for s, (ax, size) in enumerate(zip(axes, HAZARD_SIZES_M)):
    ax.plot(stations, truth_p[s], "k-", lw=2, label="truth")
    for (label, exc), colour in zip(tables.items(), ("tab:red", "tab:blue")):
        g = exc[np.isclose(exc.block_size_m, size)].sort_values("x_m")
        ax.plot(g.x_m, g.p_exceed_mean, color=colour, label=label)
        ax.fill_between(g.x_m, g.p_exceed_q05, g.p_exceed_q95, color=colour, alpha=0.2)
        c = close[str(size)]
        if c[label]["mean_abs_error"] is not None:
            print(f"D = {size:g} m, {label:34} mean |P - P_truth| "
                  f"{c[label]['mean_abs_error']:.3f} over {c['n_stations']} stations, truth "
                  f"inside the 90 % band at {c[label]['truth_in_band']:.0%} of them")
    road = close[str(size)]["road"]
    print(f"D = {size:g} m at the road (x = {road['x_m']:g} m): truth {road['truth']:.3f}; "
          + "; ".join(f"{k} {road[k][0]:.3f} [{road[k][1]:.3f}, {road[k][2]:.3f}]"
                      for k in tables))
    ax.set_title(f"D = {size:g} m")
    ax.set_xlabel("x (m)")
axes[0].set_ylabel("P(block passes x)")
axes[0].legend(fontsize=8)
show(fig)

# %% [markdown]
# With the effect in the model, the exceedance curves should lie closer to the
# truth's, and the held-out CRPS should be lower than the baseline's. At the
# notebook's small test size (45 rows, the quick budgets, 100 blocks per draw) the
# numbers above are noisy and need not show it; the measured chains on 180 rows are in
# `docs/studies.md`.
