"""``python -m calib.discover DATA.csv``: find where the model disagrees with the data,
name the missing effects one at a time, add them and show the gap shrink.

Fits the baseline model and each candidate effect (``calib.model.effects``: for CRSP
size_dissipation, fragmentation, rolling_resistance, vegetation_belt; for the
DEM size_dissipation and fragmentation), locates the baseline's disagreement
(quantile residuals against block size and stop position), compares the
candidates by held-out log predictive density and names the best only when
its gain over the baseline exceeds 4 nats and z standard errors, z = 2 at the
first step (its false-positive rate measured on null data) and raised
Bonferroni-style for the m candidates a later step compares (2.53 for four;
else ``none``). CRSP then keeps going: the model with the named effect is the new
baseline, each remaining candidate is added to it and compared again, until a
step names none, no candidate is left or ``--max-steps`` steps ran (the
stopping rule and the multiple-testing control: ``STOPPING_RULE`` and
``MULTIPLE_TESTING`` of ``calib/discovery/discrepancy.py``, which has the
workflow and its sources). The summary ends with the ``python -m calib.fit``
command that calibrates the final model (``--effect`` per named effect).
``--velocities FILE`` adds passage speeds at stations
(``calib.files.observations.load_velocities``), scored with the runouts by every
candidate (CRSP only): runouts alone cannot tell a forest belt from a lower
tangential restitution, a speed measured above the belt can.

Writes into ``--out`` (atomically; nothing on error):

* ``discovery.json``: named_effect (the first step's), named_effects (every
  step's, in order), final_model, steps [{step, baseline, baseline_effects,
  n_compared, z, threshold_nats, named, best, gain_nats, se_nats, gap_before,
  gap_after, candidates}], stopping_rule, multiple_testing, refit_command (the
  calib.fit command of the final model; null where calib.fit cannot fit it),
  candidates (the first step's) [{effect, model, score, gap, ...,
  khat, khat_by_fold, khat_bar, n_fold_points, fresh_draw_folds,
  psis_flagged_folds}], gap_metric,
  gap_before, gap_after,
  where (the baseline's disagreement), each candidate's fit (with its
  unfinished blocks, ``calib.model.unfinished``, the Pareto k-hats of its
  importance weights, ``calib.inference.importance``, and the noise variance
  their smoothing assumed, ``smoothing_noise_var_nats2``), warnings, budgets, timings, seed;
* ``residuals.png`` (where the baseline fails), ``candidates.png`` (scores),
  ``before_after.png`` (the gap before and after).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
import warnings

import jax
import numpy as np

from calib.files.provenance import command_args, command_line, versions
from calib.model.dem_run import DEM_RUN, with_max_time
from solvers.cli import CliError, OneLineParser, Progress, json_ready, run_guarded, write_outputs

__all__ = ["main"]

PROG = "python -m calib.discover"


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=PROG, description=__doc__.split("\n\n")[0] + " Writes discovery.json "
        "(named_effect, named_effects, steps, candidates with score and gap, gap_before, "
        "gap_after, where the baseline fails, refit_command) and residuals.png, "
        "candidates.png, before_after.png; prints a summary ending with the calib.fit "
        "command of the final model. At each step the best candidate is named only when "
        "its held-out score gain over the step's baseline exceeds 4 nats and z standard "
        "errors: z = 2 at the first step, raised Bonferroni-style at later steps for the m "
        "candidates compared (2.28, 2.43, 2.53 for 2, 3, 4); otherwise 'none', and "
        "discovery stops.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Examples:\n  python -m calib.synth --effect fragmentation --seed 3 --out "
               "synth.csv\n  python -m calib.discover synth.csv --out results/discovery/\n"
               "  python -m calib.discover data/postignano.csv --model dem\n"
               "Observation CSV columns as for calib.fit (data/README.md).")
    p.add_argument("data", help="observed runouts CSV (schema of data/postignano.csv)")
    p.add_argument("--profile", default=None,
                   help="slope profile CSV (default: <data stem>_profile.csv next to DATA)")
    p.add_argument("--model", choices=["crsp", "dem"], default="crsp",
                   help="solver (default crsp, the fast one; dem: one alpha as baseline, "
                        "candidates alpha(L) and bonded fragments)")
    p.add_argument("--effects", default=None,
                   help="comma-separated candidate effects to try (default: all four for "
                        "crsp; size_dissipation for dem, whose fragmentation candidate costs "
                        "about 25 minutes on 2 cores: add it with --effects "
                        "size_dissipation,fragmentation)")
    p.add_argument("--out", default=os.path.join("results", "discovery"),
                   help="output folder (default results/discovery/)")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of the fits (default 0)")
    p.add_argument("--quick", action="store_true", help="small budgets (tests, a first look)")
    p.add_argument("--n-blocks", type=int, default=None, metavar="N",
                   help="blocks per (design point, size class) in the fits (default 128 for "
                        "crsp, 8 for dem; 32 / 4 with --quick; the dem fragmentation candidate "
                        "keeps its own 4). More blocks lower the simulation noise of the "
                        "likelihood (reported per candidate) roughly as 1/sqrt(N), at "
                        "proportional cost, and sharpen the posterior the design must cover")
    p.add_argument("--design-scale", type=float, default=1.0, metavar="X",
                   help="crsp: multiply the points of each candidate's design (Sobol, warm "
                        "and adaptive stages; default 1: 384 for the baseline, 512 with an "
                        "effect; at most 8). More points sharpen each fit's posterior and "
                        "its log-likelihood GP, at two to four times the time; the folds the "
                        "design's weights cannot score are scored on fresh draws at any "
                        "scale (docs/discovery.md)")
    p.add_argument("--velocities", default=None, metavar="FILE",
                   help="passage speeds at stations, CSV with columns station_x_m, "
                        "block_size_m, velocity_m_s, velocity_sd_m_s[, source] (e.g. from "
                        "video of induced rockfalls; calib.synth --velocity-stations-m writes "
                        "one); scored with the runouts by every candidate; crsp only")
    p.add_argument("--rolling-resistance", choices=["profile", "fit"], default="profile",
                   help="CRSP baseline: keep the profile's per-zone rolling resistance and fit "
                        "Kn, Kt, S (default; the synthetic studies' base), or fit the "
                        "rolling resistance angle too, as calib.fit does by default (then "
                        "the rolling_resistance candidate is part of the baseline and is "
                        "left out)")
    p.add_argument("--release-tolerance-m", type=float, default=1.0,
                   help="where the rows give release_x_m, each row is simulated from its own "
                        "point, as calib.fit does: rows of one size class whose releases "
                        "(release_x_m, and release_height_m for CRSP) lie within this distance "
                        "share one simulated release (their mean); 0 "
                        "simulates every distinct release (slower). Rows without "
                        "release_x_m start at the profile's first vertex (default 1.0 m)")
    p.add_argument("--max-steps", type=int, default=None, metavar="K",
                   help="crsp: at most K steps (default: until a step names none or no "
                        "candidate is left, i.e. at most the number of candidates); 1 = the "
                        "single comparison with the plain baseline. dem: always 1 step (its "
                        "candidates are separate laws and cannot be combined)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def refit_command(args, named: tuple[str, ...]) -> str | None:
    """The ``python -m calib.fit`` command that calibrates the model discovery
    ended with (the baseline plus the ``named`` effects) on the same data,
    profile, release grouping and seed and, for CRSP, rolling-resistance
    baseline and passage speeds, every option explicit (``calib.fit.fit_argv``, the one
    builder of that command's arguments); None where calib.fit cannot fit it
    (the DEM's bonded fragments)."""
    from calib.fit import fit_argv

    if args.model == "crsp":
        model = dict(models=("crsp",), rolling_resistance=args.rolling_resistance,
                     effects=tuple(named), velocities=args.velocities)
    elif "fragmentation" in named:
        return None
    else:  # the DEM's size dependence is its power law
        model = dict(models=("dem",),
                     alpha_law="power" if "size_dissipation" in named else "constant")
    return shlex.join(["python", "-m", "calib.fit", *fit_argv(
        args.data, None, profile=args.profile, release_tolerance_m=args.release_tolerance_m,
        seed=args.seed, **model)])


def _fit_section(f) -> dict:
    return {"parameters": list(f.names),
            "estimate": dict(zip(f.names, map(float, f.estimate))),
            "q05": dict(zip(f.names, map(float, f.q05))),
            "q95": dict(zip(f.names, map(float, f.q95))),
            "best_design_point": dict(zip(f.names, map(float, f.best))),
            "ess": f.ess, "n_design": f.n_simulated,
            "n_fold_points": f.n_fold_points, "khat_bar": f.khat_bar,
            "fresh_draw_folds": list(f.fresh_draw_folds),
            "khat": f.khat, "khat_by_fold": [float(k) for k in f.khat_folds],
            "loglik_noise_sd_nats": f.loglik_noise_sd_nats,
            "smoothing_noise_var_nats2": f.smoothing_noise_var_nats2,
            "grid_emulator": f.grid_emulator,
            "unfinished_blocks": f.unfinished,
            "gap_by_size_class_m": [None if not np.isfinite(g) else float(g)
                                    for g in f.gap_by_class]}


def _run(args) -> int:
    """The command: check the inputs, run the stepwise discovery, write
    discovery.json and the figures (atomically) and print the summary."""
    from calib.discovery.discrepancy import discover
    from calib.inference.budget import has_scalable_design
    from calib.model.unfinished import UnfinishedBlocksWarning
    from calib.plots import discovery_figures as figs

    t0 = time.perf_counter()
    inputs, velocities, cands, combine, budget = _checked_inputs(args)
    bar = Progress(not args.no_progress, args.model.upper())
    with warnings.catch_warnings():  # reported in the summary and discovery.json
        warnings.simplefilter("ignore", UnfinishedBlocksWarning)
        d = discover(cands, inputs.obs, inputs.profile, jax.random.key(args.seed), budget, bar,
                     velocities, args.release_tolerance_m, inputs.release_errors,
                     combine=combine, max_steps=args.max_steps)
    bar.close()
    result = _result(args, inputs, velocities, combine, budget, d, t0)
    result["warnings"] = _run_warnings(
        d, budget, inputs.obs, velocities,
        args.design_scale if has_scalable_design(budget) else None)
    out_figs = figs.discovery_figures(inputs.obs, d, args.model)
    text = json.dumps(json_ready(result), indent=1, allow_nan=False) + "\n"
    write_outputs(args.out, {"discovery.json": text}, out_figs)
    _print_summary(result, args.out)
    return 0


def _checked_inputs(args):
    """The run's inputs, every one checked before any fit starts: (inputs,
    velocities or None, candidates, combine, budget); a bad one is a CliError."""
    from calib.discovery.candidates import candidate_set
    from calib.files.inputs import InputError, load_inputs
    from calib.inference.budget import discovery_budget, scaled_design

    if args.velocities is not None and args.model != "crsp":
        raise CliError("--velocities: passage speeds are scored with the crsp model only")
    try:
        inputs = load_inputs(args.data, args.profile, args.out, args.velocities)
    except InputError as e:
        raise CliError(str(e)) from None
    velocities = inputs.speeds
    if not args.release_tolerance_m >= 0:
        raise CliError(f"--release-tolerance-m must be >= 0, got {args.release_tolerance_m:g}")
    try:
        cands, combine = candidate_set(args.model, args.effects, inputs.profile,
                                       args.rolling_resistance,
                                       inputs.site.rolling_threshold_m_s, _dem_run(inputs.site))
    except ValueError as e:
        raise CliError(str(e)) from None
    if args.max_steps is not None and args.max_steps < 1:
        raise CliError(f"--max-steps: expected at least 1, got {args.max_steps}")
    try:
        budget = discovery_budget(args.model, args.quick, args.n_blocks)
    except ValueError as e:
        raise CliError(f"--n-blocks: {e}") from None
    if args.design_scale != 1.0:
        try:
            budget = scaled_design(budget, args.design_scale)
        except ValueError as e:
            raise CliError(f"--design-scale: {e}") from None
    return inputs, velocities, cands, combine, budget


def _dem_run(site):
    """The DEM numerics of the site's candidates: the site file's simulated time
    (``calib.files.site``), or None for the toolkit's ``DEM_RUN``."""
    if site.dem_max_time_s is None:
        return None
    return with_max_time(site.dem_max_time_s, f"{site.path}: key 'dem_max_time_s'")


def _result(args, inputs, velocities, combine, budget, d, t0: float) -> dict:
    """discovery.json without its warnings: the run's settings and inputs, the
    steps and their verdicts, the first step's candidates, the gap before and
    after, where the baseline fails, each fit, the budget and the timings."""
    from calib.discovery.candidate_fit import GAP_METRIC
    from calib.discovery.discrepancy import MULTIPLE_TESTING, STOPPING_RULE
    from calib.discovery.scores import ELPD_MIN, Z_MIN

    obs = inputs.obs
    return {
        "schema": "rockfall-discovery/1",
        "command": command_line(PROG),
        "data_csv": args.data, "profile_csv": inputs.profile_path, "model": args.model,
        "seed": args.seed, "quick": bool(args.quick), "n_observations": obs.n_obs,
        "rolling_resistance": args.rolling_resistance if args.model == "crsp" else None,
        "release_groups": _release_record(d.entries, obs.n_obs, args.release_tolerance_m),
        "release_height_sd_m": inputs.site.release_height_sd_m,
        "release_speed_sd_m_s": inputs.site.release_speed_sd_m_s,
        "rolling_threshold_m_s": (inputs.site.rolling_threshold_m_s if args.model == "crsp"
                                  else None),
        "dem_max_time_s": ((inputs.site.dem_max_time_s or DEM_RUN.max_time_s)
                           if args.model == "dem" else None),
        "velocities_csv": args.velocities,
        "n_velocity_observations": 0 if velocities is None else velocities.n_obs,
        "velocity_stations_m": ([] if velocities is None
                                else [float(x) for x in velocities.stations_m]),
        "named_effect": d.named_effect,
        "named_effects": list(d.named_effects),
        "final_model": d.final_model,
        "refit_command": refit_command(args, d.named_effects),
        "decision_rule": f"at each step, name the candidate with the largest held-out score "
                         f"gain over the step's baseline if the gain exceeds {ELPD_MIN:g} nats "
                         f"and z standard errors (z = {Z_MIN:g} at step 1; later steps raised "
                         f"Bonferroni-style for the m candidates compared: steps[].z); "
                         f"otherwise 'none'",
        "stopping_rule": STOPPING_RULE if combine is not None else
        "one step: the DEM's candidates cannot be combined",
        "multiple_testing": MULTIPLE_TESTING,
        "max_steps": args.max_steps,
        "steps": d.steps,
        "score": f"{budget.k_folds}-fold (leave-one-out below {budget.k_folds} rows) held-out "
                 f"log predictive density, summed over rows (higher is better)",
        "candidates": d.table,
        "gap_metric": GAP_METRIC,
        "gap_before": d.gap_before, "gap_after": d.gap_after,
        "gap_ratio": d.gap_after / d.gap_before if d.gap_before > 0 else None,
        "size_classes_m": [float(s) for s in d.class_sizes_m],
        "where": d.where_before,
        "where_after": d.where_after,
        "fits": {e: _fit_section(f) for e, f in d.fits.items()},
        "budget": {k: (list(v) if isinstance(v, tuple) else v)
                   for k, v in vars(budget).items()},
        "timings_s": {**d.timings_s, "total_s": time.perf_counter() - t0},
        "versions": versions(),
    }


def _run_warnings(d, budget, obs, velocities, design_scale: float | None = 1.0) -> list[str]:
    """The run's warnings, in the order discovery.json lists them: the first step's
    (ESS, PSIS, simulation noise, gap, concentration), each later step's with its
    own candidates (prefixed with the step), what fixed grids leave out, then the
    fits' unfinished blocks;
    ``design_scale``, the run's ``--design-scale`` (None for the DEM's fixed
    grids), sets the rerun they suggest."""
    from calib.discovery.discovery_warnings import (
        concentration_warnings,
        ess_warnings,
        gap_warnings,
        grid_warnings,
        noise_warnings,
        psis_warnings,
    )

    speed_sizes = None if velocities is None else velocities.block_size_m
    later = []  # a later step's warnings: its own candidates, prefixed with the step
    for s in d.steps[1:]:
        ws = (psis_warnings([r for r in s["candidates"] if r["effect"] != "none"],
                            design_scale)
              + noise_warnings(s["candidates"], budget.n_blocks, s["n_compared"])
              + concentration_warnings(s["candidates"], obs.block_size_m, speed_sizes,
                                       s["n_compared"]))
        later += [f"step {s['step']}: {w}" for w in ws]
    return (ess_warnings({e: (f.ess, int(f.theta.shape[0])) for e, f in d.fits.items()},
                         design_scale=design_scale)
            + psis_warnings(d.table, design_scale)
            + noise_warnings(d.table, budget.n_blocks, d.steps[0]["n_compared"])
            + gap_warnings(d.final_model, d.gap_before, d.gap_after)
            + concentration_warnings(d.table, obs.block_size_m, speed_sizes,
                                     d.steps[0]["n_compared"])
            + later
            + grid_warnings({e: f.grid_emulator for e, f in d.fits.items()})
            + [f.unfinished["warning"] for f in d.fits.values()
               if f.unfinished and f.unfinished["warning"]])


def _release_record(entries, n_runout_rows: int, tol_m: float) -> dict | None:
    """Where the candidates released the blocks: None (every block at the
    profile's first vertex) or the simulated (size class, release) groups."""
    if entries is None:
        return None
    return {"tolerance_m": tol_m,
            "groups": [{"block_size_m": float(d), "release_x_m": float(x),
                        "release_speed_m_s": None if not np.isfinite(v) else float(v),
                        "release_height_m": None if not np.isfinite(h) else float(h),
                        "profile_csv": pf or None,
                        "n_runout_rows": int(np.sum(entries.index[:n_runout_rows] == g))}
                       for g, (d, x, v, h, pf) in enumerate(zip(
                           entries.sizes_m, entries.release_x_m, entries.release_speed_m_s,
                           entries.release_height_m, entries.profile_csv))]}


def _print_summary(r: dict, out: str) -> None:
    groups = r["release_groups"]
    if groups is not None:
        print(f"each row simulated from its own release: {len(groups['groups'])} simulated "
              f"(size class, release) groups, rows within {groups['tolerance_m']:g} m "
              f"grouped (discovery.json: release_groups)")
    print(f"where the baseline ({r['model']}) disagrees with the {r['n_observations']} rows:")
    flagged = r["where"]["flagged"]
    for line in flagged[:6] or [r["where"]["summary"]]:
        print(f"  - {line}")
    if len(flagged) > 6:
        print(f"  ... and {len(flagged) - 6} more (discovery.json: where)")
    if r["n_velocity_observations"]:
        print(f"  (and {r['n_velocity_observations']} passage speeds at "
              f"{', '.join(f'{x:g}' for x in r['velocity_stations_m'])} m, scored with them)")
    for st in r["steps"]:
        _print_step(st, r["n_velocity_observations"], len(r["steps"]) > 1)
    print(f"\nnamed effect: {r['named_effect']}")
    if len(r["steps"]) > 1 or r["named_effects"]:
        print(f"named effects, in order: {', '.join(r['named_effects']) or 'none'} "
              f"(final model: {r['final_model']})")
    if r["named_effects"]:
        f = r["fits"][r["final_model"]]
        est = ", ".join(f"{n} {f['estimate'][n]:.3g} [{f['q05'][n]:.3g}, {f['q95'][n]:.3g}]"
                        for n in f["parameters"])
        print(f"fit with {'it' if len(r['named_effects']) == 1 else 'them'} "
              f"(mean [90 %]): {est}")
    print(f"stopping rule: {r['stopping_rule']}")
    print(f"multiple testing: {r['multiple_testing']}")
    for w in r["warnings"]:
        print(f"warning: {w}")
    print(f"gap (mean CRPS per size class): before {r['gap_before']:.2f} m, after "
          f"{r['gap_after']:.2f} m (x{r['gap_after'] / r['gap_before']:.2f})")
    if r["refit_command"]:
        print(f"calibrate the final model: {r['refit_command']}")
    else:
        print("calib.fit cannot fit the final model (the DEM's bonded fragments are a "
              "discovery candidate only)")
    print(f"total {r['timings_s']['total_s']:.0f} s; wrote {os.path.join(out, 'discovery.json')} "
          f"and figures in {out}/")


def _print_step(st: dict, n_velocity: int, several: bool) -> None:
    """One step's table of candidates and its verdict."""
    if several:
        print(f"\nstep {st['step']}: against {st['baseline']} ({st['n_compared']} candidate"
              f"{'s' if st['n_compared'] > 1 else ''}; named if the gain exceeds 4 nats and "
              f"{st['z']:.2f} se)")
    print(f"{'' if several else chr(10)}{'candidate':20} {'score':>9} {'gain':>8} {'± se':>6} "
          f"{'gap m':>7} {'sim sd':>7} {'k-hat':>7}")
    rows = st["candidates"]
    noise = [c.get("loglik_noise_sd_nats") for c in rows]
    noise = ["-" if v is None or not np.isfinite(v) else f"{v:.1f}" for v in noise]
    for c, sim in zip(rows, noise):
        se = "-" if c["effect"] == "none" or c["se_delta"] is None else f"{c['se_delta']:.1f}"
        name = c["effect"] if st["step"] == 1 or c["effect"] != "none" else "(baseline)"
        print(f"{name:20} {c['score']:9.1f} {c['delta_vs_none']:+8.1f} {se:>6} "
              f"{c['gap']:7.2f} {sim:>7} {_worst_fold(c):>7}")
    if st["step"] == 1:
        if set(noise) != {"-"}:
            print("(sim sd: Monte Carlo sd of the summed log-likelihood, nats, over "
                  "independent block sets)")
        print("(k-hat: the largest Pareto k-hat of the folds' importance weights; ! marks one "
              "above the bar min(0.7, 1 - 1/log10 S), an unreliable held-out score)")
    fresh = "; ".join(f"{c['effect']} {_folds_text(c['fresh_draw_folds'])}" for c in rows
                      if c.get("fresh_draw_folds"))
    if fresh:
        print(f"(scored on fresh draws of their training posterior, the design's weights "
              f"being above the bar: {fresh}; their k-hat is that of the draws' weights)")
    if n_velocity:
        parts = ", ".join(f"{c['effect']} {c['delta_velocity_rows']:+.1f}"
                          for c in rows if c["effect"] != "none")
        print(f"(of the gains, from the passage speeds: {parts})")
    if several:
        se = "-" if st["se_nats"] is None else f"{st['se_nats']:.1f}"
        gain = "" if st["gain_nats"] is None else (
            f": {st['best']} gains {st['gain_nats']:+.1f} ± {se} nats against a bar of "
            f"{st['threshold_nats']:.1f}")
        print(f"step {st['step']} names {st['named']}{gain}; gap {st['gap_before']:.2f} -> "
              f"{st['gap_after']:.2f} m")


def _folds_text(folds: list) -> str:
    return ("fold " if len(folds) == 1 else "folds ") + ", ".join(map(str, folds))


def _worst_fold(c: dict) -> str:
    """The largest fold k-hat of a candidate row ('-': none estimated), with '!'
    when some fold is flagged."""
    ks = np.array([np.nan if k is None else k for k in c.get("khat_by_fold") or []], float)
    ks = ks[~np.isnan(ks)]
    if not ks.size:
        return "-"
    return f"{ks.max():.2f}" + ("!" if c.get("psis_flagged_folds") else "")


def main(argv=None) -> int:
    with command_args(argv):
        return run_guarded(PROG, _run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
