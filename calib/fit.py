"""``python -m calib.fit DATA.csv``: calibrate CRSP (Kn, Kt, S) and the DEM damping law.

Reads observed runouts (``calib.files.observations``) and a slope profile, fits each
model by gradient (optax on a smoothed common-random-number objective of the
simulator) and by Bayesian inference (NumPyro NUTS on a Gaussian-process
emulator of the simulator), checks the fit by re-simulation, and writes into
``--out`` (atomically: everything is computed first, each file is written to a
temporary name and renamed, so a failure leaves no half-written file):

* ``calibration.json``: point estimates and 90 % intervals, the damping law and
  alpha at L = 0.2, 0.9, 1.8 m, per-observation fit quality, diagnostics,
  emulator checks, unfinished blocks per stage (``unfinished_blocks``, see
  ``calib.model.unfinished``), stage timings, seed and package versions;
* ``crsp_posterior.csv``, ``dem_posterior.csv``: posterior draws;
* ``crsp_posterior.nc``, ``dem_posterior.nc``: the same draws as ArviZ
  InferenceData (NetCDF-4: chains, sampler statistics, the pointwise emulated
  log-likelihood and the observed rows; ``calib.files.inference_data``, read back with
  ``read_inference_data``);
* ``runout_vs_size.png``, ``alpha_law.png``, ``crsp_pairs.png``, ``dem_pairs.png``.

``--velocities FILE`` (CRSP) fits passage speeds at stations with the runouts
(``calib.files.observations.load_velocities``; the same observation model as
``python -m calib.discover --velocities``): each speed row is scored against
the simulated speeds of the blocks of its size that passed its station, in
the summed log-likelihood NUTS samples. The fit is then Bayesian only (the
gradient stage fits runouts); ``calibration.json`` records the file
(``velocities``).

``--effect NAME`` (CRSP, repeatable) adds candidate effects of
``calib.model.effects`` (the ones ``python -m calib.discover`` compares) to
the model: their parameters are fitted with the baseline's over their prior
boxes, by the same stages and checks, and written like the baseline's
(``crsp.effects`` names them; ``calib.files.calibration_file``).

The command is options and printing around ``run_fit`` (the fit and its
outputs, typed results back; one model's calibration is
``calib.inference.calibrate.fit_model``) and ``validate_heldout`` (the
hold-out check); a notebook or script calls them with the same options.

The likelihood (``calib.inference.likelihood``): each observed row is one draw from the
simulated runout distribution of blocks of its size, seen with a Gaussian
tolerance (points) or known to lie in an interval.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
import warnings

import jax

from calib.files.provenance import command_args, command_running
from calib.model.dem_run import DEM_RUN, with_max_time
from calib.model.effects import CRSP_EFFECTS
from calib.model.priors import CRSP_ROLLING_BOX, ROLLING, NoRestError
from calib.model.unfinished import UnfinishedBlocksWarning
from calib.validate import print_summary as print_validation
from calib.validate import run_validation
from solvers import crsp
from solvers.cli import (
    CliError,
    OneLineParser,
    Progress,
    run_guarded,
    write_outputs,
)
from solvers.percentiles import few_blocks_warning

__all__ = ["POINT_ESTIMATE_BLOCKS", "FitRun", "fit_argv", "main", "run_fit", "run_options",
           "validate_heldout"]

PROG = "python -m calib.fit"


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=PROG,
        description=__doc__.split("\n\n")[0] + " Writes calibration.json, posterior CSVs and "
        "figures; prints a summary table.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example: python -m calib.fit data/postignano.csv --quick --out results/\n"
               "Observation CSV columns: block_size_m, runout_m, runout_sd_m (a point with a "
               "tolerance) or runout_min_m, runout_max_m (an interval), source.")
    p.add_argument("data", help="observed runouts CSV (see data/README.md for the schema)")
    p.add_argument("--profile", default=None,
                   help="slope profile CSV (default: <data stem>_profile.csv next to DATA, "
                        "else profile.csv in DATA's folder)")
    p.add_argument("--model", choices=["crsp", "dem", "both"], default="both",
                   help="which solver to calibrate (default: both)")
    p.add_argument("--method", choices=["gradient", "bayes", "both"], default="both",
                   help="gradient (optax, point estimate), bayes (NumPyro NUTS on an "
                        "emulator, posterior) or both (default)")
    p.add_argument("--rolling-resistance", choices=["fit", "zones", "profile"], default="fit",
                   help="CRSP rolling resistance angle: fit it as a 4th parameter, one value "
                        "for the slope, prior 5-40 deg (from the profile's flattest slope "
                        "where that is steeper: below it no block can rest on the profile), "
                        "with S from 0.01 m (default); 'zones': "
                        "fit one angle per material zone of the profile(s), "
                        "rolling_friction_deg[<zone>], same prior; 'profile': keep the "
                        "profile's per-zone rolling_friction_deg and S from 0.25 m")
    p.add_argument("--effect", action="append", default=[], metavar="NAME",
                   choices=[e for e in CRSP_EFFECTS if e != "none"],
                   help="CRSP only: switch on a candidate effect of calib.discover ("
                        + ", ".join(e for e in CRSP_EFFECTS if e != "none") + "; physics "
                        "in solvers/crsp/_effects.py, prior boxes in calib/model/effects.py) "
                        "and fit its parameters with the baseline's; repeat it to combine "
                        "effects (any distinct ones run together; rolling_resistance only with "
                        "--rolling-resistance profile, the other modes fit that angle "
                        "already). calibration.json records them (crsp.effects), and "
                        "calib.validate and calib.hazard simulate them. Default: none")
    p.add_argument("--velocities", default=None, metavar="FILE",
                   help="CRSP only: passage speeds at stations to fit with the runouts, CSV "
                        "with columns station_x_m, block_size_m, velocity_m_s, "
                        "velocity_sd_m_s[, source] (calib.synth --velocity-stations-m writes "
                        "one); the fit is then Bayesian (--method both means bayes; the "
                        "gradient stage fits runouts only); every speed row is fitted, "
                        "also under --holdout-fraction. Default: none")
    p.add_argument("--alpha-law", choices=["power", "constant"], default="power",
                   help="DEM damping law: power alpha = a L^-b (default) or constant alpha")
    p.add_argument("--dem-max-time-s", type=float, default=None,
                   help="DEM only: simulated time every block gets, s; a block still moving "
                        "then is unfinished and left out of the fit (the fit's summary "
                        "counts them). calibration.json records it (dem.run.max_time_s), "
                        "and calib.validate and calib.hazard run with it (default: the "
                        "site file's dem_max_time_s, else "
                        f"{DEM_RUN.max_time_s:g}, calib/model/dem_run.py)")
    p.add_argument("--row-shapes", action="store_true",
                   help="CRSP only: simulate each row's block in its shape column's CRSP class "
                        "(sphere, cylinder, disc; empty: sphere) of the volume of the sphere "
                        "of its block_size_m; calibration.json records it (row_shapes) and "
                        "calib.validate simulates held-out rows the same way. Default: every "
                        "row a sphere (Tschamut's plate fits worse as a CRSP disc: "
                        "docs/studies.md)")
    p.add_argument("--out", default="results", help="output folder (default: results/)")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed (default 0)")
    p.add_argument("--quick", action="store_true",
                   help="small budgets (about 4.5 min on 2 cores; for tests and a first look; "
                        "its posterior diagnostics usually fail and say so)")
    p.add_argument("--holdout-fraction", type=float, default=0.0,
                   help="keep this fraction of the rows aside (split by --seed), fit the "
                        "rest, then check the calibration's predictions of the held-out rows "
                        "(python -m calib.validate; written to OUT/validation/). Default 0: "
                        "fit every row")
    p.add_argument("--release-tolerance-m", type=float, default=1.0,
                   help="rows of one block size whose release_x_m (and, for CRSP, "
                        "release_height_m) lie within this distance share one simulated "
                        "release (their mean); 0 simulates "
                        "every distinct release (slower). Rows without release_x_m start at "
                        "the profile's first vertex (default 1.0 m)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


@dataclasses.dataclass
class FitRun:
    """What one calibration run (``run_fit``) produced, typed.

    Attributes:
        calibration: the calibration file written, as the typed document
            it was written from, its ``path`` set
            (``calib.files.calibration_file.CalibrationFile``; one model's
            ``Calibration`` is ``calibration.calibration(model)``).
        fits: model -> its ``calib.inference.calibrate.ModelRun`` (the
            ``ModelFit`` with its posterior, check and adequacy; the forward model).
        inputs: the rows fitted (under a hold-out split, the calibration part),
            their profile and site (``calib.files.inputs.Inputs``).
        entries: what those rows made the solvers simulate
            (``calib.model.entries.Entries``).
        out: the output folder.
        heldout_csv: the held-out rows' CSV in ``out``, or None (no split).
    """

    calibration: object
    fits: dict
    inputs: object
    entries: object
    out: str
    heldout_csv: str | None = None


def run_fit(data: str, out: str, *, profile: str | None = None,
            models: tuple[str, ...] = ("crsp", "dem"),
            methods: tuple[str, ...] = ("gradient", "bayes"), rolling_resistance: str = "fit",
            effects: tuple[str, ...] = (), alpha_law: str = "power", seed: int = 0,
            quick: bool = False, holdout_fraction: float = 0.0,
            release_tolerance_m: float = 1.0, velocities: str | None = None,
            dem_max_time_s: float | None = None, row_shapes: bool = False,
            progress: bool = False, report=None) -> FitRun:
    """Calibrate ``models`` on the rows of ``data`` and write every output into
    ``out`` (the files of the module docstring; the rows files of the split),
    as ``python -m calib.fit`` does with the same options (defaults: the
    command's). The predictive check of a hold-out split is ``validate_heldout``.

    Args:
        data, profile: the observations CSV and its profile (None: the default
            profile next to the data, ``calib.files.inputs.default_profile``).
        out: output folder.
        models, methods, rolling_resistance, effects, alpha_law, seed, quick,
        holdout_fraction, release_tolerance_m, velocities, dem_max_time_s,
        row_shapes: the
            command's options of those names (``--model``, ``--method``, ...;
            ``build_parser``; with ``velocities``, methods ("gradient", "bayes")
            fit by "bayes" alone).
        progress: show progress bars on stderr.
        report: callable(line) given the lines the command prints before it
            fits (the split, the release groups); None: silent.

    Returns:
        ``FitRun``.

    Raises:
        CliError: bad input (one line naming the file, row and column) or a
            fit the alpha-law check refuses; nothing is written.

    Longer than 80 lines with this docstring (about 60 without): the job's
    steps in order, each one call into the module that owns it (load, split,
    fit per model, record, figures, write); cut into helpers of this module,
    the inputs and fits would pass back and forth through it between steps.
    """
    from calib.files.fit_record import FitOptions, fit_document, posterior_files
    from calib.files.inputs import InputError, load_inputs
    from calib.files.provenance import provenance
    from calib.files.split import hold_out
    from calib.inference.calibrate import fit_model
    from calib.model.alpha_law import check_fit
    from calib.plots.figures import fit_figures

    t_start = time.perf_counter()
    say = report or (lambda line: None)
    # the command this call is: main's own arguments, or a library call's equivalent
    argv = None if command_running() else fit_argv(
        data, out, profile=profile, models=models, methods=methods,
        rolling_resistance=rolling_resistance, effects=effects, alpha_law=alpha_law,
        seed=seed, quick=quick, holdout_fraction=holdout_fraction,
        release_tolerance_m=release_tolerance_m, velocities=velocities,
        dem_max_time_s=dem_max_time_s, row_shapes=row_shapes)
    _check_effects(models, rolling_resistance, effects)
    if row_shapes and "crsp" not in models:
        raise CliError("--row-shapes: shape classes are CRSP's (the DEM's blocks are squares); "
                       "give --model crsp or both")
    if not release_tolerance_m >= 0:
        raise CliError(f"--release-tolerance-m must be >= 0, got {release_tolerance_m:g}")
    if dem_max_time_s is not None:
        _dem_run(dem_max_time_s, "--dem-max-time-s")
    methods = _check_velocities(velocities, models, methods, say)
    try:
        inputs = load_inputs(data, profile, out, velocities)
    except InputError as e:
        raise CliError(str(e)) from None
    dem_run, dem_time_source = _dem_time(dem_max_time_s, inputs.site,
                                         say if "dem" in models else None)
    files, data_csv = {}, data
    if holdout_fraction:
        try:
            split = hold_out(inputs, holdout_fraction, seed, out)
        except ValueError as e:
            raise CliError(str(e)) from None
        inputs, data_csv, files = split.inputs, split.rows_path, dict(split.files)
        say(split.message)
    entries = inputs.entries(release_tolerance_m, row_shapes)
    grouped = inputs.own_releases
    if grouped:
        for line in inputs.grouping_lines(entries, release_tolerance_m):
            say(line)
    models, methods = tuple(models), tuple(methods)
    key = jax.random.key(seed)
    fits = {}
    for i, model in enumerate(models):
        bar = Progress(progress, model.upper())
        with warnings.catch_warnings():  # reported in the summary and the json
            warnings.simplefilter("ignore", UnfinishedBlocksWarning)
            try:
                fits[model] = fit_model(model, inputs, entries, jax.random.fold_in(key, i),
                                        methods=methods, quick=quick,
                                        rolling_resistance=rolling_resistance,
                                        effects=tuple(effects), alpha_law=alpha_law,
                                        dem_run=dem_run, progress=bar)
            except NoRestError as e:
                raise CliError(f"{inputs.profile_path}: {e}") from None
        bar.close()
        if model == "dem":
            fit = fits[model].fit
            try:
                check_fit(alpha_law, fit.estimate,
                          None if fit.posterior is None else fit.posterior.samples,
                          inputs.obs.sizes_m)
            except ValueError as e:
                raise CliError(str(e)) from None
    options = FitOptions(provenance(PROG, seed, {"data": data, "profile": inputs.profile_path,
                                                 **({"velocities": velocities}
                                                    if velocities else {})}, argv),
                         data_csv, bool(quick), methods, grouped, release_tolerance_m,
                         bool(row_shapes), dem_time_source if "dem" in models else None)
    cal = fit_document(options, inputs, entries, fits, time.perf_counter() - t_start)
    files["calibration.json"] = cal.to_json()
    texts, writers = posterior_files(fits, inputs.obs)
    files.update(texts)
    write_outputs(out, files, fit_figures(fits, inputs), writers)
    # the document written, with the path its relative paths resolve against
    # (not read back: it is the typed results just written)
    return FitRun(dataclasses.replace(cal, path=os.path.join(out, "calibration.json")), fits,
                  inputs, entries, out,
                  os.path.join(out, "heldout_rows.csv") if holdout_fraction else None)


def _dem_run(max_time_s: float, name: str):
    """``calib.model.dem_run.with_max_time`` as a ``CliError`` naming ``name``."""
    try:
        return with_max_time(max_time_s, name)
    except ValueError as e:
        raise CliError(str(e)) from None


def _dem_time(max_time_s: float | None, site, say=None):
    """The DEM numerics of the fit and where their simulated time came from:
    ``--dem-max-time-s`` where given, else the site file's ``dem_max_time_s``
    (``say`` told so), else ``DEM_RUN``'s."""
    if max_time_s is None and site.dem_max_time_s is not None:
        if say is not None:
            say(f"DEM simulated time: {site.dem_max_time_s:g} s per block, the site's "
                f"({site.path}; default {DEM_RUN.max_time_s:g} s; calibration.json: "
                "dem_max_time_source)")
        return (_dem_run(site.dem_max_time_s, f"{site.path}: key 'dem_max_time_s'"),
                f"{site.path}: {site.dem_max_time_source}")
    if max_time_s is None:
        return _dem_run(DEM_RUN.max_time_s, "--dem-max-time-s"), "default (calib/model/dem_run.py)"
    return _dem_run(max_time_s, "--dem-max-time-s"), "--dem-max-time-s"


