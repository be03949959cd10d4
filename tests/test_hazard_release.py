"""Release conditions of the hazard run (``calib.model.release``, ``calib.hazard
--volume-law / --volumes-csv / --release-zone-m / --release-height-m ...``): the
volume laws against their own definitions, draws against their laws
(Kolmogorov-Smirnov and binomial bounds), the classes, the T-year block, the key of
each block, a seeded run of one fixed size against the run without release
conditions (the same blocks), the class tables, the fixed-size tables unchanged to
the byte, and bad input (one line, exit 2, nothing written)."""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from cli_run import run_cli
from scipy import stats
from test_hazard_fixtures import posterior_rows, write_calibration

from calib.files.block_survey import BlockSurveyError, read_block_survey
from calib.hazard import draw_parameters, load_calibration, run_hazard
from calib.hazard.__main__ import main
from calib.hazard._units import draw_key, seeded_chunk
from calib.model.release import (
    ReleaseState,
    ReleaseZone,
    Seeder,
    VolumeLaw,
    diameter_m,
    parse_release_zone,
    parse_volume_law,
    sample_release,
    volume_classes,
)
from solvers import crsp, load_profile

N_DRAWS = 20000  # release draws per distribution test: KS critical value ~1 %
LOGNORMAL = "lognormal:median_m3=0.3,sigma=1"
POWERLAW = "powerlaw:vmin_m3=0.01,vmax_m3=20,b=0.7"
# the small run of tests/test_hazard_cli.py (its compiled pool is reused in one process)
SMALL = ["--n-posterior", "3", "--n-blocks", "400", "--stations-m", "0:300:10",
         "--no-progress"]


@functools.partial(jax.jit, static_argnames=("kinds", "n"))
def _sample(seeds, key, kinds, n):
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(n, dtype=jnp.uint32))
    return jax.vmap(lambda k: sample_release(seeds, kinds, k))(keys)


def _draws(seeder: Seeder, t: int, n: int = N_DRAWS, seed: int = 0):
    """n releases of class t, blocks 0 .. n - 1 of draw 0 (NumPy arrays)."""
    out = _sample(seeder.arrays(t), draw_key(seed, 0), seeder.kinds, n)
    return tuple(np.asarray(a) for a in out)


def _seeder(law, zone="0:5", state=ReleaseState(), edges=None):
    return Seeder(law, tuple(volume_classes(law, edges)), parse_release_zone(zone), state)


# ------------------------------------------------------------- laws and classes

def test_laws_follow_their_definitions():
    """Q(F(v)) = v; lognormal F(median) = 1/2 and the sigma of ln V; the truncated
    power law's F = (vmin^-b - v^-b) / (vmin^-b - vmax^-b); the survey's F = the
    fraction strictly below and Q(p) = v_(floor(p n) + 1)."""
    ln, pw = parse_volume_law(LOGNORMAL), parse_volume_law(POWERLAW)
    v = np.geomspace(0.02, 10.0, 7)
    for law in (ln, pw):
        np.testing.assert_allclose(law.quantile(law.cdf(v)), v, rtol=1e-9)
    assert ln.cdf(0.3) == pytest.approx(0.5)
    assert ln.cdf(0.3 * math.e) == pytest.approx(stats.norm.cdf(1.0))
    lo, hi, b = 0.01, 20.0, 0.7
    np.testing.assert_allclose(pw.cdf(v), (lo**-b - v**-b) / (lo**-b - hi**-b), rtol=1e-12)
    assert pw.support_m3 == (0.01, 20.0)
    emp = VolumeLaw("empirical", (0.1, 0.2, 0.2, 0.5, 1.0), "survey")
    np.testing.assert_array_equal(emp.cdf([0.2, 0.3, 1.0, 2.0]), [0.2, 0.6, 0.8, 1.0])
    np.testing.assert_array_equal(emp.quantile([0.0, 0.39, 0.4, 0.99]), [0.1, 0.2, 0.2, 1.0])


