"""``python -m calib.power``: how often does the discrepancy workflow name a hidden
effect, as a function of its strength and of the number of observed blocks?

A power study. For every (effect, strength, rows, seed) it makes synthetic data
with the effect switched on (``calib.discovery.synthetic.synthesize_effect``, the same
data as ``calib.synth``), runs the whole workflow on it (``calib.discovery.discrepancy``,
the same fit and naming rule as ``calib.discover``) and records which effect
was named. Per cell (effect, strength, rows) it reports the detection rate
(for ``none``: the rate of correctly naming ``none``, i.e. one minus the
false-positive rate) with its exact (Clopper-Pearson) 90 % interval, what was
named instead, the median gain of the true effect in nats and in standard
errors, and how many of the first step's held-out folds have importance
weights the workflow flags (Pareto k-hat above its bar) and in how many runs:
a verdict from such a run rests in part on scores ``calib.discover`` calls
unreliable, and ``named_right_unwarned`` in ``power.json`` counts the right
verdicts of the other runs (``folds_fresh_draws`` there: the folds the
design could not weight, scored on fresh draws of their training posterior
instead). It answers a planning question: how many mapped
blocks does a survey need before an effect of a given size can be told from
the baseline?

Every finished run is written at once to ``OUT/runs/`` (one JSON file each);
a re-run with the same ``--out`` skips the runs already there, so a long study
can be stopped and resumed. The summary (``power.csv``, ``power.json``) is
written atomically at the end.

The runs are independent (each a pure function of its effect, strength, rows
and seeds: ``calib.discovery.power_study.one_run``), so they are dispatched
(``solvers.dispatch``): by default to a local Dask cluster of ``--workers``
processes, one per core; to a Dask scheduler elsewhere with ``--scheduler
tcp://host:port``; in this process with ``--serial`` or one worker. Every way
gives the same records. Dask distributed rather than Ray: pure-Python wheels,
a local cluster of processes by default and a remote scheduler with the same
code, and futures with ``as_completed`` are all a few dozen independent runs
need (``solvers.dispatch`` says more, and how the workers share the cores).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from calib.files.provenance import command_args, command_line
from solvers.cli import (
    CliError,
    OneLineParser,
    deprecated_alias,
    parse_floats,
    run_guarded,
    write_text_atomic,
)

__all__ = ["main", "parse_seeds"]

PROG = "python -m calib.power"


def build_parser() -> argparse.ArgumentParser:
    from calib.synth import add_speed_options

    p = OneLineParser(
        prog=PROG, description=__doc__.split("\n\n")[0] + " Runs synth + discover over a "
        "grid and writes power.csv / power.json with detection rates and their exact 90 % "
        "intervals.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example (the Postignano slope shipped in data/; about 3-5 minutes per run on "
               "2 cores at the default budget):\n"
               "  python -m calib.power --profile data/postignano_profile.csv \\\n"
               "      --effects vegetation_belt --strengths 1,2 --n-obs 60,180 \\\n"
               "      --seeds 3001-3005 --out results/power/\n"
               "The same study on a Dask cluster (docs/distributed.md): add "
               "--scheduler tcp://HOST:8786")
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
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="processes of the local Dask cluster that runs the study, one thread "
                        "and an equal share of the cores each (default: the number of cores "
                        "this process may use, 1 on an accelerator; 1 runs in this process)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run on the Dask cluster whose scheduler is at ADDRESS "
                        "(tcp://host:port), started with 'dask scheduler' and 'dask worker' "
                        "where this project is installed (docs/distributed.md); default: a "
                        "local cluster")
    p.add_argument("--serial", action="store_true",
                   help="run one run after the other in this process (same results)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bar: one line per finished run")
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
    from solvers.cli import json_ready

    write_text_atomic(path, json.dumps(json_ready(obj), indent=1, allow_nan=False) + "\n")


def _error_path(run_path: str) -> str:
    """Where a failed run's traceback goes, beside where its record would."""
    return os.path.splitext(run_path)[0] + ".error.txt"


def _save_run(path: str, rec: dict) -> None:
    """A finished run's record; the traceback of an earlier failed try goes."""
    _write_json_atomic(path, rec)
    if os.path.exists(_error_path(path)):
        os.remove(_error_path(path))


def _grid(args) -> list[tuple]:
    """The checked (effect, strength, rows, seed) of every run (null data: one
    strength, as strength does not apply)."""
    from calib.model.effects import EFFECT_NAMES

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
    seeds = parse_seeds(args.seeds)
    grid = [(e, s if e != "none" else 1.0, int(n), k) for e in effects
            for s in (strengths if e != "none" else [1.0]) for n in n_list for k in seeds]
    return list(dict.fromkeys(grid))


def _where(args) -> dict:
    """``solvers.dispatch.run_tasks``'s scheduler, workers and serial from the options."""
    from solvers.dispatch import local_workers

    if args.scheduler is not None:
        if args.serial or args.workers is not None:
            raise CliError("--scheduler: the cluster has its own workers; give it without "
                           "--workers and --serial")
        if not args.scheduler.strip():
            raise CliError("--scheduler: expected an address such as tcp://host:8786")
    if args.workers is not None and args.workers < 1:
        raise CliError(f"--workers: expected a whole number of at least 1, got {args.workers}")
    return {"scheduler": args.scheduler, "serial": args.serial,
            "workers": args.workers or local_workers()}