def fit_argv(data: str, out: str | None, *, profile: str | None = None,
             models: tuple[str, ...] = ("crsp", "dem"),
             methods: tuple[str, ...] = ("gradient", "bayes"), rolling_resistance: str = "fit",
             effects: tuple[str, ...] = (), alpha_law: str = "power", seed: int = 0,
             quick: bool = False, holdout_fraction: float = 0.0,
             release_tolerance_m: float = 1.0, velocities: str | None = None,
             dem_max_time_s: float | None = None, row_shapes: bool = False) -> list[str]:
    """The arguments of ``python -m calib.fit`` that run ``run_fit`` with these
    options (its keywords less ``progress`` and ``report``), every option
    explicit (``--dem-max-time-s`` where the DEM is fitted and it was given; without
    it the site file's or the default, as the command does): the command a
    library call of ``run_fit`` records, and (``out`` None: the command's
    default folder) the one ``calib.discover`` prints to refit with the
    effects it named."""
    argv = [data] + (["--out", out] if out is not None else [])
    argv += ["--profile", profile] if profile else []
    argv += ["--model", "both" if set(models) == {"crsp", "dem"} else models[0],
             "--method", "both" if set(methods) == {"gradient", "bayes"} else methods[0],
             "--rolling-resistance", rolling_resistance]
    for e in effects:
        argv += ["--effect", e]
    argv += ["--alpha-law", alpha_law, "--seed", str(seed)] + (["--quick"] if quick else [])
    argv += ["--holdout-fraction", repr(float(holdout_fraction)),
             "--release-tolerance-m", repr(float(release_tolerance_m))]
    argv += (["--dem-max-time-s", repr(float(dem_max_time_s))]
             if "dem" in models and dem_max_time_s is not None else [])
    argv += ["--row-shapes"] if row_shapes else []
    return argv + (["--velocities", velocities] if velocities else [])