def test_draws_follow_the_law_within_each_class():
    """Each class's blocks follow the law restricted to the class (KS test at 0.1 %;
    a wrong inverse or a class range off by one fails it), lie inside the class, and
    their sphere diameter is (6 V / pi)^(1/3)."""
    for text in (LOGNORMAL, POWERLAW):
        law = parse_volume_law(text)
        seeder = _seeder(law)
        assert sum(c.probability for c in seeder.classes) == pytest.approx(1.0)
        for t, c in enumerate(seeder.classes):
            vol, d, *_ = _draws(seeder, t)
            assert np.all((vol >= c.volume_min_m3) & (vol <= c.volume_max_m3)), (text, t)
            np.testing.assert_allclose(d, diameter_m(vol), rtol=1e-12)

            def cond_cdf(v, c=c, law=law):
                return (law.cdf(v) - c.p_lo) / c.probability

            assert stats.kstest(vol, cond_cdf).pvalue > 1e-3, (text, t)


def test_survey_draws_resample_the_survey_within_each_class():
    """A survey class draws its own surveyed volumes, each equally often (chi-square
    at 0.1 %), never another class's."""
    vols = np.round(np.geomspace(0.05, 8.0, 40), 4)
    law = VolumeLaw("empirical", tuple(vols), "survey")
    seeder = _seeder(law)
    assert [round(c.probability * 40) for c in seeder.classes] == [20, 16, 3, 1]
    for t, c in enumerate(seeder.classes):
        vol = _draws(seeder, t, 8000)[0]
        mine = vols[(vols >= c.volume_min_m3) & (vols <= c.volume_max_m3)]
        assert set(np.unique(vol)) == set(mine)
        if mine.size > 1:
            counts = np.array([np.sum(vol == v) for v in mine])
            assert stats.chisquare(counts).pvalue > 1e-3


def test_zone_height_and_speed_draws():
    """Uniform zone: uniform on [A, B] (KS); points: each with its weight (binomial,
    4.5 standard errors); heights a normal truncated to >= 0, the solver's
    release-error rule (KS against scipy's truncnorm); a NaN mean keeps the
    solver's default (NaN)."""
    law = parse_volume_law(LOGNORMAL)
    s = _seeder(law, "10:30", ReleaseState(0.5, 0.5, 2.0, 0.0))
    _, _, x, h, v = _draws(s, 0)
    assert stats.kstest(x, stats.uniform(10.0, 20.0).cdf).pvalue > 1e-3
    assert stats.kstest(h, stats.truncnorm(-1.0, np.inf, loc=0.5, scale=0.5).cdf).pvalue > 1e-3
    assert np.all(h >= 0) and np.all(v == 2.0)
    s = _seeder(law, "10:1,20:3")
    _, _, x, h, v = _draws(s, 0)
    assert set(np.unique(x)) == {10.0, 20.0} and np.isnan(h).all() and np.isnan(v).all()
    assert abs(np.mean(x == 20.0) - 0.75) < 4.5 * math.sqrt(0.75 * 0.25 / N_DRAWS)


def test_a_blocks_release_depends_on_its_index_only():
    """Block j's draws are a function of fold_in(K_d, j): the same in a batch of 8 or
    of 3, and different from block j + 1's."""
    s = _seeder(parse_volume_law(POWERLAW), "0:5", ReleaseState(1.0, 0.2, 1.0, 0.3))
    a = _draws(s, 1, 8)
    b = _draws(s, 1, 3)
    for u, w in zip(a, b, strict=True):
        np.testing.assert_array_equal(u[:3], w)
        assert len(np.unique(u)) == 8


def test_classes_edges_and_refusals():
    """Default edges at the 50/90/99 % quantiles; given edges; a class without blocks
    and edges out of order are refused; the representative size names the class."""
    law = parse_volume_law(POWERLAW)
    cls = volume_classes(law)
    np.testing.assert_allclose([c.p_hi for c in cls[:-1]], [0.5, 0.9, 0.99], rtol=1e-9)
    for c in cls:
        assert c.volume_min_m3 <= c.volume_m3 <= c.volume_max_m3
        assert c.size_m == pytest.approx(diameter_m(c.volume_m3), rel=5e-3)
    cls = volume_classes(law, [0.1, 1.0])
    assert [(c.volume_min_m3, c.volume_max_m3) for c in cls] == [(0.01, 0.1), (0.1, 1.0),
                                                                 (1.0, 20.0)]
    with pytest.raises(ValueError, match="holds no block"):
        volume_classes(law, [1.0, 30.0])
    with pytest.raises(ValueError, match="increasing"):
        volume_classes(law, [1.0, 0.5])


