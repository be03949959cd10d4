#!/usr/bin/env python3
"""Does the discovery loop pay off on a site whose missing effect is known?

A user's whole path, command by command, on synthetic data with one effect
hidden (``calib.synth``), where the truth is known and fresh rows of the same
site can be drawn:

1. ``calib.synth``: the rows to fit (``--n-obs``, ``--seed``; with
   ``--velocity-stations-m``, also ``--n-velocity`` passage speeds there) and,
   from the same truth with another seed, runout rows the fits never see
   (``--heldout-n-obs``, ``--heldout-seed``);
2. ``calib.discover`` on the rows to fit (and their speeds): which effect it names;
3. the ``calib.fit`` command discovery prints (``refit_command``, which carries
   the speeds), and the same command without its ``--effect`` options: the baseline;
4. ``calib.validate`` of both calibrations on the unseen rows: CRPS, skill
   against the fitted rows' climatology, coverage;
5. ``calib.hazard`` of both calibrations (``--road-x-m``), and the truth's own
   exceedance at the same stations and sizes (``--truth-blocks`` blocks of the
   true parameters, ``calib.model.forward.CrspForward`` with the effect): how
   far each fit's exceedance curve lies from the truth's, and whether the truth
   lies inside each fit's 5-95 % band.

The chain "worked" for an effect when discovery names it, the fit with it
scores better than the baseline on the unseen rows (lower mean CRPS) and its
exceedance lies closer to the truth's. The script reports each of these; it
does not decide what a study concludes.

Usage (the figures of docs/studies.md)::

    python scripts/hidden_effect_chain.py --effect size_dissipation \\
        --profile data/postignano_profile.csv --n-obs 180 --seed 9101 \\
        --heldout-seed 9102 --out results/chain-size_dissipation/
    python scripts/hidden_effect_chain.py --effect vegetation_belt \\
        --velocity-stations-m 110 --n-velocity 30 --out results/chain-vegetation_belt/

Writes into ``--out``: the synthetic rows, every command's output folder, and
``chain.json`` (the commands, their times and the figures printed).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time

import numpy as np

SIZES_M = (0.2, 0.5, 1.0, 2.0)  # block sizes of the hazard runs and the truth, m


def run_command(args: list[str], log: str) -> float:
    """Run ``python -m ...`` as a user would; its output to ``log``; seconds taken.
    A command that fails stops the chain with its last lines."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.run([sys.executable, *args], stdout=f, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        with open(log) as f:
            tail = f.read()[-2000:]
        raise SystemExit(f"{' '.join(args)} failed (exit {proc.returncode}):\n{tail}")
    return time.perf_counter() - t0


def read_json(path: str) -> dict:
    """A command's JSON output."""
    with open(path) as f:
        return json.load(f)


