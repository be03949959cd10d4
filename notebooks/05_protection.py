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
# # Deciding on a protection barrier, with the calibration's uncertainty
#
# From a calibration (`python -m calib.fit`) to a barrier decision, through the
# library that `python -m calib.hazard` and `python -m calib.design` run:
#
# 1. **Postignano** (the seed paper's slope): the hazard of blocks of the design
#    size along the lower slope, the design after UNI 11211-4 (Peila & Ronco 2009)
#    at every position between the foot of the talus and the road, the position
#    and the kit chosen, the impact angle there, and the residual hazard at the
#    road with and without the barrier (a second run with the barrier element,
#    same seed and draws: common random numbers);
# 2. **Tschamut 2014** (the field campaign): the site's own rock density and the
#    three tracked blocks' masses turned into block sizes and the design block.
#
# Every design value is the library's (`calib.design.design_at`, a typed
# `Design`); the figures are the design sheet's. The kits are GENERIC energy
# classes (`data/barrier_kits.csv`), not products; the partial factors, their
# values and sources are printed below. 2D: the barrier's length and blocks
# passing round its ends are not modelled.
#
# Calibrations: `PROTECTION_CALIBRATION` (Postignano) and
# `PROTECTION_TSCHAMUT_CALIBRATION` name `calibration.json` files; without them
# the notebook runs a `--quick` CRSP fit of each site first (their diagnostics
# usually fail, and say so). Run so on 2 cores shared with one other job
# (2026-11-27): the fits took 5 and 13 minutes, the whole notebook 23.
# `PROTECTION_NOTEBOOK_SMALL=1` runs tiny Monte Carlo sizes (the tests);
# `PROTECTION_NOTEBOOK_OUT` is the output folder.

# %%
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from IPython.display import Image, display  # noqa: E402

from calib.design import (  # noqa: E402
    DesignOptions,
    best_position,
    design_at,
    design_block,
    design_record,
    distributions_figure,
    exceedance_figure,
    impact_angles,
    load_kits,
    posterior_warning,
    profile_figure,
    residual_exceedance,
    scan_figure,
    scan_rows,
)
from calib.files.hazard_results import write_hazard_results  # noqa: E402
from calib.files.site import load_site  # noqa: E402
from calib.hazard import (  # noqa: E402
    Barrier,
    calibration_record,
    default_release_x_m,
    draw_parameters,
    hazard_dataset,
    load_calibration,
    run_hazard,
)
from calib.model.entries import sphere_diameter_m  # noqa: E402
from solvers import load_profile  # noqa: E402

SMALL = os.environ.get("PROTECTION_NOTEBOOK_SMALL") == "1"
OUT = os.environ.get("PROTECTION_NOTEBOOK_OUT", "results/protection_notebook")
os.makedirs(OUT, exist_ok=True)
SEED = 0
N_POSTERIOR = 2 if SMALL else 100      # posterior draws
N_BLOCKS = 200 if SMALL else 20000     # blocks per draw and size, Postignano
N_BLOCKS_T = 200 if SMALL else 5000    # the same, Tschamut (179 profile segments: slower)
N_ANGLE = 100 if SMALL else 2000       # blocks per draw of the impact-angle run
STEP_M = 20.0 if SMALL else 5.0        # spacing of the scanned positions
KITS = load_kits("data/barrier_kits.csv")
# ILLUSTRATIVE, NOT DATA: blocks of the design size released per year (nothing in
# the paper gives a release frequency): it only sets the impacts per year and
# P(more than one SEL-level impact between yearly inspections).
RELEASE_RATE_PER_YEAR = 0.2


def calibration(env: str, data_csv: str, folder: str) -> str:
    """The calibration file named by ``env``, else a quick CRSP fit of ``data_csv``."""
    path = os.environ.get(env)
    if path:
        return path
    from calib.fit import run_fit

    return run_fit(data_csv, folder, models=("crsp",), quick=True, seed=1).calibration.path