def test_return_period_block():
    """The T-year block of R blocks a year solves R (1 - F(V_T)) = 1/T: for the
    truncated power law, V_T^-b = vmax^-b + (vmin^-b - vmax^-b) / (R T); R T < 1 has
    none."""
    law = parse_volume_law(POWERLAW)
    lo, hi, b = 0.01, 20.0, 0.7
    for rate, t in ((2.0, 100.0), (50.0, 30.0)):
        expected = (hi**-b + (lo**-b - hi**-b) / (rate * t)) ** (-1 / b)
        assert law.return_period_volume_m3(t, rate) == pytest.approx(expected, rel=1e-9)
        assert rate * (1 - law.cdf(expected)) == pytest.approx(1 / t, rel=1e-9)
    with pytest.raises(ValueError, match="fewer than one block"):
        law.return_period_volume_m3(10.0, 0.05)


def test_extrapolated_fraction_of_a_class():
    """The share of a class's blocks outside the fitted sizes, by the law's CDF at the
    volumes of the smallest and largest fitted size; a fixed size is in or out."""
    law = parse_volume_law(LOGNORMAL)
    s = _seeder(law)
    fitted = [0.2, 1.2]
    v_lo, v_hi = (math.pi / 6 * d**3 for d in fitted)
    frac = s.extrapolated_fraction(fitted)
    for c, f in zip(s.classes, frac, strict=True):
        below = max(0.0, min(float(law.cdf(v_lo)), c.p_hi) - c.p_lo)
        above = max(0.0, c.p_hi - max(float(law.cdf(v_hi)), c.p_lo))
        # rel: the method widens the fitted range by 1e-9 of its largest size
        assert f == pytest.approx((below + above) / c.probability, rel=1e-6, abs=1e-12)
    assert 0 < frac[0] < 0.05 and frac[-1] == pytest.approx(1.0)
    fixed = Seeder.fixed_sizes([0.5, 2.0], ReleaseZone("point", (0.0,)))
    np.testing.assert_array_equal(fixed.extrapolated_fraction(fitted), [0.0, 1.0])


def test_parse_errors_name_the_option():
    for text, msg in (("gamma:k=1", "unknown law 'gamma'"),
                      ("lognormal:median_m3=0.3", "sigma missing"),
                      ("lognormal:median_m3=x,sigma=1", "median_m3: expected a number"),
                      ("powerlaw:vmin_m3=2,vmax_m3=1,b=1", "vmax_m3 > vmin_m3"),
                      ("powerlaw:vmin_m3=1,vmax_m3=2,b=-1", "b: expected a positive")):
        with pytest.raises(ValueError, match="--volume-law") as e:
            parse_volume_law(text)
        assert msg in str(e.value)
    for text in ("5:2", "1:x", "3", "1:1,2:0"):
        with pytest.raises(ValueError, match="--release-zone-m"):
            parse_release_zone(text)
    assert parse_release_zone("2:5") == ReleaseZone("uniform", (2.0, 5.0))


def test_block_survey(tmp_path):
    """Volumes as given; masses divided by the density; bad cells refused naming the
    file, line and column."""
    (tmp_path / "v.csv").write_text("id,volume_m3\na,0.5\nb,0.1\n\nc,2\n")
    law = read_block_survey(str(tmp_path / "v.csv"), 2500.0)
    assert law.values == (0.1, 0.5, 2.0) and law.kind == "empirical"
    (tmp_path / "m.csv").write_text("mass_kg\n250\n5000\n")
    assert read_block_survey(str(tmp_path / "m.csv"), 2500.0).values == (0.1, 2.0)
    for text, msg in (("volume_m3\n0.5\n-1\n", "line 3: column 'volume_m3': expected a "
                                               "positive number"),
                      ("volume_m3\n0.5\nabc\n", "line 3: column 'volume_m3': expected a "
                                                "number"),
                      ("size\n0.5\n", "line 1: expected one column"),
                      ("volume_m3,mass_kg\n1,2\n", "line 1: expected one column"),
                      ("volume_m3\n", "no rows")):
        (tmp_path / "bad.csv").write_text(text)
        with pytest.raises(BlockSurveyError) as e:
            read_block_survey(str(tmp_path / "bad.csv"), 2500.0)
        assert msg in str(e.value) and str(tmp_path / "bad.csv") in str(e.value)


