"""The hazard results file (``calib.files.hazard_results``): round trip, refusal of other
schemas, the fine bins' error against exact quantiles of synthetic samples, the
coverage of the percentiles' Monte Carlo intervals, and a run's tables written from
the Dataset. ``synthetic_results`` builds a small results Dataset from per-block
samples without simulating (also used by ``test_design.py``)."""

from __future__ import annotations

import math
import shlex

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import solvers  # noqa: F401  (float64)
from calib.files.hazard_results import (
    SCHEMA,
    HazardResultsError,
    hazard_results,
    json_attr,
    read_hazard_results,
    write_hazard_results,
)
from calib.hazard._stats import (
    BINS,
    DRAW_BINS,
    DRAW_SUB,
    FINE,
    FINE_BINS,
    PERCENTILES,
    hist_quantile,
    percentile_interval,
    percentile_table,
    rebin,
)

QUANTITIES = ("energy_kJ", "velocity_m_s", "bounce_height_m")


_INDEX = {q: jax.jit(lambda v, b=b: b.index(v, FINE)) for q, b in BINS.items()}


def _fine_index(values, q) -> np.ndarray:
    """The fine bin of each value, as a run's chunks count them (``Bins.index``)."""
    return np.asarray(_INDEX[q](jnp.asarray(np.asarray(values, float))))


def _fine_counts(values, q) -> np.ndarray:
    return np.bincount(_fine_index(values, q), minlength=FINE_BINS[q].n)


def synthetic_results(samples, *, sizes_m, stations_x_m, n_blocks, release_x_m=0.0,
                      profile=((0.0, 100.0), (300.0, 0.0)), model="crsp", attrs=None,
                      block_mass_kg=None):
    """A results Dataset from per-block samples, as ``calib.hazard`` would record them.

    Args:
        samples: dict (draw, size index, station index) -> dict quantity -> (n,) values
            of the passers (missing keys: no passers).
        sizes_m, stations_x_m: coordinates.
        n_blocks: blocks per draw and size (passers <= n_blocks).
        release_x_m, profile ((x, z) vertices), model, attrs: as in a run.
        block_mass_kg: (T,) masses (default: spheres of 2350 kg/m^3).
    """
    n_draws = 1 + max(k[0] for k in samples)
    t, s, p = len(sizes_m), len(stations_x_m), len(PERCENTILES)
    shape = (n_draws, t, s)
    fine = {q: np.zeros(shape + (FINE_BINS[q].n,), np.int64) for q in QUANTITIES}
    reach = np.zeros(shape, np.int64)
    e30, e300 = np.zeros(shape, np.int64), np.zeros(shape, np.int64)
    keys = list(samples)
    for (d, i, j), vals in samples.items():
        reach[d, i, j] = len(vals["energy_kJ"])
        e30[d, i, j] = np.sum(vals["energy_kJ"] > 30.0)
        e300[d, i, j] = np.sum(vals["energy_kJ"] > 300.0)
    for q in QUANTITIES:  # one call per quantity: every sample concatenated
        k = _fine_index(np.concatenate([samples[key][q] for key in keys]), q)
        for key, part in zip(keys, np.split(k, np.cumsum([reach[key] for key in keys])[:-1]),
                             strict=True):
            fine[q][key] = np.bincount(part, minlength=FINE_BINS[q].n)
    data = {"n_exceed": reach.copy(), "n_reach": reach, "n_reach_E_gt_30kJ": e30,
            "n_reach_E_gt_300kJ": e300, "n_unfinished": np.zeros((n_draws, t), np.int64),
            "n_left_profile": np.zeros((n_draws, t), np.int64),
            "energy_p95_binned_kJ": hist_quantile(rebin(fine["energy_kJ"], FINE), 0.95,
                                                  BINS["energy_kJ"]),
            "block_mass_kg": (np.pi / 6 * np.asarray(sizes_m) ** 3 * 2350.0
                              if block_mass_kg is None else np.asarray(block_mass_kg)),
            "parameter_value": np.full((n_draws, 1), 0.4), "posterior_row":
            np.arange(1, n_draws + 1), "zone": np.asarray(["slope"] * s, dtype=object),
            "profile_x_m": np.asarray([v[0] for v in profile], float),
            "profile_z_m": np.asarray([v[1] for v in profile], float)}
    bins = {}
    for q in QUANTITIES:
        data[f"hist_{q}"] = rebin(fine[q].sum(axis=0), FINE)
        bins[f"hist_{q}"] = BINS[q]
        per = percentile_table(fine[q], FINE_BINS[q])
        pooled = percentile_table(fine[q].sum(axis=0), FINE_BINS[q])
        for j, end in enumerate(("", "_lo", "_hi")):
            data[f"{q}_pct{end}"] = per[j]
            data[f"{q}_pct_pooled{end}"] = pooled[j]
    for q in ("energy_kJ", "bounce_height_m"):
        data[f"draw_hist_{q}"] = rebin(fine[q], DRAW_SUB).astype(np.int32)
        bins[f"draw_hist_{q}"] = DRAW_BINS[q]
    coords = {"draw": np.arange(n_draws), "block_size_m": np.asarray(sizes_m, float),
              "x_m": np.asarray(stations_x_m, float), "percentile": np.asarray(PERCENTILES),
              "parameter": np.asarray(["Kn"], dtype=object),
              "vertex": np.arange(len(profile))}
    base = {"model": model, "n_blocks_per_draw": int(n_blocks), "release_x_m": release_x_m,
            "seed": 0, "draws_source": "posterior", "energy_basis": "kJ per block",
            "height_convention": "clearance", "provenance_json": {"command": "synthetic"},
            "road_x_m": 250.0, "road_label": "road"}
    base.update(attrs or {})
    assert p == 3
    return hazard_results(data, coords, base, bins)


