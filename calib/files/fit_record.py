"""The calibration document of one ``python -m calib.fit`` run, assembled from
its typed results (``calib.inference.calibrate.ModelFit`` per model, the inputs
and their simulated entries): ``fit_document`` builds the
``calib.files.calibration_file.CalibrationFile`` that the fit writes with
``to_json``; ``model_section`` and ``dem_alpha_section`` are its model
sections; ``posterior_files`` are the posterior draws' own files. The schema, its
reader and every consumer's checks are in ``calib.files.calibration_file``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from calib.files.calibration_file import SCHEMA, CalibrationFile
from calib.model.effects import effect_names

__all__ = ["ALPHA_AT_L", "BLOCK_SIZE_MAPPING", "FitOptions", "dem_alpha_section",
           "fit_document", "model_section", "posterior_files", "summary_stats"]


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """How one ``calib.fit`` run ran, as its calibration file records it.

    Attributes:
        provenance: the run's record (``calib.files.provenance.provenance``:
            command, seed, the input files' hashes, versions).
        data_csv: the rows fitted: the observations file given, or the rows
            file a hold-out split wrote.
        quick, methods: the command's options of those names (its seed is
            the provenance's).
        grouped: True where each row was released from its own point (the
            ``release_groups`` record is written).
        tolerance_m: the grouping tolerance, m.
        row_shapes: CRSP simulated each row in its ``shape`` column's class
            (``calib.model.entries``); False: spheres.
        dem_time_source: where the DEM's simulated time came from (the site
            file's ``dem_max_time_source``, the option, or the default); None
            where the DEM was not fitted.
    """

    provenance: dict
    data_csv: str
    quick: bool
    methods: tuple[str, ...]
    grouped: bool
    tolerance_m: float
    row_shapes: bool = False
    dem_time_source: str | None = None


def summary_stats(values: np.ndarray | None, point: float) -> dict:
    """``map`` (the point estimate), ``mean``, ``q05``, ``q95`` of one parameter's
    posterior draws ``values`` (None: the point estimate only)."""
    if values is None:
        return {"map": float(point), "mean": None, "q05": None, "q95": None}
    return {"map": float(point), "mean": float(np.mean(values)),
            "q05": float(np.quantile(values, 0.05)), "q95": float(np.quantile(values, 0.95))}


def _finite(v) -> float | None:
    """A float for JSON; None for a non-finite value (an objective of +inf where
    some size had no finished block)."""
    return float(v) if np.isfinite(v) else None


def model_section(name: str, fit, forward, law_form: str | None = None) -> dict:
    """The section of one model (``calib.inference.calibrate.ModelFit`` ``fit`` of
    ``forward``) as ``calib.fit`` writes it: parameters with map/mean/q05/q95
    (DEM: under ``alpha_law``, with the DEM numerics under ``run``), prior,
    gradient and Bayes records with their diagnostics, fit quality, adequacy,
    unfinished blocks, budgets and timings; CRSP: ``effects``, the effects
    ``forward`` switches on (their columns are among the parameters); ``posterior_csv`` and
    ``posterior_netcdf`` name the files written next to it."""
    post = fit.posterior
    sec = {"parameters": list(fit.names), "estimate_source": fit.estimate_source,
           "estimate_choice": fit.estimate_choice,
           "fit_quality": fit.quality, "unfinished_blocks": fit.unfinished,
           "adequacy": fit.adequacy,
           "timings_s": fit.timings_s,
           "budget": {k: v for k, v in vars(fit.budget).items()},
           "n_blocks_check": int(fit.check_runouts.shape[-1]),
           "common_random_numbers": True,
           "prior": {n: [float(lo), float(hi)] for n, lo, hi in
                     zip(fit.names, forward.box.lo, forward.box.hi)}}
    stats = {n: summary_stats(None if post is None else post.samples[:, i], fit.estimate[i])
             for i, n in enumerate(fit.names)}
    if fit.gradient is not None:
        g = fit.gradient
        sec["gradient"] = {
            "estimate": dict(zip(fit.names, map(float, g.theta))),
            "starts_final": [dict(zip(fit.names, map(float, t))) for t in g.theta_starts],
            "objective_final": [_finite(v) for v in g.objective_final],
            "objective_history": [[_finite(v) for v in row] for row in g.history]}
    if post is not None:
        sec["bayes"] = {
            "summary": post.summary(), "ok": post.ok, "problems": post.problems,
            "divergences": post.divergences, "accept_prob": post.accept_prob,
            "n_draws": int(post.samples.shape[0]), "n_chains": post.n_chains,
            "diagnostics": post.criteria,
            "emulator": fit.emulator_check, "focus": fit.focus,
            "chain_screen": fit.chain_screen}
        sec["posterior_csv"] = f"{name}_posterior.csv"
        sec["posterior_netcdf"] = f"{name}_posterior.nc"
    else:
        sec["posterior_csv"] = sec["posterior_netcdf"] = None
    if law_form is None:
        sec["effects"] = list(effect_names(getattr(forward, "effect", "none")))
        sec.update(stats)
    else:
        sec["run"] = dataclasses.asdict(forward.run)  # the DEM numerics (calib.model.dem_run)
        sec["alpha_law"] = {"form": law_form,
                            "expression": "a*L**-b" if law_form == "power" else "alpha",
                            **stats}
    return sec


ALPHA_AT_L = (0.2, 0.9, 1.8)  # DEM square sides at which alpha(L) is reported by default, m

BLOCK_SIZE_MAPPING = {"crsp_radius_m": "s * block_size_m / 2 (s: the group's shape's radius "
                                       "scale, solvers.crsp.shape_constants; a sphere's s = 1)",
                      "dem_side_m": "block_size_m",
                      "crsp_mass_kg": "rock_density_kg_m3 * pi * block_size_m**3 / 6",
                      "dem_mass_kg_per_m": "rock_density_kg_m3 * block_size_m**2"}


def dem_alpha_section(form: str, fit, site, sizes_m) -> dict:
    """alpha(L) of a DEM fit at the site's reference sides (``site.alpha_reference``)
    or at ``ALPHA_AT_L``: ``map``/``mean``/``q05``/``q95`` per side, with the
    published value beside it where the site gives one."""
    from calib.model.alpha_law import alpha_of

    ref = dict(site.alpha_reference)
    ls = np.asarray(sorted(ref) if ref else ALPHA_AT_L)
    at = np.asarray(alpha_of(form, fit.estimate, ls))
    post = fit.posterior
    samp = None if post is None else np.asarray(alpha_of(form, post.samples, ls))
    sec = {"alpha_at_L": {f"{L:g}": {**summary_stats(None if samp is None else samp[:, i], at[i]),
                                     **({"reference": ref[L]} if ref else {})}
                          for i, L in enumerate(ls)}}
    if ref:
        sec["alpha_reference"] = {"label": site.alpha_reference_label, "site_file": site.path}
    return sec


def fit_document(options: FitOptions, inputs, entries, fits: dict,
                 total_s: float) -> CalibrationFile:
    """The calibration file of one ``calib.fit`` run, from its typed results.

    Args:
        options: how the run ran (``FitOptions``).
        inputs: ``calib.files.inputs.Inputs`` (profile, site, rows).
        entries: the rows' ``calib.model.entries.Entries``.
        fits: model -> (``ModelFit``, forward model, alpha-law form or None).
        total_s: the run's wall time, s.
    """
    sections = {}
    for model, (fit, forward, form) in fits.items():
        sec = model_section(model, fit, forward, form)
        if form is not None:
            sec.update(dem_alpha_section(form, fit, inputs.site, inputs.obs.sizes_m))
        sections[model] = sec
    models = list(fits)
    prov = options.provenance
    doc = {"schema": SCHEMA, "command": prov["command"], "data_csv": options.data_csv,
           "profile_csv": inputs.profile_path, "seed": prov["seed"],
           "release_x_m": inputs.release_x_m,
           "release_groups": None if not options.grouped else {
               "tolerance_m": options.tolerance_m, "models": models,
               "speed_and_height_models": models,
               "groups": [{k: v for k, v in g.items()}
                          for g in entries.record(inputs.profile_path)]},
           "quick": options.quick, "methods": list(options.methods),
           "versions": prov["versions"], "inputs": prov["inputs"],
           "rock_density_kg_m3": entries.density_kg_m3,
           "rock_density_source": inputs.site.density_source,
           "release_height_sd_m": inputs.site.release_height_sd_m,
           "release_height_source": inputs.site.release_height_source or None,
           "release_speed_sd_m_s": inputs.site.release_speed_sd_m_s,
           "release_speed_source": inputs.site.release_speed_source or None,
           "rolling_threshold_m_s": inputs.site.rolling_threshold_m_s,
           "rolling_threshold_source": inputs.site.rolling_threshold_source,
           "block_size_mapping": BLOCK_SIZE_MAPPING, "row_shapes": options.row_shapes,
           **({"dem_max_time_source": options.dem_time_source}
              if options.dem_time_source is not None else {}),
           "likelihood": "point: (1/n) sum_j N(y; r_j, sd^2 + v_j); interval: (1/n) sum_j "
                         "[Phi((b-r_j)/w_j) - Phi((a-r_j)/w_j)] (calib/inference/likelihood.py)",
           "n_observations": inputs.obs.n_obs,
           "velocities": _velocity_record(inputs.speeds),
           "fit_quality": {m: f.quality for m, (f, _, _) in fits.items()},
           "timings_s": {**{m: f.timings_s for m, (f, _, _) in fits.items()},
                         "total_s": total_s},
           **sections}
    return CalibrationFile.from_dict(doc)


def _velocity_record(vel) -> dict | None:
    """The passage speeds fitted (key ``velocities``), or None."""
    if vel is None:
        return None
    return {"csv": vel.path, "n_observations": vel.n_obs,
            "stations_m": [float(x) for x in vel.stations_m],
            "likelihood": "(1 - eps) (1/m) sum_{j passed} N(v; u_j, sd^2 + h_v^2) + eps / V_MAX "
                          "over the simulated blocks of the row's size that passed its "
                          "station (calib/inference/likelihood.py)"}


def posterior_files(fits: dict, obs) -> tuple[dict, dict]:
    """The posterior draws' files of one ``calib.fit`` run: (name -> CSV text,
    name -> NetCDF writer), ``<model>_posterior.csv`` (``posterior_csv_text``) and
    ``<model>_posterior.nc`` (ArviZ InferenceData with the rows ``obs``,
    ``calib.files.inference_data``) for every model fitted with a posterior.

    Args:
        fits: model -> (``ModelFit``, forward model, alpha-law form or None).
        obs: the rows fitted (``calib.files.observations.Observations``).
    """
    from calib.files.calibration_file import posterior_csv_text
    from calib.files.inference_data import inference_data, netcdf_writer

    texts, writers = {}, {}
    for model, (fit, _, _) in fits.items():
        post = fit.posterior
        if post is not None:
            texts[f"{model}_posterior.csv"] = posterior_csv_text(fit.names, post.samples)
            writers[f"{model}_posterior.nc"] = netcdf_writer(inference_data(post, obs, model))
    return texts, writers