def run_options(args) -> dict:
    """``run_fit``'s keywords (less ``progress`` and ``report``) from the
    command's parsed arguments; ``fit_argv`` is its inverse."""
    return dict(data=args.data, out=args.out, profile=args.profile,
                models=("crsp", "dem") if args.model == "both" else (args.model,),
                methods=("gradient", "bayes") if args.method == "both" else (args.method,),
                rolling_resistance=args.rolling_resistance, effects=tuple(args.effect),
                alpha_law=args.alpha_law, seed=args.seed, quick=args.quick,
                holdout_fraction=args.holdout_fraction,
                release_tolerance_m=args.release_tolerance_m, velocities=args.velocities,
                dem_max_time_s=args.dem_max_time_s, row_shapes=args.row_shapes)


def _run(args) -> int:
    options = run_options(args)
    models = options["models"]
    run = run_fit(**options, progress=not args.no_progress, report=print)
    _print_summary(run.calibration.doc, models, args.out)
    if args.holdout_fraction:
        for summary, folder in validate_heldout(args.out, models[0], args.seed,
                                                posterior=args.method != "gradient"):
            print()
            print_validation(summary, folder)
    return 0


def _check_velocities(velocities, models, methods, say) -> tuple[str, ...]:
    """The methods a fit with ``--velocities`` runs (the gradient stage fits
    runouts only: "both" runs bayes, said in a line); a DEM or gradient-only
    fit with them is refused in one line."""
    methods = tuple(methods)
    if velocities is None:
        return methods
    if tuple(models) != ("crsp",):
        raise CliError("--velocities: passage speeds are fitted with --model crsp only")
    if "bayes" not in methods:
        raise CliError("--velocities: the gradient stage fits runouts only; passage speeds "
                       "are fitted with --method bayes (or both)")
    if "gradient" in methods:
        say("passage speeds given: the fit is Bayesian (the gradient stage fits runouts only)")
    return ("bayes",)