# ------------------------------------------------------------------ simulations

@pytest.fixture(scope="module")
def cal_path(tmp_path_factory):
    return write_calibration(tmp_path_factory.mktemp("cal"), crsp_posterior=posterior_rows(50))


# the command's solver settings (its default --max-events): one compiled program serves
# these runs and the command's
SETTINGS = crsp.Settings(max_events=5000)


def _run(cal_path, **kw):
    cal = load_calibration(cal_path, "crsp")
    profile = load_profile(cal.profile_csv)
    draws = draw_parameters(cal, 3, 0)
    return run_hazard(cal, draws, profile, kw.pop("sizes", None), np.arange(0.0, 301.0, 10.0),
                      400, 0, settings=SETTINGS, **kw)


@pytest.mark.slow  # its own compiled program (about 30 s on 2 shared cores): -m slow
@pytest.mark.parametrize("shapes", [None, ("cylinder", "disc")])
def test_one_fixed_size_through_the_release_path_is_the_same_run(cal_path, shapes):
    """Blocks of fixed sizes released at one point through the per-block path
    (``_units.seeded_chunk``: every block its own task, keyed as block j of the draw)
    are the blocks of the run without release conditions: the same counts at every
    station and the same histograms; spheres, and blocks of other shapes."""
    plain = _run(cal_path, sizes=[0.5, 2.0], shapes=shapes)
    seeded = _run(cal_path, release=Seeder.fixed_sizes([0.5, 2.0],
                                                       ReleaseZone("point", (0.0,)),
                                                       shapes=shapes))
    for k in ("exceed", "reach", "e30", "e300", "n_unfinished", "n_left_profile"):
        np.testing.assert_array_equal(getattr(seeded, k), getattr(plain, k), err_msg=k)
    for q in plain.hist:
        np.testing.assert_array_equal(seeded.hist[q], plain.hist[q], err_msg=q)
    np.testing.assert_allclose(seeded.block_mass_kg, plain.block_mass_kg, rtol=1e-15)


def test_a_chunk_counts_its_blocks_whatever_their_place(cal_path, class_run):
    """Blocks 0..399 of a class in one chunk count as blocks 0..199 plus blocks
    200..399 each run at the head of a chunk of the same compiled size (``n_valid``
    masks the rest): a block's volume, release and impacts depend on its index in
    the draw, not on its place in a chunk. (The chunk of ``class_run``'s program.)"""
    cal = load_calibration(cal_path, "crsp")
    profile = load_profile(cal.profile_csv)
    law = parse_volume_law(LOGNORMAL)
    seeder = _seeder(law, "0:5", ReleaseState(1.0, 0.3, 1.0, 0.2))
    p = crsp.params_from_profile(profile, Kn=0.4, Kt=0.87, roughness_m=2.0)
    stations = jnp.asarray(np.arange(0.0, 301.0, 10.0))
    kw = dict(n_chunk=400, pool=256, kinds=seeder.kinds, settings=SETTINGS)

    def chunk(off, n_valid):  # the arguments as calib.hazard._run passes them
        args = (p, seeder.arrays(2), jnp.asarray(2350.0, jnp.float64), draw_key(0, 0),
                profile, stations, jnp.asarray(off, jnp.int32), jnp.asarray(n_valid, jnp.int32))
        return seeded_chunk(*jax.device_put(args, jax.devices()[0]), **kw)

    whole, head, tail = chunk(0, 400), chunk(0, 200), chunk(200, 200)
    for name in whole._fields:
        a = np.asarray(getattr(whole, name))
        np.testing.assert_array_equal(a, np.asarray(getattr(head, name))
                                      + np.asarray(getattr(tail, name)), err_msg=name)
    assert np.asarray(whole.reach).max() == 400  # every block passed a station


# ------------------------------------------------------------------ the command