def _small(seed=0, n_draws=3, n=400):
    rng = np.random.default_rng(seed)
    samples = {}
    for d in range(n_draws):
        for j in (1, 2):
            m = n - 40 * j
            samples[(d, 0, j)] = {"energy_kJ": rng.lognormal(4.0, 0.6, m),
                                  "velocity_m_s": rng.uniform(8.0, 16.0, m),
                                  "bounce_height_m": np.where(rng.random(m) < 0.3, 0.0,
                                                              rng.exponential(1.0, m))}
    return synthetic_results(samples, sizes_m=[1.0], stations_x_m=[0.0, 100.0, 200.0],
                             n_blocks=n, attrs={"release_rate_per_year": 0.5,
                                                "adequacy_json": {"ok": True, "problems": []}})


# ------------------------------------------------------------------ the file object

def test_round_trip_keeps_every_variable_unit_and_attribute(tmp_path):
    ds = _small()
    path = tmp_path / "hazard.nc"
    write_hazard_results(ds, str(path))
    back = read_hazard_results(str(path))
    assert back.attrs["schema"] == SCHEMA
    for name in ds.data_vars:
        np.testing.assert_array_equal(back[name].values, ds[name].values, err_msg=name)
        assert back[name].attrs == ds[name].attrs, name
        assert back[name].dims == ds[name].dims, name
    for c in ds.coords:
        np.testing.assert_array_equal(back[c].values, ds[c].values, err_msg=c)
    assert float(back.attrs["release_rate_per_year"]) == 0.5
    assert json_attr(back, "adequacy_json") == {"ok": True, "problems": []}
    assert json_attr(back, "provenance_json") == {"command": "synthetic"}
    assert back["energy_kJ_pct"].attrs["units"] == "kJ"
    assert back["velocity_m_s_pct_pooled"].attrs["units"] == "m s-1"