def _check_effects(models, rolling_resistance, effects) -> None:
    """Refuse, in one line, ``--effect`` with a model or baseline it cannot join."""
    if not effects:
        return
    from calib.model.effects import effect_names

    if tuple(models) != ("crsp",):
        raise CliError(f"--effect {effects[0]}: effects are fitted with --model crsp only "
                       "(the DEM's size-dependent damping is --alpha-law power; its bonded "
                       "fragments are a calib.discover candidate only)")
    try:
        names = effect_names(effects)
        if "rolling_resistance" in names and rolling_resistance != "profile":
            raise ValueError(f"--rolling-resistance {rolling_resistance} fits the rolling "
                             "resistance angle already (the two are one parameter); use "
                             "--rolling-resistance profile with it")
    except ValueError as e:
        raise CliError(f"--effect: {e}") from None


# CRSP blocks per row group of the point estimate's check after a Bayesian fit
POINT_ESTIMATE_BLOCKS = 2000


def validate_heldout(out: str, model: str, seed: int = 0, posterior: bool = True,
                     point_estimate_blocks: int = POINT_ESTIMATE_BLOCKS
                     ) -> list[tuple[dict, str]]:
    """The predictive check (``calib.validate.run_validation``) of ``model``'s
    calibration in ``out`` on the held-out rows ``run_fit`` wrote there. With
    ``posterior`` (after a Bayesian fit): of its posterior predictive
    (``out/validation/``, 50 draws) and also of its point estimate alone
    (``out/validation/point_estimate/``, ``point_estimate_blocks`` CRSP blocks
    per row group, default ``POINT_ESTIMATE_BLOCKS``):
    where the posterior failed its checks, the two can differ widely, and the
    user should see both. Without (a gradient-only fit): of the point
    estimate, in ``out/validation/``.

    Returns:
        [(summary written to validation.json, its folder)], the posterior's first.
    """
    vargs = argparse.Namespace(
        calibration=os.path.join(out, "calibration.json"),
        heldout=os.path.join(out, "heldout_rows.csv"), model=model,
        calibration_data=None, n_posterior=50 if posterior else 1,
        n_blocks=None, seed=seed, out=os.path.join(out, "validation"))
    done = [(run_validation(vargs), vargs.out)]
    if posterior:
        n_blocks = point_estimate_blocks if model == "crsp" else None
        point = argparse.Namespace(**{**vars(vargs), "n_posterior": 1, "n_blocks": n_blocks,
                                      "out": os.path.join(vargs.out, "point_estimate")})
        done.append((run_validation(point), point.out))
    return done


