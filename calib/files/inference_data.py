"""Posteriors as ArviZ InferenceData: ``{model}_posterior.nc`` (NetCDF-4), built
from a NUTS run (``calib.inference.bayes.Posterior``) and read back.

ArviZ's InferenceData schema (https://python.arviz.org/projects/base/en/latest/
schema/schema.html; here an ``xarray.DataTree`` of ``arviz_base``) with groups:

* ``posterior``: one variable per parameter, dims (chain, draw), in the units
  of the calibration (``calib.model.priors``);
* ``sample_stats``: NumPyro's per-draw statistics under ArviZ's names
  (``diverging``, ``acceptance_rate``, ``n_steps``, ``energy``, ``lp``,
  ``step_size``), dims (chain, draw);
* ``log_likelihood``: the EMULATED log-likelihood that NUTS sampled at each
  draw (the group's ``likelihood`` attribute says which), not a
  re-simulation, in nats: ``runout_m`` (chain, draw, row), log p(y_i | theta)
  of each observation row (``calib.inference.likelihood`` on the quantile
  emulator's runouts, its variance added), or, where the fit emulated the
  rows' SUMMED log-likelihood (CRSP inside its focus region,
  ``calib.inference.loglik_emulator``), ``total`` (chain, draw) only: no
  per-row values, so no PSIS-LOO over rows; the DEM's fits store under
  ``total`` the log of the posterior averaged over the quantile emulator's
  realisations, less the log prior (``calib.inference.quantile_realisations``),
  likewise without per-row values;
* ``observed_data``: the rows (dim row, file order): ``block_size_m``,
  ``runout_m``, ``runout_sd_m`` (NaN for intervals), ``runout_min_m``,
  ``runout_max_m`` (NaN for points), ``is_interval``.

``runout_m`` is named alike in ``log_likelihood`` and ``observed_data``, as
ArviZ pairs them (e.g. for PSIS-LOO with ``arviz_stats.loo``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["EXPECTED_NOTE", "LIKELIHOOD_NOTE", "SUMMED_NOTE", "inference_data", "netcdf_writer",
           "read_inference_data"]

LIKELIHOOD_NOTE = ("emulated: calib.inference.likelihood on the Gaussian-process emulator's runout "
                   "quantiles with its predictive variance added (calib.inference.calibrate), the "
                   "density NUTS sampled; not a re-simulation")
SUMMED_NOTE = ("emulated: the expected rows' summed simulated log-likelihood, capped, under a "
               "Gaussian process of its log deficit below a ceiling "
               "(calib.inference.loglik_emulator), the density NUTS sampled; not a "
               "re-simulation, and no per-row values")
EXPECTED_NOTE = ("emulated: the log of the posterior averaged over realisations of the "
                 "Gaussian processes of the runout quantiles, less the log prior "
                 "(calib.inference.quantile_realisations), the density the draws were taken "
                 "from on a grid; not a re-simulation, and no per-row values")
_ONE_COLUMN = {"summed": SUMMED_NOTE, "expected": EXPECTED_NOTE}


def inference_data(post, obs, model: str):
    """The InferenceData of one NUTS posterior (see module docstring).

    Args:
        post: ``calib.inference.bayes.Posterior`` with C = ``n_chains`` chains of N draws.
        obs: ``calib.files.observations.Observations`` the fit used (n_obs rows).
        model: "crsp" or "dem" (stored as the ``model`` attribute).

    Returns:
        ``xarray.DataTree`` with groups posterior, sample_stats, log_likelihood,
        observed_data.
    """
    from arviz_base import from_dict

    c = int(post.n_chains)
    by_chain = np.asarray(post.samples).reshape(c, -1, len(post.names))
    n_draws = by_chain.shape[1]
    loglik = np.asarray(post.pointwise_loglik).reshape(c, n_draws, -1)
    summed = post.loglik_kind in _ONE_COLUMN
    if summed:
        if loglik.shape[-1] != 1:
            raise ValueError(f"a {post.loglik_kind} log density has one column, not "
                             f"{loglik.shape[-1]}")
    elif loglik.shape[-1] != obs.n_obs:
        raise ValueError(f"the posterior's log-likelihood has {loglik.shape[-1]} rows, the "
                         f"observations {obs.n_obs}")
    rows = {"block_size_m": obs.block_size_m, "runout_m": obs.runout_m,
            "runout_sd_m": obs.runout_sd_m, "runout_min_m": obs.runout_min_m,
            "runout_max_m": obs.runout_max_m, "is_interval": obs.is_interval}
    tree = from_dict(
        {"posterior": {n: by_chain[..., i] for i, n in enumerate(post.names)},
         "sample_stats": {k: np.asarray(v) for k, v in post.sample_stats.items()},
         "log_likelihood": ({"total": loglik[..., 0]} if summed else {"runout_m": loglik}),
         "observed_data": {k: np.asarray(v) for k, v in rows.items()}},
        dims={k: ["row"] for k in rows}, coords={"row": np.arange(obs.n_obs)})
    tree.attrs.update(model=model, observations=obs.path)
    tree["log_likelihood"].attrs["likelihood"] = _ONE_COLUMN.get(post.loglik_kind,
                                                                LIKELIHOOD_NOTE)
    tree["log_likelihood"]["total" if summed else "runout_m"].attrs["units"] = "nats"
    return tree


def netcdf_writer(tree):
    """A ``write(path)`` callable for ``solvers.cli.write_all_atomic`` that writes
    ``tree`` as NetCDF-4 (h5netcdf engine)."""
    def write(path):
        tree.to_netcdf(path, engine="h5netcdf")
    return write


def read_inference_data(path: str):
    """Read a ``{model}_posterior.nc`` back, fully loaded (the file is closed).

    Returns:
        ``xarray.DataTree`` with the groups of ``inference_data``.
    """
    import xarray as xr

    with xr.open_datatree(path, engine="h5netcdf") as tree:
        return tree.load()