def test_another_schema_or_not_netcdf_is_refused_in_one_line(tmp_path):
    ds = _small()
    other = ds.copy()
    other.attrs["schema"] = "rockfall-hazard-results/0"
    path = tmp_path / "old.nc"
    other.to_netcdf(path, engine="h5netcdf")
    with pytest.raises(HazardResultsError, match=r"old\.nc: attribute 'schema': expected "
                                                  r"'rockfall-hazard-results/1', got "):
        read_hazard_results(str(path))
    text = tmp_path / "hazard.nc"
    text.write_text("not a netcdf file\n")
    with pytest.raises(HazardResultsError, match="not a NetCDF-4 hazard results file") as e:
        read_hazard_results(str(text))
    assert "\n" not in str(e.value)
    missing = ds.drop_vars("n_reach")
    missing.to_netcdf(tmp_path / "m.nc", engine="h5netcdf")
    with pytest.raises(HazardResultsError, match="variable 'n_reach' missing"):
        read_hazard_results(str(tmp_path / "m.nc"))
    with pytest.raises(HazardResultsError, match="file not found"):
        read_hazard_results(str(tmp_path / "none.nc"))


# ---------------------------------------------------- fine bins and the error claim

def test_fine_bins_sum_to_the_table_bins_and_lie_within_one_fine_bin():
    """Nested bins: the 1000-per-decade counts sum to the 200-per-decade ones exactly
    (values on and next to bin edges included), both computed under jit as a run's
    chunks compute them, and the quantile read from them lies within one fine bin
    (10^(1/1000) - 1 = 0.23 %) of the exact sample quantile."""
    rng = np.random.default_rng(3)
    for q, b in BINS.items():
        edges = b.edges()
        v = np.concatenate([rng.lognormal(1.0, 2.0, 50000), edges[::37],
                            np.nextafter(edges[::37], 0), [0.0, b.v_min / 2, b.v_max * 2]])
        fine = _fine_counts(v, q)
        coarse = np.bincount(np.asarray(jax.jit(b.index)(jnp.asarray(v))), minlength=b.n)
        np.testing.assert_array_equal(rebin(fine, FINE), coarse, err_msg=q)
        w = rng.lognormal(1.0, 0.8, 20000)
        fw = _fine_counts(w, q)
        for p in (0.5, 0.95, 0.99):
            got = hist_quantile(fw, p, FINE_BINS[q])
            exact = np.quantile(w, p, method="inverted_cdf")
            assert abs(math.log10(got / exact)) <= 1.0 / FINE_BINS[q].per_decade + 1e-12


def test_percentile_interval_covers_the_true_quantile_95_percent_of_the_time():
    """R = 400 samples of n = 1500 lognormal values: the order-statistic interval read
    from the fine histogram holds the true p95 in at least 95 % of them (the interval
    is exact and conservative), less 3 binomial standard errors
    (3 sqrt(0.95 0.05 / 400) = 3.3 %)."""
    rng = np.random.default_rng(7)
    r, n, mu, sigma = 400, 1500, 2.0, 0.7
    true = math.exp(mu + sigma * 1.6448536269514722)
    v = rng.lognormal(mu, sigma, (r, n))
    b = BINS["energy_kJ"]
    k = np.asarray(b.index(jnp.asarray(v), FINE)) + np.arange(r)[:, None] * FINE_BINS[
        "energy_kJ"].n
    counts = np.bincount(k.ravel(), minlength=r * FINE_BINS["energy_kJ"].n).reshape(r, -1)
    value, lo, hi = percentile_interval(counts, 0.95, FINE_BINS["energy_kJ"])
    covered = np.mean((lo <= true) & (true <= hi))
    assert covered >= 0.95 - 3 * math.sqrt(0.95 * 0.05 / r), covered
    assert covered <= 0.995, covered  # not trivially wide
    exact = np.quantile(v, 0.95, axis=1, method="inverted_cdf")
    assert np.all(np.abs(np.log10(value / exact)) <= 1e-3 + 1e-12)


