"""Command line: ``python -m calib.validate results/calibration.json heldout.csv``.

Checks a calibration against runouts it was not fitted to: simulates the
posterior predictive runout distribution of every held-out row (its block size
and, where the CSV gives ``release_x_m``, its release point) and scores it
against the row and against a climatology baseline (the calibration rows' own
observed runouts). The scores and their sources are in
``calib.inference.predictive_check``.

Outputs (in ``--out``, all written together or not at all):

* ``validation.csv``: one row per held-out observation (predictive quantiles,
  PIT, 50/90 % coverage, error of the predictive mean, CRPS of the model and of
  both baselines; ``few_blocks`` where the quantiles rest on fewer than 20
  finished blocks, also named in a warning line);
* ``validation.json``: the averages, skill scores, settings and provenance
  (command line, seed, SHA-256 of every input, package versions), the
  release errors the blocks were drawn with (the calibration's
  ``release_height_sd_m``, ``release_speed_sd_m_s``) and ``stalled_rows``:
  rows of which at least half the predictive runouts end within 5 m of the
  release though the observed runout exceeds 20 m, with the slope below the
  release and the fraction of draws whose rolling-resistance angle exceeds
  it (``calib.inference.predictive_check.stalled_rows``), also printed;
* ``pit_histogram.png`` and ``intervals.png``.
"""

from __future__ import annotations

import json
import os
import sys

from solvers.cli import CliError, OneLineParser, run_guarded
from solvers.percentiles import few_blocks_warning

PROG = "python -m calib.validate"
SCHEMA = "rockfall-validation/1"

__all__ = ["SCHEMA", "command_argv", "main", "print_summary", "read_summary", "run_validation"]


def build_parser() -> OneLineParser:
    p = OneLineParser(
        prog=PROG, description=__doc__.split("\n\n")[1],
        epilog="Example: python -m calib.validate results/calibration.json heldout.csv "
               "--n-posterior 50 --out results/validation/")
    p.add_argument("calibration", help="calibration.json written by python -m calib.fit")
    p.add_argument("heldout", help="observations CSV of the held-out rows (same schema as "
                   "calib.fit's input; optional column release_x_m)")
    p.add_argument("--model", choices=("crsp", "dem"), default=None,
                   help="which calibrated model (default: crsp if calibrated, else dem)")
    p.add_argument("--calibration-data", default=None,
                   help="observations the calibration was fitted to, for the climatology "
                   "baseline (default: the data_csv recorded in the calibration file)")
    p.add_argument("--n-posterior", type=int, default=50,
                   help="posterior draws (default 50; 1 = the point estimate)")
    p.add_argument("--n-blocks", type=int, default=None,
                   help="blocks per draw and row group (default 100 CRSP, 4 DEM)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", default="results/validation", help="output folder "
                   "(default results/validation)")
    return p


def _load(args):
    from calib.files.calibration_file import CalibrationError, load_calibration
    from calib.files.inputs import InputError, own_profile
    from calib.files.observations import ObservationError, load_observations, on_command_profile
    from calib.files.site import SiteError, load_site
    from solvers.profile import ProfileError, load_profile

    try:
        cal = load_calibration(args.calibration, args.model)
    except CalibrationError as e:
        raise CliError(str(e)) from None
    data = args.calibration_data or cal.data_csv
    if data is None:
        raise CliError(f"{args.calibration}: the calibration data it records cannot be found; "
                       "give --calibration-data")
    try:
        heldout = load_observations(args.heldout)
        calib_obs = load_observations(data)
        profile = load_profile(cal.profile_csv)
        # rows on their own profiles (Observations.profile): read them now, so a
        # bad file is one line here
        heldout = on_command_profile(heldout, cal.profile_csv)
        for p in dict.fromkeys(heldout.profile):
            if p:
                own_profile(p)
        site = load_site(cal.profile_csv)
        cal.check_density(site.rock_density_kg_m3, f"the site file {site.path}"
                          if site.path else "the solvers' default")
    except (ObservationError, ProfileError, InputError, SiteError, CalibrationError) as e:
        raise CliError(str(e)) from None
    if args.n_posterior < 1:
        raise CliError(f"--n-posterior: expected a positive count, got {args.n_posterior}")
    if args.n_blocks is not None and args.n_blocks < 1:
        raise CliError(f"--n-blocks: expected a positive count, got {args.n_blocks}")
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise CliError(f"--out {args.out}: exists and is not a folder")
    return cal, heldout, calib_obs, data, profile


def command_argv(args) -> list[str]:
    """The arguments of this command that repeat the check of ``args`` (parsed
    options: from this command's parser, or built by ``calib.fit``'s held-out
    check, which runs it inside the fit), every option explicit: what its
    provenance records, so that the command it names runs."""
    argv = [args.calibration, args.heldout]
    for opt, value in (("--model", args.model), ("--calibration-data", args.calibration_data),
                       ("--n-posterior", args.n_posterior), ("--n-blocks", args.n_blocks),
                       ("--seed", args.seed), ("--out", args.out)):
        if value is not None:
            argv += [opt, str(value)]
    return argv


