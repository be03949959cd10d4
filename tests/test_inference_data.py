"""Posteriors as ArviZ InferenceData (``calib.files.inference_data``): the NetCDF file
reads back equal to what was written."""

from __future__ import annotations

import os

import numpy as np
import pytest
import xarray as xr

from calib.files.inference_data import inference_data, netcdf_writer, read_inference_data
from calib.files.observations import Observations
from calib.inference.bayes import Posterior
from solvers.cli import write_all_atomic


def _posterior(rng, n_chains=2, n_draws=7, n_rows=3):
    n = n_chains * n_draws
    stats = {"diverging": rng.uniform(size=(n_chains, n_draws)) < 0.1,
             "acceptance_rate": rng.uniform(size=(n_chains, n_draws)),
             "n_steps": rng.integers(1, 64, size=(n_chains, n_draws)),
             "lp": rng.normal(size=(n_chains, n_draws))}
    return Posterior(("Kn", "Kt"), rng.uniform(size=(n, 2)), rng.normal(size=n),
                     rng.normal(size=(n, n_rows)), np.ones(2), np.full(2, 500.0),
                     np.full(2, 450.0), 0, 0.9, True, [], n_chains, stats)


def _observations():
    nan = np.nan
    return Observations(np.array([0.2, 0.9, 2.0]), np.array([40.0, nan, 120.0]),
                        np.array([5.0, nan, 5.0]), np.array([nan, 60.0, nan]),
                        np.array([nan, 80.0, nan]), np.array([False, True, False]),
                        ("a", "b", "c"), path="rows.csv")


def test_inference_data_round_trips_through_netcdf(tmp_path):
    rng = np.random.default_rng(0)
    post, obs = _posterior(rng), _observations()
    tree = inference_data(post, obs, "crsp")
    path = str(tmp_path / "crsp_posterior.nc")
    old = os.umask(0o027)
    try:
        write_all_atomic({path: netcdf_writer(tree)})  # as calib.fit writes it
    finally:
        os.umask(old)
    assert os.stat(path).st_mode & 0o777 == 0o640
    back = read_inference_data(path)
    xr.testing.assert_identical(back, tree)
    assert set(back.children) == {"posterior", "sample_stats", "log_likelihood",
                                  "observed_data"}
    # the groups hold the Posterior's arrays, chain after chain
    np.testing.assert_array_equal(back["posterior"]["Kt"].values,
                                  post.samples[:, 1].reshape(2, 7))
    np.testing.assert_array_equal(back["log_likelihood"]["runout_m"].values,
                                  post.pointwise_loglik.reshape(2, 7, 3))
    assert back["log_likelihood"]["runout_m"].dims == ("chain", "draw", "row")
    assert "emulated" in back["log_likelihood"].attrs["likelihood"]
    assert back["sample_stats"]["diverging"].dtype == bool
    np.testing.assert_array_equal(back["observed_data"]["runout_min_m"].values,
                                  obs.runout_min_m)
    assert back.attrs["model"] == "crsp"


@pytest.mark.parametrize("kind", ["summed", "expected"])
def test_a_summed_log_likelihood_is_stored_as_its_total_only(tmp_path, kind):
    """A fit that emulated the rows' summed log-likelihood (CRSP in its focus
    region), or the DEM's posterior averaged over its emulator's realisations,
    has no per-row values: the group holds ``total`` (chain, draw) and says
    which it is."""
    import dataclasses

    from calib.files.inference_data import EXPECTED_NOTE, SUMMED_NOTE

    rng = np.random.default_rng(1)
    post = _posterior(rng)
    post = dataclasses.replace(post, pointwise_loglik=post.pointwise_loglik.sum(1)[:, None],
                               loglik_kind=kind)
    tree = inference_data(post, _observations(), "crsp")
    path = str(tmp_path / "crsp_posterior.nc")
    write_all_atomic({path: netcdf_writer(tree)})
    back = read_inference_data(path)
    assert list(back["log_likelihood"].data_vars) == ["total"]
    assert back["log_likelihood"]["total"].dims == ("chain", "draw")
    np.testing.assert_array_equal(back["log_likelihood"]["total"].values,
                                  post.pointwise_loglik.reshape(2, 7))
    assert back["log_likelihood"].attrs["likelihood"] == {"summed": SUMMED_NOTE,
                                                          "expected": EXPECTED_NOTE}[kind]