def calibration_checks(record: dict) -> str:
    """The calibration's own predictive check and its posterior's diagnostics
    (R-hat, ESS, chains, mass at the bounds, the log-likelihood GP's realisations),
    as the hazard record holds them: a design on a posterior that failed says so
    loudly, as ``calib.design``'s sheet does."""
    check, post = record["adequacy_json"], record["posterior_check_json"]
    text = "the calibration's own predictive check: " + (
        "none recorded" if check is None else "passed" if check.get("ok")
        else f"FAILED ({check.get('message')})")
    if post is None:
        return text + "; no posterior diagnostics recorded"
    warning = posterior_warning(post)
    if warning is None:
        return text + "; its posterior passed its diagnostics"
    return (text + "\n" + warning + " (the 5-95 % bands and probabilities below may not "
            "represent the parameters' uncertainty)")


def show(fig, name: str) -> None:
    path = os.path.join(OUT, name)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    display(Image(path))


# %% [markdown]
# ## Postignano: the calibration and the site
#
# The road is the site file's station of interest
# (`data/postignano_site.json`); the foot of the talus is the profile vertex
# where the talus zone ends. The design block is the largest observed size,
# D = 2 m, a sphere of the site's density.

# %%
cal = load_calibration(calibration("PROTECTION_CALIBRATION", "data/postignano.csv",
                                   os.path.join(OUT, "postignano-fit")), "crsp")
profile = load_profile(cal.profile_csv)
site = load_site(cal.profile_csv)
zones = profile.segment_zone_names()
FOOT_M = float(profile.x_m[zones.index("talus") + 1])
ROAD_M = float(site.station_x_m)
SIZE_M = 2.0
print(f"{cal.path}: point estimate "
      + ", ".join(f"{n} = {v:.3g}" for n, v in zip(cal.names, cal.point, strict=True)))
print(f"{site.name}: {site.station_label} at x = {ROAD_M:g} m, foot of the talus at "
      f"x = {FOOT_M:g} m, rock density {site.rock_density_kg_m3:g} kg/m^3")

# %% [markdown]
# ## One hazard run for every candidate position
#
# `N_POSTERIOR` draws x `N_BLOCKS` blocks of D = 2 m; every station records the
# per-draw percentiles of speed, passing height and energy a design reads, so
# one run serves the whole scan.

# %%
draws = draw_parameters(cal, N_POSTERIOR, SEED)
positions = list(np.arange(FOOT_M, ROAD_M, STEP_M))
stations = np.union1d(np.arange(0.0, float(profile.x_m[-1]) + 1.0, 10.0),
                      positions + [ROAD_M])
record = calibration_record("notebooks/05_protection.py", SEED, cal, cal.path)
counts = run_hazard(cal, draws, profile, [SIZE_M], stations, N_BLOCKS, SEED)
ds = hazard_dataset(counts, profile, seed=SEED, road_x_m=ROAD_M,
                    road_label=site.station_label,
                    release_rate_per_year=RELEASE_RATE_PER_YEAR, record=record)
hazard_nc = os.path.join(OUT, "postignano_hazard.nc")
write_hazard_results(ds, hazard_nc)
print(f"{len(draws.values)} draw(s) from the {draws.source} x {N_BLOCKS} blocks; "
      + calibration_checks(record))

# %% [markdown]
# ## The design along the lower slope
#
# At each position: the characteristic speed and passing height (95th
# percentile of the passers, all draws pooled), the design values with the
# partial factors, and the smallest generic kit that passes every check. The
# chosen position is the one whose smallest passing kit has the least MEL
# (`best_position`, as `calib.design --scan-x-m` chooses).

# %%
block, notes = design_block(ds, hazard_nc, size_m=SIZE_M)
options = DesignOptions(kits=KITS)
scan = scan_rows(ds, block, positions, options)
print(pd.DataFrame(scan)[["x_m", "reach_prob_mean", "n_passers", "v_d_m_s", "E_sd_kJ",
                          "design_height_m", "kit"]].to_string(index=False))
X_M = best_position(scan)

# %% [markdown]
# ## The design at the chosen position

# %%
design = design_at(ds, X_M, block, options)
dv = design.values
show(scan_figure(scan, design.kits, options.energy_level), "postignano_scan.png")
print(f"barrier at x = {X_M:g} m, {design.protected_distance_m:g} m above the road; "
      f"P(reach) = {dv.reach_prob_mean:.3g} [5-95 %: {dv.reach_prob_band[0]:.3g}-"
      f"{dv.reach_prob_band[1]:.3g}], {dv.n_passers} passers")