# the run SMALL + --block-sizes-m 0.5,2.0 --release-rate-per-year 0.2, as written before
# the hazard run had release conditions (same calibration fixture): exceedance.csv, the
# simulated reach counted per station, by its bytes; hazard_table.csv by value
# (tests/data/README.md), its floats to a relative 1e-9: its energy and height
# percentiles pass through NumPy's vectorised float functions (np.log in the binned
# quantiles), whose last bits depend on the SIMD extensions NumPy dispatches to: the
# same install (numpy 2.4.6, jax 0.10.2) writes other
# bytes on a CPU with AVX-512 than with NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL",
# measured 2026-12-04: at most 4e-16 apart, relative
EXCEEDANCE_SHA256 = "a5738e864fa6333f1f3e3b3a173fe390f4ad053beee90d0e1cbbae2a362f74d2"
FIXED_SIZES_TABLE = os.path.join(os.path.dirname(__file__), "data",
                                 "hazard_table_fixed_sizes.csv")
TABLE_RTOL = 1e-9


def _sha(path):
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def test_fixed_sizes_write_the_same_table_as_before(cal_path, tmp_path, capsys):
    """The simple case, fixed sizes released at one point: exceedance.csv byte for
    byte and hazard_table.csv value for value as before release conditions existed,
    and hazard.nc with no variable or attribute of the release conditions."""
    import xarray as xr

    rc, _, _ = run_cli(main, [cal_path, *SMALL, "--block-sizes-m", "0.5,2.0",
                              "--release-rate-per-year", "0.2", "--out", str(tmp_path)], capsys)
    assert rc == 0
    assert _sha(tmp_path / "exceedance.csv") == EXCEEDANCE_SHA256
    got = pd.read_csv(tmp_path / "hazard_table.csv")
    want = pd.read_csv(FIXED_SIZES_TABLE)
    assert list(got.columns) == list(want.columns)
    for col in want.columns:
        if pd.api.types.is_float_dtype(want[col]):
            np.testing.assert_allclose(got[col], want[col], rtol=TABLE_RTOL, atol=0.0,
                                       equal_nan=True, err_msg=col)
        else:
            assert got[col].fillna("").tolist() == want[col].fillna("").tolist(), col
    with xr.open_dataset(tmp_path / "hazard.nc", engine="h5netcdf") as ds:
        assert not [k for k in ds.data_vars if k.startswith("class_") or "extrapol" in k]
        assert not [k for k in ds.attrs if k.startswith(("release_json", "fitted", "barrier",
                                                         "design_block"))]