def test_interval_half_width_matches_a_percentile_bootstrap():
    """The same samples, a percentile bootstrap (B = 200 resamples): the mean over 20
    samples of n = 2000 of the ratio of half-widths is 1 within 15 % (each ratio varies
    by about 20 %, so the mean by about 5 %; 3 of those)."""
    rng = np.random.default_rng(11)
    ratios = []
    for _ in range(20):
        v = rng.lognormal(2.0, 0.7, 2000)
        _, lo, hi = percentile_interval(_fine_counts(v, "energy_kJ"), 0.95,
                                        FINE_BINS["energy_kJ"])
        boot = np.quantile(rng.choice(v, (200, v.size)), 0.95, axis=1, method="inverted_cdf")
        b_lo, b_hi = np.quantile(boot, [0.025, 0.975])
        ratios.append((hi - lo) / (b_hi - b_lo))
    assert abs(np.mean(ratios) - 1.0) < 0.15, np.mean(ratios)


def test_interval_needs_enough_values():
    """Fewer values than the level needs (n = 20 for p99): the upper end is NaN, so a
    design says the percentile's error is unknown, not small."""
    counts = _fine_counts(np.linspace(1.0, 2.0, 20), "energy_kJ")
    value, lo, hi = percentile_interval(counts, 0.99, FINE_BINS["energy_kJ"])
    assert np.isfinite(value) and np.isnan(hi)
    v, lo, hi = percentile_interval(np.zeros(FINE_BINS["energy_kJ"].n, int), 0.95,
                                    FINE_BINS["energy_kJ"])
    assert np.isnan(v) and np.isnan(lo) and np.isnan(hi)


# ----------------------------------------------------- a run: the tables from the file

@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    """``python -m calib.hazard`` in-process on the shapes of test_hazard_cli.py's run
    (a pytest process running both compiles once)."""
    import contextlib
    import io

    from test_hazard_cli import SMALL
    from test_hazard_fixtures import posterior_rows, write_calibration

    from calib.hazard.__main__ import main

    cal = write_calibration(tmp_path_factory.mktemp("cal"), crsp_posterior=posterior_rows(50))
    out = tmp_path_factory.mktemp("out")
    with contextlib.redirect_stdout(io.StringIO()):
        assert main([cal, *SMALL, "--release-rate-per-year", "0.2", "--out", str(out)]) == 0
    return cal, out


def test_run_writes_hazard_nc_and_its_csv_tables_come_from_it(cli_run):
    from calib.files.provenance import file_sha256
    from calib.hazard import exceedance_table, hazard_table

    cal, out = cli_run
    ds = read_hazard_results(str(out / "hazard.nc"))
    assert hazard_table(ds).to_csv(index=False) == (out / "hazard_table.csv").read_text()
    assert exceedance_table(ds).to_csv(index=False) == (out / "exceedance.csv").read_text()
    prov = json_attr(ds, "provenance_json")
    assert prov["inputs"]["calibration"]["sha256"] == file_sha256(cal)
    # the command run in this process with its own arguments, not pytest's
    from test_hazard_cli import SMALL

    assert prov["seed"] == 0 and prov["command"] == "python -m calib.hazard " + shlex.join(
        [cal, *SMALL, "--release-rate-per-year", "0.2", "--out", str(out)])
    assert float(ds.attrs["release_rate_per_year"]) == 0.2
    assert ds.sizes["draw"] == 3 and ds.sizes["percentile"] == 3
    # per-draw percentiles inside their own intervals, pooled ones bracketed by draws
    for q in QUANTITIES:
        v, lo, hi = (ds[f"{q}_pct{e}"].values for e in ("", "_lo", "_hi"))
        ok = np.isfinite(lo) & np.isfinite(hi)
        assert ok.any() and np.all((lo[ok] <= v[ok]) & (v[ok] <= hi[ok])), q
        pooled = ds[f"{q}_pct_pooled"].values
        fin = np.isfinite(pooled) & np.all(np.isfinite(v), axis=0)
        assert np.all(pooled[fin] >= np.min(v, axis=0)[fin] * (1 - 1e-9))
        assert np.all(pooled[fin] <= np.max(v, axis=0)[fin] * (1 + 1e-9))
    # the per-draw histograms hold every passer
    np.testing.assert_array_equal(ds["draw_hist_energy_kJ"].values.sum(-1), ds["n_reach"])