def run_validation(args) -> dict:
    """Run the check of ``args`` (parsed options) and write its outputs; returns
    the summary written to validation.json."""
    from calib.files.provenance import provenance
    from calib.inference.predictive_check import (
        heldout_entries,
        predictive_runouts,
        score_rows,
        stalled_rows,
    )
    from calib.model.forward import release_rolling_deg, release_slopes_deg
    from calib.plots.figures import validation_figures
    from solvers.cli import write_outputs

    cal, heldout, calib_obs, data, profile = _load(args)
    try:
        pooled, index, draws, n_blocks = predictive_runouts(
            cal, heldout, profile, args.n_posterior, args.n_blocks, args.seed)
    except ValueError as e:
        raise CliError(str(e)) from None
    try:
        check = score_rows(heldout, pooled, index, calib_obs, seed=args.seed)
    except ValueError as e:
        raise CliError(f"{data}: {e}") from None
    # rows that stall at their release, and why (the slope against phi_r)
    entries = heldout_entries(cal, heldout, profile)
    stalls = stalled_rows(heldout, pooled, index, entries.release_x_m,
                          release_slopes_deg(profile, entries.release_x_m, entries.profiles),
                          release_rolling_deg(draws.names, draws.values, profile, entries)
                          if cal.model == "crsp" else None)
    summary = {"schema": SCHEMA, "model": cal.model,
               "draws": draws.source, "n_draws": int(draws.values.shape[0]),
               "n_blocks_per_draw_and_group": int(n_blocks), **check.summary,
               "release_height_sd_m": cal.release_height_sd_m,
               "release_speed_sd_m_s": cal.release_speed_sd_m_s, "stalled_rows": stalls,
               "rolling_threshold_m_s": (cal.rolling_threshold_m_s if cal.model == "crsp"
                                         else None),
               "provenance": provenance(PROG, args.seed, {
                   "calibration": args.calibration, "heldout": args.heldout,
                   "calibration_data": data, "profile": cal.profile_csv},
                   command_argv(args))}
    figs = validation_figures(check)
    files = {"validation.csv": check.rows.to_csv(index=False, float_format="%.6g"),
             "validation.json": json.dumps(summary, indent=1, allow_nan=False) + "\n"}
    write_outputs(args.out, files, figs)
    return summary


def read_summary(path: str) -> dict:
    """The summary a check wrote (``validation.json``: the dict ``run_validation``
    returns), its schema checked.

    Raises:
        ValueError: the file does not parse or is not a ``SCHEMA`` summary.
    """
    try:
        with open(path) as fh:
            doc = json.load(fh)
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: cannot read a validation summary ({e})") from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        raise ValueError(f"{path}: key 'schema': expected {SCHEMA!r}")
    return doc


def print_summary(s: dict, out: str) -> None:
    from calib.inference.predictive_check import stall_message
    from solvers.crsp import ROLLING_THRESHOLD_M_S

    def f(v, fmt="{:.1f}"):
        return "-" if v is None else fmt.format(v)

    print(f"predictive check ({s['model']}, {s['draws']}: {s['n_draws']} draws x "
          f"{s['n_blocks_per_draw_and_group']} blocks per row group) on {s['n_scored']} "
          f"held-out point rows" + (f" (+{s['n_interval_rows']} interval rows, coverage only)"
                                    if s["n_interval_rows"] else ""))
    if s.get("release_height_sd_m") or s.get("release_speed_sd_m_s"):
        print(f"  release errors       each block's release height and speed drawn about the "
              f"rows' (sd {s['release_height_sd_m']:g} m, {s['release_speed_sd_m_s']:g} m/s, "
              "the calibration's)")
    if s.get("rolling_threshold_m_s") not in (None, ROLLING_THRESHOLD_M_S):
        print(f"  rolling threshold    {s['rolling_threshold_m_s']:g} m/s (the calibration's; "
              f"solver default {ROLLING_THRESHOLD_M_S:g})")
    print(f"  mean CRPS            {f(s['mean_crps_m'], '{:.2f}')} m")
    print(f"  climatology CRPS     {f(s['mean_crps_climatology_m'], '{:.2f}')} m (all "
          f"calibration rows), {f(s['mean_crps_climatology_size_m'], '{:.2f}')} m (per size)")
    print(f"  skill                {f(s['skill_vs_climatology'], '{:+.2f}')} vs climatology, "
          f"{f(s['skill_vs_climatology_size'], '{:+.2f}')} vs per-size climatology "
          "(1 perfect, 0 no better, < 0 worse)")
    print(f"  coverage             50 %: {f(s['coverage_50'], '{:.0%}')}, 90 %: "
          f"{f(s['coverage_90'], '{:.0%}')} ({s['n_above_90']} rows above the 90 % band, "
          f"{s['n_below_90']} below)")
    print(f"  error of the mean    {f(s['mean_error_of_mean_m'], '{:+.1f}')} m on average "
          f"(positive: overshoot), {f(s['mean_abs_error_of_mean_m'])} m in absolute value")
    few = few_blocks_warning([(f"row {r}", n) for r, n in s.get("few_blocks_rows", [])],
                             what="the predictive quantiles")
    if few:
        print(f"!!! {few}", file=sys.stderr)
    if s["n_without_prediction"]:
        print(f"!!! {s['n_without_prediction']} held-out rows have no finished simulated block "
              "and no score", file=sys.stderr)
    stall = stall_message(s["stalled_rows"]) if "stalled_rows" in s else None
    if stall:
        print(f"!!! {stall}", file=sys.stderr)
    if s["skill_vs_climatology"] is not None and s["skill_vs_climatology"] < 0:
        print("!!! the calibration predicts these rows WORSE than quoting the observed runout "
              "distribution", file=sys.stderr)
    print(f"wrote validation.csv, validation.json, pit_histogram.png, intervals.png to {out}")


def _main(args) -> int:
    s = run_validation(args)
    print_summary(s, args.out)
    return 0


def main(argv=None) -> int:
    return run_guarded(PROG, _main, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