@pytest.fixture(scope="module")
def class_run(cal_path, tmp_path_factory):
    """A lognormal run over the default classes, released on 0-5 m at 1 m (sd 0.3),
    with a release rate and a 50-year design block."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("classes")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main([cal_path, *SMALL, "--volume-law", LOGNORMAL, "--release-zone-m", "0:5",
                     "--release-height-m", "1", "--release-height-sd-m", "0.3",
                     "--release-rate-per-year", "2", "--return-period-yr", "50",
                     "--out", str(out)]) == 0
    return out, buf.getvalue()


def test_class_tables_hazard_nc_and_summary(class_run):
    """One row per class and station with the class columns; a class's frequencies
    are R P(class) P(reach | class); the classes and the extrapolated share in
    hazard.nc; the summary names the zone, the classes, the extrapolation and the
    50-year block."""
    from calib.files.hazard_results import read_hazard_results

    out, stdout = class_run
    table = pd.read_csv(out / "hazard_table.csv")
    law = parse_volume_law(LOGNORMAL)
    classes = volume_classes(law)
    assert list(table.columns[:8]) == ["model", "block_size_m", "volume_class",
                                       "class_volume_min_m3", "class_volume_max_m3",
                                       "class_probability", "extrapolated",
                                       "extrapolated_fraction"]
    assert len(table) == 4 * 31
    sizes = sorted(set(table.block_size_m))
    assert sizes == [c.size_m for c in classes]
    ok = table.reach_prob_mean.notna()
    np.testing.assert_allclose(table.freq_reach_per_yr[ok], 2.0 * table.class_probability[ok]
                               * table.reach_prob_mean[ok], rtol=1e-12)
    # the calibration was fitted on 0.2 and 2 m blocks (data/postignano.csv): the top
    # class reaches beyond 2 m
    top = table[table.block_size_m == sizes[-1]].iloc[0]
    assert bool(top.extrapolated) and 0 < top.extrapolated_fraction < 1
    ds = read_hazard_results(str(out / "hazard.nc"))
    np.testing.assert_allclose(ds["class_probability"].values, [c.probability for c in classes])
    assert ds.attrs["fitted_block_size_max_m"] == 2.0
    assert "volume_class" in pd.read_csv(out / "exceedance.csv").columns
    summary = (out / "summary.txt").read_text()
    assert summary.strip() in stdout
    assert "uniformly on x = 0-5 m" in summary and "height 1 m (sd 0.3" in summary
    assert "extrapolation" in summary and "50-year return period" in summary
    v_t = law.return_period_volume_m3(50.0, 2.0)
    assert f"V = {v_t:.3g} m3" in summary


# ------------------------------------------------------------------ bad input

@pytest.mark.parametrize("extra, message", [
    (["--volume-law", LOGNORMAL, "--block-sizes-m", "0.5"], "give fixed sizes or a volume "
                                                            "distribution"),
    (["--volume-law", LOGNORMAL, "--volumes-csv", "x.csv"], "give one volume distribution"),
    (["--volume-law", "lognormal:sigma=1"], "--volume-law lognormal:sigma=1: median_m3 "
                                            "missing"),
    (["--volume-classes-m3", "0.1"], "--volume-classes-m3: needs a volume distribution"),
    (["--volume-law", LOGNORMAL, "--volume-classes-m3", "1,0.5"], "increasing"),
    (["--volume-law", LOGNORMAL, "--return-period-yr", "50"], "needs --release-rate-per-year"),
    (["--volume-law", LOGNORMAL, "--return-period-yr", "5", "--release-rate-per-year",
      "0.1"], "fewer than one block in 5 years"),
    (["--volumes-csv", "missing.csv"], "missing.csv: file not found"),
    (["--release-zone-m", "0:5", "--release-x-m", "2"], "give one of them"),
    (["--release-zone-m", "250:290"], "lies at or downslope of the station of interest"),
    (["--release-zone-m=-5:5"], "outside the profile"),
    (["--release-height-m", "-1"], "--release-height-m -1: expected a number >= 0"),
    (["--release-speed-sd-m-s", "0.5"], "needs --release-speed-m-s"),
    (["--model", "dem", "--volume-law", LOGNORMAL], "the DEM hazard run takes fixed sizes"),
    (["--block-shape", "cube"], "--block-shape: expected sphere, cylinder, disc, got 'cube'"),
    (["--block-shape", "disc,disc,disc"], "expected one shape or 4 (one per size"),
    (["--model", "dem", "--block-shape", "disc"], "the DEM's blocks are squares"),
])
def test_bad_release_options_one_line_exit_2_nothing_written(cal_path, tmp_path, capsys,
                                                             extra, message):
    out = tmp_path / "out"  # the fixture calibrates both models
    rc, _, err = run_cli(main, [cal_path, *SMALL, *extra, "--out", str(out)], capsys)
    assert rc == 2, err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and not os.path.exists(out)


def test_design_on_an_extrapolated_class_warns(class_run, tmp_path, capsys):
    """calib.design on a run over classes: the largest class by default, named by its
    representative size, and a warning where its blocks reach beyond the fitted sizes."""
    from calib.design.__main__ import main as design

    out, _ = class_run
    rc, stdout, err = run_cli(design, [str(out / "hazard.nc"), "--barrier-x-m", "100",
                                       "--kits", os.path.abspath("data/barrier_kits.csv"),
                                       "--out", str(tmp_path / "design")], capsys)
    assert rc == 0, err
    top = volume_classes(parse_volume_law(LOGNORMAL))[-1]
    assert f"D = {top.size_m:g} m" in stdout
    assert "of the blocks of the design class" in err and "extrapolation" in err


# ------------------------------------------------------------ CRSP shape classes

@pytest.mark.parametrize("shape", crsp.SHAPES)
def test_a_shape_of_a_spheres_volume_has_the_spheres_mass(shape):
    """``solvers.crsp.shape_constants``: the block of ``shape`` whose radius is s
    times a sphere's weighs what the sphere weighs (make_block at its default
    length), and k is the shape's inertia ratio."""
    s, k = crsp.shape_constants(shape)
    for r in (0.1, 0.7, 2.3):
        block = crsp.make_block(s * r, shape)
        assert math.isclose(float(block.mass_kg), float(crsp.make_block(r).mass_kg),
                            rel_tol=1e-13)
        assert float(block.inertia_ratio) == k
    assert crsp.shape_constants("sphere")[0] == 1.0