def _fmt(v, nd=3):
    return "-" if v is None else f"{v:.{nd}f}"


def _print_summary(result: dict, models, out: str) -> None:
    """The fit's summary: parameters, rows, warnings, checks, the NUTS repairs,
    stage times."""
    _print_parameters(result, models)
    vel = result.get("velocities")
    if vel:
        print(f"fitted with {vel['n_observations']} passage speeds at "
              f"{', '.join(f'{x:g}' for x in vel['stations_m'])} m (calibration.json: "
              "velocities); the rows below are the runouts")
    _print_rows(result, models)
    _print_checks(result, models)
    _print_nuts_repairs(result, models)
    tim = result["timings_s"]
    parts = []
    for model in models:
        parts.append(model + ": " + ", ".join(f"{k[:-2]} {v:.0f} s" for k, v in tim[model].items()))
    print("\nstage times: " + "; ".join(parts) + f"; total {tim['total_s']:.0f} s")
    print(f"wrote {os.path.join(out, 'calibration.json')} and figures in {out}/")


def _print_parameters(result: dict, models) -> None:
    # the name column as wide as the longest name (rolling_friction_deg[<zone>])
    w = max([12] + [len(n) for m in models for n in result[m]["parameters"]])
    effects = result.get("crsp", {}).get("effects") if "crsp" in models else None
    if effects:
        print(f"CRSP effects: {', '.join(effects)} (their parameters follow the baseline's; "
              "calibration.json: crsp.effects)")
    threshold = result.get("rolling_threshold_m_s")
    if "crsp" in models and threshold is not None and threshold != crsp.ROLLING_THRESHOLD_M_S:
        print(f"CRSP rolling threshold: {threshold:g} m/s, the site's (solver default "
              f"{crsp.ROLLING_THRESHOLD_M_S:g} m/s; calibration.json: rolling_threshold_source)")
    floor = result.get("crsp", {}).get("prior", {}).get(ROLLING, (None,))[0] \
        if "crsp" in models else None
    published = CRSP_ROLLING_BOX.lower[CRSP_ROLLING_BOX.names.index(ROLLING)]
    if floor is not None and floor > published:
        print(f"CRSP rolling resistance: prior from {floor:.1f} deg, the flattest slope of the "
              f"profile (below it no block can come to rest on it; published range from "
              f"{published:g} deg)")
    print(f"{'model':5} {'parameter':{w}} {'estimate':>9} {'mean':>8} {'90% interval':>19}")
    for model in models:
        sec = result[model]
        params = _summaries(sec, model)
        for name in sec["parameters"]:
            s = params[name]
            iv = "-" if s["q05"] is None else f"[{s['q05']:.3f}, {s['q95']:.3f}]"
            print(f"{model:5} {name:{w}} {s['map']:9.3f} {_fmt(s['mean']):>8} {iv:>19}")
        if model == "dem":
            for L, s in sec["alpha_at_L"].items():
                iv = "-" if s["q05"] is None else f"[{s['q05']:.3f}, {s['q95']:.3f}]"
                ref = (f"   {sec['alpha_reference']['label']}: {s['reference']:.2f}"
                       if "reference" in s else "")
                print(f"{model:5} {'alpha(' + L + ')':{w}} {s['map']:9.3f} {_fmt(s['mean']):>8} "
                      f"{iv:>19}{ref}")
    for model in models:
        c = result[model].get("estimate_choice")
        if c and c["chosen"] == "posterior_mode":
            print(f"{model.upper()} estimate: the posterior's mode, which the simulator scores "
                  f"at {c['posterior_mode']['loglik']:.1f} nats against "
                  f"{_fmt(c['gradient']['loglik'], 1)} at the gradient stage's end point "
                  f"(margin {c['margin_nats']:.1f}; calibration.json: {model}.estimate_choice)")
        outside = _outside_interval(result[model], model)
        if c and c["chosen"] == "gradient" and outside:
            g, m = c["gradient"]["loglik"], c["posterior_mode"]["loglik"]
            gap = None if g is None or m is None else g - m
            what = ("the rows fit about as well at both, a sign that they leave a combination "
                    "of the parameters free. The posterior's draws, not this point, carry that"
                    if gap is not None and abs(gap) <= c["margin_nats"] else
                    "the simulator scores the point higher than the posterior's mode by more "
                    "than the margin: the posterior may have missed the best region")
            print(f"{model.upper()} estimate: the gradient stage's end point, outside the 90 % "
                  f"interval of {', '.join(outside)}; the simulator scores it at "
                  f"{_fmt(g, 1)} nats and the posterior's mode at {_fmt(m, 1)} (margin "
                  f"{_fmt(c['margin_nats'], 1)}): {what} (calib.hazard and calib.validate "
                  f"use the draws; calibration.json: {model}.estimate_choice)")