for name, unit in (("E_sd_kJ", "kJ"), ("design_height_m", "m"), ("v_d_m_s", "m/s")):
    lo, hi = dv.bands[name]
    print(f"  {name} = {dv.design[name]:.4g} {unit} (5-95 % over draws {lo:.4g}-{hi:.4g})")
for name, m in dv.mc.items():
    need = m["blocks_per_draw_for_target"]
    print(f"  Monte Carlo error of {name}: {100 * m['rel_half_width']:.2g} % "
          + ("(2 % met)" if m["met"] else f"(2 % needs about {need} blocks per draw)"))
for f in options.factors.table():
    print(f"  {f['factor']} = {f['value']:g}: {f['source']}")
kit = design.chosen_kit
print(f"{design.chosen_by}: {kit.name if kit else 'none'}")
for name, s in design.unfactored.items():
    print(f"  {name} (no partial factors) = {s['mean']:.3g} [5-95 %: {s['q05']:.3g}-"
          f"{s['q95']:.3g}]")
for name, s in (design.impacts or {}).items():
    print(f"  {name} = {s['mean']:.3g} [5-95 %: {s['q05']:.3g}-{s['q95']:.3g}]")
for w in notes + design.warnings:
    print(w)

# %% [markdown]
# ## The impact angle
#
# The hazard results hold speeds, heights and energies, not directions: the
# angles come from the same draws and seed run with the barrier element (the
# crossing is recorded before the barrier acts).

# %%
angles = impact_angles(cal, draws.values, draws.names, profile, X_M, SIZE_M, N_ANGLE, SEED,
                       float(ds.attrs["release_x_m"]))
p, g = angles.percentiles(), angles.percentiles(to_ground=True)
print(f"{angles.angle_deg.size} crossings: below the horizontal p5/p50/p95 = "
      f"{p[5.0]:.3g}/{p[50.0]:.3g}/{p[95.0]:.3g} deg; to the ground (slope "
      f"{angles.ground_slope_deg:.3g} deg) {g[5.0]:.3g}/{g[50.0]:.3g}/{g[95.0]:.3g} deg")

# %% [markdown]
# ## The residual hazard at the road, with and without the barrier
#
# A second run of the same draws and seed with the chosen kit as the barrier
# element (height: its nominal height; capacity: its MEL): the blocks it does
# not touch are the same blocks as without it.

# %%
if kit is None:
    raise SystemExit("no kit of the catalogue passes: no barrier to simulate")
barrier = Barrier(X_M, kit.nominal_height_m, kit.mel_kJ)
with_barrier = hazard_dataset(
    run_hazard(cal, draws, profile, [SIZE_M], stations, N_BLOCKS, SEED, barrier=barrier),
    profile, seed=SEED, road_x_m=ROAD_M, road_label=site.station_label,
    release_rate_per_year=RELEASE_RATE_PER_YEAR, record=record)
table = residual_exceedance(ds, with_barrier)
at_road = table[np.isclose(table.x_m, ROAD_M)]
print(at_road[["block_size_m", "p_exceed_mean", "p_exceed_q95", "p_exceed_mean_with_barrier",
               "p_exceed_q95_with_barrier", "reach_prob_mean",
               "reach_prob_mean_with_barrier"]].to_string(index=False))

# %% [markdown]
# ## The design sheet's figures

# %%
sheet = design_record(ds, design, options, hazard_path=hazard_nc,
                      inputs={"hazard": hazard_nc, "kits": "data/barrier_kits.csv"},
                      with_barrier=with_barrier, impact_angle=angles.record())
show(profile_figure(ds, sheet), "postignano_profile.png")
show(distributions_figure(ds, sheet), "postignano_distributions.png")
show(exceedance_figure(table, sheet), "postignano_exceedance.png")

# %% [markdown]
# ## Tschamut 2014: the site's density and its blocks
#
# The site file gives the rock density (2650 kg/m^3, an assumption stated
# there: the data give none); the three tracked rocks' masses
# (`data/tschamut2014/blocks.csv`) are turned into volumes V = m / rho and block
# sizes, the volume-equivalent sphere's diameter (the toolkit's rule). The design
# block is the heaviest rock. No road exists at Tschamut: the protected line below
# is ILLUSTRATIVE, at the far end of the tracked stops; the barrier candidates lie
# on the flat runout zone, from the foot of the steep slope.