def without_effects(command: str) -> list[str]:
    """The arguments of a ``python -m calib.fit ...`` command line without its
    ``--effect NAME`` options."""
    words = shlex.split(command)[1:]  # drop "python"
    out, skip = [], False
    for w in words:
        if skip:
            skip = False
        elif w == "--effect":
            skip = True
        elif not w.startswith("--effect="):
            out.append(w)
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python scripts/hidden_effect_chain.py",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--effect", required=True,
                   help="effect hidden in the data (a calib.synth --effect)")
    p.add_argument("--profile", default="data/postignano_profile.csv",
                   help="slope profile CSV the synthetic site uses")
    p.add_argument("--strength", type=float, default=1.0, help="calib.synth --strength")
    p.add_argument("--n-obs", type=int, default=180, help="rows to fit")
    p.add_argument("--seed", type=int, default=9101, help="calib.synth seed of the rows to fit")
    p.add_argument("--heldout-n-obs", type=int, default=60, help="unseen rows")
    p.add_argument("--heldout-seed", type=int, default=9102,
                   help="calib.synth seed of the unseen rows")
    p.add_argument("--velocity-stations-m", default=None, metavar="X[,X...]",
                   help="also make passage speeds of the rows to fit at these abscissae, m "
                        "(calib.synth --velocity-stations-m), fitted by discover and both "
                        "fits; the unseen rows stay runouts")
    p.add_argument("--n-velocity", type=int, default=30,
                   help="passage speeds with --velocity-stations-m")
    p.add_argument("--road-x-m", type=float, default=230.0,
                   help="road abscissa for calib.hazard, m")
    p.add_argument("--truth-blocks", type=int, default=20000,
                   help="blocks per size of the truth's exceedance")
    p.add_argument("--out", required=True, help="output folder")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import pandas as pd

    from calib.discovery.synthetic import compare_exceedance, truth_exceedance
    from solvers.profile import load_profile

    os.makedirs(args.out, exist_ok=True)
    o = lambda *p: os.path.join(args.out, *p)  # noqa: E731
    times, record = {}, {"effect": args.effect, "strength": args.strength,
                         "n_obs": args.n_obs, "seed": args.seed,
                         "heldout_n_obs": args.heldout_n_obs,
                         "heldout_seed": args.heldout_seed,
                         "velocity_stations_m": args.velocity_stations_m,
                         "n_velocity": args.n_velocity if args.velocity_stations_m else 0}
    data, held = o("data.csv"), o("heldout.csv")
    speeds = ([] if args.velocity_stations_m is None else
              ["--velocity-stations-m", args.velocity_stations_m,
               "--n-velocity", str(args.n_velocity)])
    for csv, n, seed, extra in ((data, args.n_obs, args.seed, speeds),
                                (held, args.heldout_n_obs, args.heldout_seed, [])):
        times[f"synth {os.path.basename(csv)}"] = run_command(
            ["-m", "calib.synth", "--effect", args.effect, "--strength", str(args.strength),
             "--n-obs", str(n), "--seed", str(seed), "--profile", args.profile, "--out", csv,
             *extra], csv + ".log")
    truth = read_json(o("data.truth.json"))

    times["discover"] = run_command(
        ["-m", "calib.discover", data, "--out", o("discover"), "--no-progress",
         *(["--velocities", o("data_velocities.csv")] if speeds else [])], o("discover.log"))
    disc = read_json(o("discover", "discovery.json"))
    record["named_effects"] = disc["named_effects"]
    record["gap_m"] = [disc["gap_before"], disc["gap_after"]]
    fits = {}
    if disc["refit_command"] and disc["named_effects"]:
        fits["effect"] = shlex.split(disc["refit_command"])[1:]
        fits["baseline"] = without_effects(disc["refit_command"])
    else:
        fits["baseline"] = ["-m", "calib.fit", data, "--model", "crsp",
                            *(["--velocities", o("data_velocities.csv")] if speeds else [])]
    record["fit_commands"] = {}
    for k, cmd in fits.items():
        cmd = [*cmd, "--out", o(f"fit_{k}"), "--no-progress"]
        record["fit_commands"][k] = "python " + shlex.join(cmd)
        times[f"fit {k}"] = run_command(cmd, o(f"fit_{k}.log"))

    record["validation"], tables = {}, {}
    for k in fits:
        cal = o(f"fit_{k}", "calibration.json")
        times[f"validate {k}"] = run_command(
            ["-m", "calib.validate", cal, held, "--out", o(f"validate_{k}")],
            o(f"validate_{k}.log"))
        v = read_json(o(f"validate_{k}", "validation.json"))
        record["validation"][k] = {key: v[key] for key in (
            "mean_crps_m", "mean_crps_climatology_m", "skill_vs_climatology",
            "skill_vs_climatology_size", "coverage_50", "coverage_90")}
        times[f"hazard {k}"] = run_command(
            ["-m", "calib.hazard", cal, "--road-x-m", str(args.road_x_m), "--no-progress",
             "--block-sizes-m", ",".join(f"{d:g}" for d in SIZES_M),
             "--out", o(f"hazard_{k}")], o(f"hazard_{k}.log"))
        tables[k] = pd.read_csv(o(f"hazard_{k}", "exceedance.csv"))
    stations = np.sort(tables["baseline"]["x_m"].unique())
    t0 = time.perf_counter()
    truth_p = truth_exceedance(load_profile(truth["profile_csv"]), truth["effect"],
                               truth["strength"], SIZES_M, stations, args.truth_blocks,
                               args.seed + 1)
    times["truth exceedance"] = time.perf_counter() - t0
    record["exceedance"] = compare_exceedance(tables, truth_p, SIZES_M, stations,
                                              args.road_x_m)
    record["times_s"] = {k: round(v, 1) for k, v in times.items()}
    with open(o("chain.json"), "w") as f:
        json.dump(record, f, indent=1, allow_nan=False)
    _print(record)
    return 0


def _print(r: dict) -> None:
    speeds = (f" and {r['n_velocity']} passage speeds at {r['velocity_stations_m']} m"
              if r.get("n_velocity") else "")
    print(f"hidden effect {r['effect']} (strength {r['strength']:g}), {r['n_obs']} rows"
          f"{speeds} (seed {r['seed']}), {r['heldout_n_obs']} unseen rows (seed "
          f"{r['heldout_seed']})")
    print(f"discover named: {', '.join(r['named_effects']) or 'none'}; gap "
          f"{r['gap_m'][0]:.2f} -> {r['gap_m'][1]:.2f} m")
    for k, v in r["validation"].items():
        print(f"{k:9s} on the unseen rows: CRPS {v['mean_crps_m']:.2f} m (climatology "
              f"{v['mean_crps_climatology_m']:.2f} m, skill {v['skill_vs_climatology']:+.2f}, "
              f"per size {v['skill_vs_climatology_size']:+.2f}); 50 % / 90 % coverage "
              f"{v['coverage_50']:.2f} / {v['coverage_90']:.2f}")
    for d, e in r["exceedance"].items():
        road = e["road"]
        if not e["n_stations"]:
            print(f"d {d} m: no block passes any station, in the truth or either fit")
            continue
        parts = [f"{k} {e[k]['mean_abs_error']:.3f} (truth in band {e[k]['truth_in_band']:.0%}"
                 f", road {road[k][0]:.3f} [{road[k][1]:.3f}, {road[k][2]:.3f}])"
                 for k in r["validation"]]
        print(f"d {d} m, {e['n_stations']} stations: mean |P - P_truth|: " + "; ".join(parts)
              + f"; truth at the road (x {road['x_m']:g} m) {road['truth']:.3f}")
    print("times: " + ", ".join(f"{k} {v:.0f} s" for k, v in r["times_s"].items()))


if __name__ == "__main__":
    sys.exit(main())