def _summaries(sec: dict, model: str) -> dict:
    """Where a model's parameter summaries live in ``calibration.json`` (name -> map,
    mean, q05, q95): the DEM's under ``alpha_law``, CRSP's in its section."""
    return sec["alpha_law"] if model == "dem" else sec


def _outside_interval(sec: dict, model: str) -> list[str]:
    """The parameters whose point estimate lies outside their posterior 90 % interval."""
    params = _summaries(sec, model)
    out = []
    for name in sec["parameters"]:
        s = params[name]
        if s.get("q05") is not None and not s["q05"] <= s["map"] <= s["q95"]:
            out.append(name)
    return out


def _print_rows(result: dict, models) -> None:
    print(f"\n{'model':5} {'size m':>6} {'observed m':>14} {'sim median':>10} "
          f"{'sim 5-95 %':>15} {'PIT':>5}")
    for model in models:
        for q in result["fit_quality"][model]:
            o = (f"{q['observed_m']:.0f} ± {q['observed_sd_m']:.0f}" if "observed_m" in q
                 else f"[{q['observed_min_m']:.0f}, {q['observed_max_m']:.0f}]")
            pit = q.get("pit", q.get("p_in_interval"))
            if q["sim_median_m"] is None:  # no simulated block of this size finished
                print(f"{model:5} {q['block_size_m']:6.2f} {o:>14} {'-':>10} {'-':>15} "
                      f"{'-':>5}  no finished block")
                continue
            flag = "" if q.get("in_90_band", True) else "  outside 90% band"
            if q.get("sim_few_blocks"):
                flag += f"  from {q['sim_n_finished']} blocks"
            print(f"{model:5} {q['block_size_m']:6.2f} {o:>14} {q['sim_median_m']:10.1f} "
                  f"{q['sim_q05_m']:6.1f}-{q['sim_q95_m']:<6.1f} {pit:5.2f}{flag}")