# %%
cal_t = load_calibration(calibration("PROTECTION_TSCHAMUT_CALIBRATION",
                                     "data/tschamut2014/observations.csv",
                                     os.path.join(OUT, "tschamut-fit")), "crsp")
profile_t = load_profile(cal_t.profile_csv)
site_t = load_site(cal_t.profile_csv)
rho = site_t.rock_density_kg_m3
blocks = pd.read_csv("data/tschamut2014/blocks.csv")
blocks["volume_m3"] = blocks.mass_kg / rho
blocks["block_size_m"] = sphere_diameter_m(blocks.mass_kg, rho)
print(f"{site_t.name}: rock density {rho:g} kg/m^3 ({site_t.density_source}); the "
      f"calibration was fitted at {cal_t.rock_density_kg_m3:g} kg/m^3")
print(blocks[["name", "mass_kg", "volume_m3", "block_size_m"]].to_string(index=False))
heaviest = blocks.loc[blocks.mass_kg.idxmax()]
PROTECTED_M = 150.0   # ILLUSTRATIVE protected line, m
zones_t = profile_t.segment_zone_names()
FOOT_T_M = float(profile_t.x_m[zones_t.index("flat")])
sizes_t = np.sort(blocks.block_size_m.to_numpy())
positions_t = list(np.arange(FOOT_T_M, PROTECTED_M, 2 * STEP_M))
stations_t = np.union1d(np.arange(0.0, float(profile_t.x_m[-1]), 10.0),
                        positions_t + [PROTECTED_M])
draws_t = draw_parameters(cal_t, N_POSTERIOR, SEED)
record_t = calibration_record("notebooks/05_protection.py", SEED, cal_t, cal_t.path)
ds_t = hazard_dataset(
    run_hazard(cal_t, draws_t, profile_t, sizes_t, stations_t, N_BLOCKS_T, SEED), profile_t,
    seed=SEED, road_x_m=PROTECTED_M, road_label="illustrative protected line",
    record=record_t)
print(f"{len(draws_t.values)} draw(s) from the {draws_t.source} x {N_BLOCKS_T} blocks; "
      + calibration_checks(record_t))
reach_foot = float(ds_t["n_reach"].sel(block_size_m=sizes_t[-1], x_m=FOOT_T_M).mean())
print(f"released at x = {default_release_x_m(cal_t, profile_t):g} m; P(reach) of the "
      f"heaviest block at {FOOT_T_M:g} m = {reach_foot / N_BLOCKS_T:.3g}")

# %%
hazard_t = os.path.join(OUT, "tschamut_hazard.nc")
write_hazard_results(ds_t, hazard_t)
block_t, notes_t = design_block(ds_t, hazard_t, size_m=float(sizes_t[-1]),
                                volume_m3=float(heaviest.volume_m3), density_kg_m3=rho)
scan_t = scan_rows(ds_t, block_t, positions_t, options)
X_T_M = best_position(scan_t)
design_t = design_at(ds_t, X_T_M, block_t, options)
dv_t = design_t.values
print(f"design block: {heaviest['name']}, {heaviest.mass_kg:g} kg, V = "
      f"{block_t.volume_m3:.4g} m^3, rho = {block_t.density_kg_m3:g} kg/m^3, D = "
      f"{block_t.size_m:.4g} m; barrier at x = {X_T_M:g} m")
for name, unit in (("E_sd_kJ", "kJ"), ("design_height_m", "m")):
    lo, hi = dv_t.bands[name]
    print(f"  {name} = {dv_t.design[name]:.4g} {unit} (5-95 % over draws {lo:.4g}-{hi:.4g})")
print(f"{design_t.chosen_by}: {design_t.chosen_kit.name if design_t.chosen_kit else 'none'}")
for name, s in design_t.unfactored.items():
    print(f"  {name} (no partial factors) = {s['mean']:.3g}")
for w in notes_t + design_t.warnings:
    print(w)
