"""``python -m calib.power``: how often does the discrepancy workflow name a hidden
effect, as a function of its strength and of the number of observed blocks?

A power study. For every (effect, strength, rows, seed) it makes synthetic data
with the effect switched on (``calib.discovery.synthetic.synthesize_effect``, the same
data as ``calib.synth``), runs the whole workflow on it (``calib.discovery.discrepancy``,
the same fit and naming rule as ``calib.discover``) and records which effect
was named. Per cell (effect, strength, rows) it reports the detection rate
(for ``none``: the rate of correctly naming ``none``, i.e. one minus the
false-positive rate) with its exact (Clopper-Pearson) 90 % interval, what was
named instead, and the median gain of the true effect in nats and in standard
errors. It answers a planning question: how many mapped blocks does a survey
need before an effect of a given size can be told from the baseline?

Every finished run is written at once to ``OUT/runs/`` (one JSON file each);
a re-run with the same ``--out`` skips the runs already there, so a long study
can be stopped and resumed. The summary (``power.csv``, ``power.json``) is
written atomically at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from solvers.cli import CliError, OneLineParser, deprecated_alias, parse_floats, run_guarded

__all__ = ["main", "parse_seeds"]

PROG = "python -m calib.power"


def build_parser() -> argparse.ArgumentParser:
    from calib.synth import add_speed_options

    p = OneLineParser(
        prog=PROG, description=__doc__.split("\n\n")[0] + " Runs synth + discover over a "
        "grid and writes power.csv / power.json with detection rates and their exact 90 % "
        "intervals.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example (the Postignano slope shipped in data/; about 2.5 minutes per run on "
               "2 cores at the default budget):\n"
               "  python -m calib.power --profile data/postignano_profile.csv \\\n"
               "      --effects vegetation_belt --strengths 1,2 --n-obs 60,180 \\\n"
               "      --seeds 3001-3005 --out results/power/")
    p.add_argument("--effects", default="fragmentation,vegetation_belt",
                   help="comma-separated effects to hide in the data, 'none' for null data "
                        "(default fragmentation,vegetation_belt)")
    p.add_argument("--strengths", default="1", help="comma-separated strengths (default 1, "
                   "'moderate'; calib.model.effects says what they mean)")
    p.add_argument("--n-obs", default="60", help="comma-separated numbers of rows (default 60)")
    p.add_argument("--seeds", default="3001-3005",
                   help="data seeds: a list '1,2,3' or a range '3001-3005' (default 3001-3005)")
    p.add_argument("--profile", required=True,
                   help="slope profile CSV (x_m,z_m,zone; its materials CSV next to it), "
                        "e.g. data/postignano_profile.csv")
    p.add_argument("--sd-m", type=float, default=5.0,
                   help="measurement noise and stated tolerance of each row, m (default 5)")
    deprecated_alias(p, "--sd", "--sd-m")
    p.add_argument("--out", default=os.path.join("results", "power"),
                   help="output folder (default results/power/)")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of the fits (default 0)")
    p.add_argument("--quick", action="store_true", help="the workflow's small budget")
    p.add_argument("--n-blocks", type=int, default=None, metavar="N",
                   help="blocks per (design point, size class) in the fits (as calib.discover "
                        "--n-blocks; default 128, 32 with --quick)")
    add_speed_options(p, "also make passage speeds at these abscissae, m, and score them "
                         "(as calib.synth --velocity-stations-m and calib.discover "
                         "--velocities)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def parse_seeds(text: str) -> list[int]:
    """``"3001-3005"`` or ``"1,2,7"`` -> list of ints (a CliError names the problem)."""
    text = text.strip()
    try:
        if "-" in text and "," not in text:
            a, b = (int(t) for t in text.split("-", 1))
            if b < a:
                raise CliError(f"--seeds: range {text!r} ends before it starts")
            return list(range(a, b + 1))
        seeds = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise CliError(f"--seeds: expected a list '1,2,3' or a range '3001-3005', "
                       f"got {text!r}") from None
    if not seeds:
        raise CliError("--seeds: expected at least one seed")
    return seeds


def _write_json_atomic(path: str, obj) -> None:
    from solvers.cli import json_ready, write_text_atomic

    write_text_atomic(path, json.dumps(json_ready(obj), indent=1, allow_nan=False) + "\n")


def _run(args) -> int:
    import pandas as pd

    from calib.discovery.discrepancy import PRESETS, preset_budget
    from calib.discovery.power_study import detection_table, one_run
    from calib.model.effects import EFFECT_NAMES
    from calib.synth import speed_design
    from solvers.cli import write_csv_atomic
    from solvers.profile import load_profile

    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    bad = [e for e in effects if e not in EFFECT_NAMES]
    if bad or not effects:
        raise CliError(f"--effects: {', '.join(bad) or '(empty)'}: expected names among "
                       f"{', '.join(EFFECT_NAMES)}")
    strengths = parse_floats(args.strengths, "--strengths")
    if any(s <= 0 for s in strengths):
        raise CliError(f"--strengths: expected positive numbers, got {args.strengths!r}")
    n_list = parse_floats(args.n_obs, "--n-obs")
    if any(n < 1 or n != int(n) for n in n_list):
        raise CliError(f"--n-obs: expected whole numbers of at least 1, got {args.n_obs!r}")
    n_list = [int(n) for n in n_list]
    seeds = parse_seeds(args.seeds)
    if not (np.isfinite(args.sd_m) and args.sd_m > 0):
        raise CliError(f"--sd-m: expected a positive number of metres, got {args.sd_m:g}")
    try:
        profile = load_profile(args.profile)
    except (OSError, ValueError) as e:
        raise CliError(f"{args.profile}: {e}") from None
    budget_name = "crsp-quick" if args.quick else "crsp"
    try:
        budget = preset_budget("crsp", args.quick, args.n_blocks)
    except ValueError as e:
        raise CliError(f"--n-blocks: {e}") from None
    if budget.n_blocks != PRESETS[budget_name].n_blocks:
        budget_name += f"-b{budget.n_blocks}"
    speeds, speed_tag = speed_design(args, profile), ""
    if speeds is not None:
        speed_tag = (f"_v{speeds[1]}at{'+'.join(f'{x:g}' for x in speeds[0])}"
                     f"sd{args.velocity_sd_m_s:g}")
    grid = [(e, s if e != "none" else 1.0, n, k) for e in effects
            for s in (strengths if e != "none" else [1.0]) for n in n_list for k in seeds]
    grid = list(dict.fromkeys(grid))  # null data: strength does not apply
    runs_dir = os.path.join(args.out, "runs")
    bar = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=len(grid), desc="power study: runs", file=sys.stderr)
    runs = []
    for e, s, n, k in grid:
        path = os.path.join(runs_dir, f"{e}_s{s:g}_n{n}_seed{k}_fit{args.seed}_{budget_name}"
                                      f"_sd{args.sd_m:g}{speed_tag}.json")
        if os.path.exists(path):
            with open(path) as f:
                rec = json.load(f)
        else:
            rec = one_run(profile, e, s, n, k, args.sd_m, args.seed, budget, speeds)
            rec["budget"] = budget_name
            _write_json_atomic(path, rec)
        runs.append(rec)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{e} s{s:g} n{n} seed {k}: {rec['named']}")
        else:
            print(f"{e} strength {s:g} n {n} seed {k}: named {rec['named']}", flush=True)
    if bar is not None:
        bar.close()
    table = detection_table(runs)
    flat = pd.DataFrame([{**{k: v for k, v in c.items() if k not in ("named", "seeds")},
                          "named": "; ".join(f"{k} {v}" for k, v in c["named"].items())}
                         for c in table])
    write_csv_atomic(flat, os.path.join(args.out, "power.csv"))
    _write_json_atomic(os.path.join(args.out, "power.json"),
                       {"schema": "rockfall-power/1", "command": " ".join([PROG] + sys.argv[1:]),
                        "budget": budget_name, "profile_csv": args.profile,
                        "passage_speeds": None if speeds is None else {
                            "stations_m": speeds[0], "rows_per_run": speeds[1],
                            "sd_m_s": speeds[2]},
                        "decision_rule": "calib.discover's: gain > 4 nats and > 2 se",
                        "cells": table, "runs": runs})
    print(f"\n{'effect':18} {'strength':>8} {'rows':>5} {'named right':>12} "
          f"{'90 % interval':>14} {'median gain':>12} {'sim sd':>6}  named")
    for c in table:
        g = "-" if c["median_gain_nats"] is None else \
            f"{c['median_gain_nats']:+.1f} ({c['median_gain_se'] or 0:.1f} se)"
        sd = c["median_loglik_noise_sd_none_nats"]
        noise = "-" if sd is None else f"{sd:.1f}"
        print(f"{c['effect']:18} {c['strength']:8g} {c['n_obs']:5d} "
              f"{c['named_right']:>5d} of {c['runs']:<4d} "
              f"{c['rate_q05']:6.2f}-{c['rate_q95']:<6.2f} {g:>12} {noise:>6}  "
              + ", ".join(f"{k} {v}" for k, v in c["named"].items()))
    print("(sim sd: median Monte Carlo sd of the baseline's summed log-likelihood, nats)")
    print(f"wrote {os.path.join(args.out, 'power.csv')} and power.json")
    return 0


def main(argv=None) -> int:
    return run_guarded(PROG, _run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