def _print_checks(result: dict, models) -> None:
    few = few_blocks_warning(
        [(f"{model} row {q['row']} ({q['block_size_m']:g} m)", q["sim_n_finished"])
         for model in models for q in result["fit_quality"][model] if q.get("sim_few_blocks")],
        what="the simulated 5/50/95 % runouts")
    if few:
        print(f"\n!!! {few}.", file=sys.stderr)
    for model in models:
        w = result[model]["unfinished_blocks"]["warning"]
        if w:
            print(f"\n!!! {w}.", file=sys.stderr)
    for model in models:
        a = result[model]["adequacy"]
        c = a["coverage"]["levels"]
        print(f"\n{model.upper()} calibration rows inside their predictive bands "
              f"({a['predictive']}): 50 %: {c['0.5']['n_covered']}/{c['0.5']['n_rows']}, "
              f"90 %: {c['0.9']['n_covered']}/{c['0.9']['n_rows']}")
        if a["bounds"] is not None:
            print(f"{model.upper()} posterior mass within {a['bound_band_fraction']:.0%} of a "
                  "prior bound: " + ", ".join(
                      f"{n} {max(b['lower'], b['upper']):.0%}" for n, b in a["bounds"].items()))
        if not a["ok"]:
            print(f"\n!!! {model.upper()} CALIBRATION: {a['message']}.", file=sys.stderr)


