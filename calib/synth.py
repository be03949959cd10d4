"""``python -m calib.synth --effect E --out synth.csv``: observations with a hidden effect.

Simulates blocks with one candidate effect of ``calib.model.effects`` switched on
(inside the solver) and writes them as observed runouts in the schema of
``data/postignano.csv``, so that ``python -m calib.discover`` can be tested on
data whose missing physics is known. Three files are written, atomically:

* ``OUT`` (e.g. ``synth.csv``): the observations. Nothing in it names the effect.
* ``<OUT stem>.truth.json``: the effect, its strength, the full parameter vector,
  the seed and the noise (kept out of the CSV so the workflow cannot see it).
* ``<OUT stem>_profile.csv``, ``<OUT stem>_materials.csv``: copies of the slope
  profile used and its materials, where ``calib.discover`` looks by default.
* with ``--velocity-stations-m X[,X...]``: ``<OUT stem>_velocities.csv``,
  ``--n-velocity`` passage speeds at those abscissae (schema of
  ``calib.files.observations.load_velocities``; noise and tolerance
  ``--velocity-sd-m-s``), for ``calib.discover --velocities`` and
  ``calib.fit --velocities``. CRSP only.

Rows: ``--n-obs`` blocks spread over the sizes 0.2, 0.4, 0.7, 1.0, 1.4, 2.0 m;
each runout is one simulated block plus Gaussian noise of ``--sd-m`` m, which is
also the row's stated tolerance. The truths (base CRSP set and strengths) are
in ``calib.model.effects``. The slope is ``--profile`` (required: no site is
the default). Old option names (``--sd``, ``--velocity-sd``,
``--velocity-stations``) stay one release as deprecated aliases.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys

from calib.files.provenance import command_args, command_line
from solvers.cli import (
    CliError,
    OneLineParser,
    deprecated_alias,
    parse_stations,
    run_guarded,
    text_writer,
    write_all_atomic,
)

__all__ = ["add_speed_options", "main", "speed_design"]

PROG = "python -m calib.synth"


def build_parser() -> argparse.ArgumentParser:
    from calib.model.effects import EFFECT_NAMES

    p = OneLineParser(
        prog=PROG, description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example (the Postignano slope shipped in data/):\n"
               "  python -m calib.synth --effect fragmentation --seed 3 \\\n"
               "      --profile data/postignano_profile.csv --out synth.csv\n"
               "  python -m calib.discover synth.csv\n"
               "Effects (calib/model/effects.py): none, size_dissipation (size-dependent "
               "restitution; DEM: alpha(L)), fragmentation (break on a hard impact), "
               "rolling_resistance (extra rolling resistance), vegetation_belt (a forest "
               "stretch that brakes blocks). The DEM has none, size_dissipation and "
               "fragmentation.")
    p.add_argument("--effect", required=True, choices=EFFECT_NAMES,
                   help="effect switched on in the simulation")
    p.add_argument("--strength", type=float, default=1.0,
                   help="strength of the effect (1 = moderate, the default; see "
                        "calib/model/effects.py for what it means for each effect)")
    p.add_argument("--model", choices=["crsp", "dem"], default="crsp",
                   help="solver that makes the data (default crsp)")
    p.add_argument("--n-obs", type=int, default=60, help="number of rows (default 60)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated blocks "
                   "and the noise (default 0)")
    p.add_argument("--sd-m", type=float, default=5.0,
                   help="measurement noise and stated tolerance of each row, m (default 5)")
    deprecated_alias(p, "--sd", "--sd-m")
    add_speed_options(p, "also write passage speeds at these abscissae, m (e.g. 110, the "
                         "foot of the steep slope on Postignano); CRSP only")
    p.add_argument("--profile", required=True,
                   help="slope profile CSV (x_m,z_m,zone; its materials CSV next to it), "
                        "e.g. data/postignano_profile.csv")
    p.add_argument("--out", required=True, help="observations CSV to write")
    p.add_argument("--no-progress", action="store_true", help="accepted for symmetry; "
                   "the simulation prints nothing")
    return p


def _check(args) -> None:
    from calib.model.effects import DEM_EFFECTS

    if args.model == "dem" and args.effect not in DEM_EFFECTS:
        raise CliError(f"--effect {args.effect}: not available for the DEM (it has "
                       f"{', '.join(DEM_EFFECTS)})")
    if not (args.strength > 0 and args.strength < 1e6):
        raise CliError(f"--strength: expected a positive number, got {args.strength:g}")
    if args.n_obs < 1 or args.n_obs > 100_000:
        raise CliError(f"--n-obs: expected 1 to 100000 rows, got {args.n_obs}")
    if not (args.sd_m > 0 and args.sd_m < 1e4):
        raise CliError(f"--sd-m: expected a positive number of metres, got {args.sd_m:g}")
    if not args.out.endswith(".csv"):
        raise CliError(f"--out {args.out}: expected a .csv file name")
    parent = os.path.dirname(os.path.abspath(args.out))
    if not os.path.isdir(parent):
        raise CliError(f"--out {args.out}: folder {parent} does not exist")
    if not os.path.isfile(args.profile):
        raise CliError(f"{args.profile}: no such profile file")
    if args.velocity_stations_m is not None and args.model != "crsp":
        raise CliError("--velocity-stations-m: passage speeds are made with CRSP only")


def add_speed_options(p: argparse.ArgumentParser, stations_help: str) -> None:
    """``--velocity-stations-m``, ``--n-velocity``, ``--velocity-sd-m-s`` (read back
    by ``speed_design``; their old names as deprecated aliases); shared with
    ``calib.power``."""
    p.add_argument("--velocity-stations-m", default=None, metavar="X[,X...]",
                   help=stations_help)
    deprecated_alias(p, "--velocity-stations", "--velocity-stations-m")
    p.add_argument("--n-velocity", type=int, default=30,
                   help="number of passage-speed rows with --velocity-stations-m (default 30)")
    p.add_argument("--velocity-sd-m-s", type=float, default=1.0,
                   help="noise and stated tolerance of each speed, m/s (default 1)")
    deprecated_alias(p, "--velocity-sd", "--velocity-sd-m-s")


def speed_design(args, profile):
    """(stations_m, rows, sd_m_s) of ``--velocity-stations-m``, ``--n-velocity`` and
    ``--velocity-sd-m-s`` (shared with ``calib.power``), or None without stations;
    a bad value is a ``CliError`` naming its option."""
    if args.velocity_stations_m is None:
        return None
    stations = parse_stations(args.velocity_stations_m, profile.x_range_m,
                              "--velocity-stations-m")
    if args.n_velocity < 1 or args.n_velocity > 100_000:
        raise CliError(f"--n-velocity: expected 1 to 100000 rows, got {args.n_velocity}")
    if not (args.velocity_sd_m_s > 0 and args.velocity_sd_m_s < 1e3):
        raise CliError(f"--velocity-sd-m-s: expected a positive number of m/s, got "
                       f"{args.velocity_sd_m_s:g}")
    return stations, args.n_velocity, args.velocity_sd_m_s


def _run(args) -> int:
    _check(args)
    from calib.discovery.synthetic import (
        observations_csv_text,
        synthesize_effect,
        velocities_csv_text,
    )
    from solvers.profile import ProfileError, default_materials_path, load_profile

    try:
        profile = load_profile(args.profile)
    except ProfileError as e:
        raise CliError(str(e)) from None
    speeds = speed_design(args, profile)  # every option checked before anything is simulated
    obs, truth = synthesize_effect(profile, args.effect, args.strength, args.n_obs,
                                   args.seed, args.model, args.sd_m)
    stem = args.out[:-4]
    files = {}
    if speeds is not None:
        from calib.discovery.synthetic import synthesize_velocities

        try:
            vel = synthesize_velocities(profile, args.effect, args.strength, speeds[1],
                                        args.seed, speeds[0], speeds[2])
        except ValueError as e:
            raise CliError(f"--velocity-stations-m: {e}") from None
        files[stem + "_velocities.csv"] = text_writer(velocities_csv_text(vel, args.seed))
        truth.update({"velocities_csv": stem + "_velocities.csv",
                      "velocity_stations_m": speeds[0], "n_velocity": args.n_velocity,
                      "velocity_sd_m_s": args.velocity_sd_m_s})
    truth.update({"observations_csv": args.out, "profile_csv": stem + "_profile.csv",
                  "profile_source": args.profile, "command": command_line(PROG),
                  "note": "the truth is kept out of the observations on purpose"})
    write_all_atomic({
        args.out: text_writer(observations_csv_text(obs, args.seed)),
        stem + ".truth.json": text_writer(json.dumps(truth, indent=1) + "\n"),
        stem + "_profile.csv": lambda p: shutil.copyfile(args.profile, p),
        stem + "_materials.csv":
            lambda p: shutil.copyfile(default_materials_path(args.profile), p),
        **files,
    })
    print(f"wrote {obs.n_obs} rows to {args.out} (truth in {stem}.truth.json, "
          f"profile in {stem}_profile.csv and {stem}_materials.csv)")
    if files:
        print(f"wrote {args.n_velocity} passage speeds to {stem}_velocities.csv (give "
              f"--velocities {stem}_velocities.csv to calib.discover and calib.fit)")
    return 0


def main(argv=None) -> int:
    with command_args(argv):
        return run_guarded(PROG, _run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