def _run(args) -> int:
    from calib.discovery.power_study import one_run
    from calib.inference.budget import DISCOVERY_PRESETS, discovery_budget
    from calib.synth import speed_design
    from solvers.dispatch import ClusterUnreachable, RunFailed, Task, run_tasks
    from solvers.profile import load_profile

    grid, where = _grid(args), _where(args)
    if not (np.isfinite(args.sd_m) and args.sd_m > 0):
        raise CliError(f"--sd-m: expected a positive number of metres, got {args.sd_m:g}")
    try:
        profile = load_profile(args.profile)
    except (OSError, ValueError) as e:
        raise CliError(f"{args.profile}: {e}") from None
    budget_name = "crsp-quick" if args.quick else "crsp"
    try:
        budget = discovery_budget("crsp", args.quick, args.n_blocks)
    except ValueError as e:
        raise CliError(f"--n-blocks: {e}") from None
    if budget.n_blocks != DISCOVERY_PRESETS[budget_name].n_blocks:
        budget_name += f"-b{budget.n_blocks}"
    speeds, speed_tag = speed_design(args, profile), ""
    if speeds is not None:
        speed_tag = (f"_v{speeds[1]}at{'+'.join(f'{x:g}' for x in speeds[0])}"
                     f"sd{args.velocity_sd_m_s:g}")
    runs_dir = os.path.join(args.out, "runs")
    tasks = [Task(name=f"{e} strength {s:g} n {n} seed {k}",
                  path=os.path.join(runs_dir, f"{e}_s{s:g}_n{n}_seed{k}_fit{args.seed}_"
                                              f"{budget_name}_sd{args.sd_m:g}{speed_tag}.json"),
                  fn=one_run, args=(profile, e, s, n, k, args.sd_m, args.seed, budget, speeds,
                                    budget_name))
             for e, s, n, k in grid]
    try:
        runs = run_tasks(tasks, _save_run, **where, progress=not args.no_progress,
                         label="power study: runs", describe=lambda r: f"named {r['named']}")
    except RunFailed as e:
        for task, _, text in e.failures:
            write_text_atomic(_error_path(task.path), f"run {task.name}\n{text}")
        sys.stderr.write(f"{PROG}: error: {e}; traceback in "
                         f"{_error_path(e.failures[0][0].path)}; the finished runs are saved "
                         f"and a re-run resumes from them\n")
        return 1
    except ClusterUnreachable as e:
        raise CliError(f"--scheduler: {e}") from None
    except KeyboardInterrupt:
        raise CliError(f"interrupted; the finished runs are saved in {runs_dir} and a re-run "
                       f"resumes from them") from None
    _summarise(args, runs, budget_name, speeds)
    return 0


def _summarise(args, runs: list[dict], budget_name: str, speeds) -> None:
    """Write power.csv and power.json and print the detection table."""
    import pandas as pd

    from calib.discovery.power_study import detection_table
    from solvers.cli import write_csv_atomic

    table = detection_table(runs)
    flat = pd.DataFrame([{**{k: v for k, v in c.items() if k not in ("named", "seeds")},
                          "named": "; ".join(f"{k} {v}" for k, v in c["named"].items())}
                         for c in table])
    write_csv_atomic(flat, os.path.join(args.out, "power.csv"))
    _write_json_atomic(os.path.join(args.out, "power.json"),
                       {"schema": "rockfall-power/1", "command": command_line(PROG),
                        "budget": budget_name, "profile_csv": args.profile,
                        "passage_speeds": None if speeds is None else {
                            "stations_m": speeds[0], "rows_per_run": speeds[1],
                            "sd_m_s": speeds[2]},
                        "decision_rule": "calib.discover's: gain > 4 nats and > 2 se",
                        "cells": table, "runs": runs})
    print(f"\n{'effect':18} {'strength':>8} {'rows':>5} {'named right':>12} "
          f"{'90 % interval':>14} {'median gain':>12} {'sim sd':>6} {'folds > bar':>12} "
          f"{'warned':>6}  named")
    for c in table:
        g = "-" if c["median_gain_nats"] is None else \
            f"{c['median_gain_nats']:+.1f} ({c['median_gain_se'] or 0:.1f} se)"
        sd = c["median_loglik_noise_sd_none_nats"]
        noise = "-" if sd is None else f"{sd:.1f}"
        folds = "-" if c["folds"] is None else f"{c['folds_above_bar']} of {c['folds']}"
        warned = "-" if c["runs_warned"] is None else f"{c['runs_warned']}"
        print(f"{c['effect']:18} {c['strength']:8g} {c['n_obs']:5d} "
              f"{c['named_right']:>5d} of {c['runs']:<4d} "
              f"{c['rate_q05']:6.2f}-{c['rate_q95']:<6.2f} {g:>12} {noise:>6} {folds:>12} "
              f"{warned:>6}  " + ", ".join(f"{k} {v}" for k, v in c["named"].items()))
    print("(sim sd: median Monte Carlo sd of the baseline's summed log-likelihood, nats;\n"
          " folds > bar: the first step's held-out folds, every candidate's, whose importance\n"
          " weights have a Pareto k-hat above the bar min(0.7, 1 - 1/log10 S); warned: runs\n"
          " with such a fold, whose verdict calib.discover flags as resting on unreliable "
          "scores)")
    print(f"wrote {os.path.join(args.out, 'power.csv')} and power.json")


def main(argv=None) -> int:
    with command_args(argv):
        return run_guarded(PROG, _run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