def test_each_block_is_the_shape_of_its_class():
    """``_units.seeded_tasks``: a fixed size D of a shape is the block of that shape
    with the volume of the sphere of diameter D (radius s D / 2, the mass make_block
    gives it, to the bit, rho pi D^3 / 6 to rounding); a volume drawn from a law is
    the block of that shape and volume (radius (V / (c pi))^(1/3), mass rho V)."""
    from calib.hazard._units import seeded_tasks

    rho = 2350.0
    p = crsp.params_from_profile(load_profile("data/postignano_profile.csv"))
    key = draw_key(0, 0)
    fixed = Seeder.fixed_sizes([0.5, 2.0], ReleaseZone("point", (0.0,)),
                               shapes=("cylinder", "disc"))
    for t, (d, shape) in enumerate(((0.5, "cylinder"), (2.0, "disc"))):
        _, b = seeded_tasks(p, fixed.arrays(t), rho, key, 0, n_chunk=8, kinds=fixed.kinds)
        want = crsp.make_block(0.5 * d * crsp.shape_constants(shape)[0], shape,
                               density_kg_m3=rho)
        assert np.all(np.asarray(b.radius_m) == float(want.radius_m))
        assert np.all(np.asarray(b.mass_kg) == float(want.mass_kg))
        np.testing.assert_allclose(np.asarray(b.mass_kg), rho * np.pi * d**3 / 6, rtol=1e-12)
        assert np.all(np.asarray(b.inertia_ratio) == float(want.inertia_ratio))
    law = parse_volume_law(LOGNORMAL)
    for shape, c in (("disc", 0.5), ("cylinder", 2.0), ("sphere", 4.0 / 3.0)):
        seeder = Seeder(law, tuple(volume_classes(law)), ReleaseZone("point", (0.0,)),
                        shapes=(shape,) * len(volume_classes(law)))
        _, b = seeded_tasks(p, seeder.arrays(1), rho, key, 0, n_chunk=64, kinds=seeder.kinds)
        volume = np.asarray(b.mass_kg) / rho
        np.testing.assert_allclose(np.asarray(b.radius_m), np.cbrt(volume / (c * np.pi)),
                                   rtol=1e-12)


def test_the_command_runs_the_shape_it_is_given(cal_path, tmp_path, capsys):
    """--block-shape cylinder: every block of the size the CRSP cylinder of the
    volume of the sphere of diameter D (hazard.nc's block_shape and block_mass_kg),
    the summary says so and that the fit simulated spheres only, and the design
    sheet names the cylinder."""
    import xarray as xr

    from calib.design.__main__ import main as design

    out = tmp_path / "out"
    rc, _, err = run_cli(main, [cal_path, *SMALL, "--block-sizes-m", "2.0", "--block-shape",
                                "cylinder", "--out", str(out)], capsys)
    assert rc == 0, err
    with xr.open_dataset(out / "hazard.nc", engine="h5netcdf") as ds:
        assert [str(v) for v in ds["block_shape"].values] == ["cylinder"]
        rho = load_calibration(cal_path, "crsp").rock_density_kg_m3
        assert math.isclose(float(ds["block_mass_kg"].values[0]), rho * math.pi * 8 / 6,
                            rel_tol=1e-12)
    summary = (out / "summary.txt").read_text()
    assert "blocks: CRSP shape classes cylinder (D = 2 m)" in summary
    assert "the fit simulated sphere only: cylinder extrapolates the calibration" in summary
    rc, _, err = run_cli(design, [str(out / "hazard.nc"), "--barrier-x-m", "100", "--kits",
                                  os.path.abspath("data/barrier_kits.csv"), "--out",
                                  str(tmp_path / "design")], capsys)
    assert rc == 0, err
    record = json.loads((tmp_path / "design" / "design.json").read_text())
    assert "cylinder" in json.dumps(record)