def _print_nuts_repairs(result: dict, models) -> None:
    """How often NUTS ran and why (each repair wave of
    ``calib.inference.bayes_stage`` reruns it once), the chains dropped, and a
    failed posterior's problems."""
    for model in models:
        b = result[model].get("bayes")
        screen = (b or {}).get("chain_screen") or {}
        focus = (b or {}).get("focus") or {}
        waves = focus.get("refined") or []
        bwaves = focus.get("best_point_waves") or []
        rwaves = focus.get("realisation_waves") or []
        widened = focus.get("widened") or []
        n_runs = focus.get("nuts_runs", 1)
        if n_runs > 1:
            print(f"\n{model.upper()} NUTS ran {n_runs} times: once, then once after each "
                  "repair below (bayes.focus.nuts_runs)")
        if widened:
            print(f"\n{model.upper()} focus region widened {len(widened)} times: the "
                  "posterior piled against a face the focus region drew (not the prior's); "
                  "the face moved out, new points filled the slab (bayes.focus.widened)")
        if waves:
            why = []
            for w in waves:
                there = w.get("emulator_at_posterior") or {}
                why.append("its diagnostics failed" if w["problems_before"] else
                           f"the GP was off where it sat (RMS z {there.get('z_rms', 0):.1f})")
            print(f"\n{model.upper()} refinement waves: "
                  + "; ".join(f"after run {i + 1} {r}" for i, r in enumerate(why))
                  + f", the {waves[0]['n_points']} draws re-simulated for the chain "
                  "screening joined the log-likelihood GP's design (bayes.focus.refined)")
        if bwaves:
            w = bwaves[0]
            print(f"\n{model.upper()} best-point waves: the design's best point "
                  f"({w['best_loglik']:.0f} nats) beat every chain ({w['chain_loglik']:.0f}) "
                  f"by more than {w['bar_nats']:.1f} nats; "
                  f"{'once' if len(bwaves) == 1 else f'{len(bwaves)} times'}, the focus region "
                  "narrowed to the points near it, new points filled it, and NUTS ran again "
                  "(bayes.focus.best_point_waves, bayes.focus.narrowed)")
        if rwaves:
            first = rwaves[0]["median_range"]
            print(f"\n{model.upper()} realisation waves: the posterior medians of "
                  f"{rwaves[0]['n_realisations']} realisations of the log-likelihood GP spread "
                  "beyond the 90 % intervals ("
                  + ", ".join(f"{n} {lo:.3g}-{hi:.3g}" for n, (lo, hi) in first.items())
                  + f"); {'once' if len(rwaves) == 1 else f'{len(rwaves)} times'}, one point "
                  "from each realisation's posterior was simulated and joined the GP's "
                  "design, and NUTS ran again "
                  "(bayes.focus.realisation_waves)")
        careful = focus.get("careful_run")
        if careful:
            print(f"\n{model.upper()} careful run: the chains agreed but had "
                  f"{careful['divergences_before']} divergent transitions; NUTS ran again "
                  f"with a smaller step size (target acceptance "
                  f"{careful['target_accept_prob']:g} for "
                  f"{careful['target_accept_prob_before']:g}; bayes.focus.careful_run)")
        longer = focus.get("longer_run")
        if longer:
            print(f"\n{model.upper()} longer run: the chains agreed but their ESS fell short "
                  f"(bulk {longer['ess_bulk_min_before']:.0f}, tail "
                  f"{longer['ess_tail_min_before']:.0f}, at least {longer['ess_min']:.0f} asked); "
                  "NUTS ran again "
                  f"with {longer['draw_factor']} times the draws, "
                  f"{longer['draws_per_chain']} per chain (bayes.focus.longer_run)")
        if screen.get("n_dropped"):
            lls = ", ".join(f"{v:.0f}" if v is not None else "none"
                            for v in screen["chain_loglik"])
            print(f"\n!!! {model.upper()} NUTS: {screen['n_dropped']} of "
                  f"{len(screen['kept'])} chains dropped: the simulator fits their draws "
                  f"worse than the best chain's by more than {screen['threshold_nats']:.0f} "
                  f"nats (median simulated log-likelihood per chain: {lls}); the emulator "
                  "was wrong where they sat, and the posterior is that of the other chains.",
                  file=sys.stderr)
        if b is not None and not b["ok"]:
            print(f"\n!!! {model.upper()} POSTERIOR DIAGNOSTICS FAILED: "
                  f"{'; '.join(b['problems'])}. Treat its intervals as unreliable.",
                  file=sys.stderr)


def main(argv=None) -> int:
    with command_args(argv):
        return run_guarded(PROG, _run, build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
