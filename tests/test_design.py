"""``calib.design``: design values against a hand computation from exact sample
quantiles, the kit choice, probabilities without partial factors against exact
fractions, impacts, the sheet's outputs, and bad input (one line, exit 2, nothing
written). Hazard files are built from synthetic samples (no simulation)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from test_hazard_results import synthetic_results

from calib.design import (
    DEFAULTS,
    SOURCES,
    check_kits,
    design_values,
    impacts,
    kit_probabilities,
    load_kits,
    smallest_passing,
)
from calib.design.__main__ import main
from calib.design._inputs import design_block
from calib.files.hazard_results import write_hazard_results

SIZES = [0.5, 2.0]
STATIONS = [0.0, 50.0, 100.0, 150.0, 200.0, 250.0]
N_BLOCKS = 500
DENSITY = 2350.0


def _samples(n_draws=4, seed=0):
    """Passers at 50, 100, 150 m (none at 200 and 250 m): speed U(10, 20) m/s,
    clearance 0 for 20 % (rolling) else exponential(0.5 m), energy of a rolling
    sphere 7/10 m v^2."""
    rng = np.random.default_rng(seed)
    out = {}
    for d in range(n_draws):
        for i, size in enumerate(SIZES):
            mass = math.pi / 6 * size**3 * DENSITY
            for j in (1, 2, 3):
                n = N_BLOCKS - 50 * j
                v = rng.uniform(10.0, 20.0, n)
                h = np.where(rng.random(n) < 0.2, 0.0, rng.exponential(0.5, n))
                out[(d, i, j)] = {"velocity_m_s": v, "bounce_height_m": h,
                                  "energy_kJ": 0.7 * mass * v**2 / 1000.0}
    return out


def _hazard(tmp_path, name="hazard.nc", samples=None, **kw):
    attrs = {"release_rate_per_year": 2.0, "rock_density_kg_m3": DENSITY,
             "adequacy_json": {"ok": True, "problems": [], "message": None,
                               "predictive": "posterior predictive",
                               "coverage": {"levels": {"0.5": {"n_covered": 1, "n_rows": 2},
                                                       "0.9": {"n_covered": 2,
                                                               "n_rows": 2}}}}}
    attrs.update(kw.pop("attrs", {}))
    ds = synthetic_results(samples or _samples(), sizes_m=SIZES, stations_x_m=STATIONS,
                           n_blocks=N_BLOCKS, profile=((0.0, 150.0), (100.0, 30.0),
                                                       (300.0, 0.0)), attrs=attrs, **kw)
    path = tmp_path / name
    write_hazard_results(ds, str(path))
    return str(path), ds


KITS = os.path.abspath("data/barrier_kits.csv")


@pytest.fixture(scope="module")
def hazard(tmp_path_factory):
    """The shared synthetic hazard file (read only): (path, Dataset)."""
    return _hazard(tmp_path_factory.mktemp("hazard"))


def _args(**kw):
    from calib.design.__main__ import build_parser

    a = build_parser().parse_args(["x.nc", "--barrier-x-m", "100"])
    for k, v in kw.items():
        setattr(a, k, v)
    return a


# ------------------------------------------------------------------- the numbers

def test_design_values_equal_the_formulas_on_exact_quantiles(hazard):
    """v_d = v95 gamma_Tr gamma_Dp, h_d = (h95 + D) gamma_Tr gamma_Dp, m_d = Vol rho
    gamma_VolF gamma_gamma, E_sd = 1/2 m_d v_d^2, with v95, h95 the exact 95th
    percentiles of the pooled synthetic passers; the file's values come from 0.23 %
    bins, so v_d agrees within 0.23 %, E_sd within 0.46 %."""
    path, ds = hazard
    samples = _samples()
    block, warnings = design_block(ds, path)
    assert block.size_m == 2.0 and not warnings and block.density_kg_m3 == DENSITY
    f = DEFAULTS
    dv = design_values(ds, 100.0, block, f, 95.0, 1.0)
    pool = {q: np.concatenate([samples[(d, 1, 2)][q] for d in range(4)])
            for q in ("velocity_m_s", "bounce_height_m")}
    v95 = np.quantile(pool["velocity_m_s"], 0.95, method="inverted_cdf")
    h95 = np.quantile(pool["bounce_height_m"], 0.95, method="inverted_cdf") + 2.0
    speed = f.gamma_Tr * f.gamma_Dp
    m_d = math.pi / 6 * 8.0 * DENSITY * f.gamma_VolF * f.gamma_gamma
    assert dv.design["v_d_m_s"] == pytest.approx(v95 * speed, rel=2.3e-3)
    assert dv.design["h_d_m"] == pytest.approx(h95 * speed, rel=2.3e-3)
    assert dv.design["m_d_kg"] == pytest.approx(m_d, rel=1e-12)
    assert dv.design["E_sd_kJ"] == pytest.approx(0.5 * m_d * (v95 * speed) ** 2 / 1000,
                                                 rel=4.6e-3)
    assert dv.design["design_height_m"] == pytest.approx(dv.design["h_d_m"] + 1.0)
    # the total energy: rolling spheres carry 7/5 of the translational energy
    assert dv.design["E_total_kJ"] == pytest.approx(1.4 * dv.design["E_sd_kJ"], rel=1e-2)
    # bands over draws hold the pooled design value
    lo, hi = dv.bands["v_d_m_s"]
    assert lo <= dv.design["v_d_m_s"] * (1 + 2.3e-3) and hi >= dv.design["v_d_m_s"] * (
        1 - 2.3e-3)
    # Monte Carlo error: 1800 pooled passers give about 1 % on v95 (U(10, 20))
    m = dv.mc["v_p_m_s"]
    assert 0.002 < m["rel_half_width"] < 0.02 and m["met"]
    assert m["blocks_per_draw_for_target"] == math.ceil(
        N_BLOCKS * (m["rel_half_width"] / 0.02) ** 2)


def test_smallest_passing_kit_and_each_check(hazard):
    """E_sd ~ 2.6 MJ: MEL / 1.2 must exceed it (3000 kJ: 2500 fails, 4500 kJ passes);
    a 130 m distance passes every elongation, 5 m fails every one."""
    path, ds = hazard
    kits = load_kits(KITS)
    block, _ = design_block(ds, path)
    dv = design_values(ds, 100.0, block, DEFAULTS, 95.0, 1.0)
    assert 2500.0 < dv.design["E_sd_kJ"] < 3750.0, dv.design["E_sd_kJ"]
    rows = check_kits(kits, dv, level="MEL", gamma_e=1.2, protected_distance_m=130.0)
    best = smallest_passing(rows)
    assert best["kit"] == "generic-4500kJ"
    assert all(r["energy_ok"] == (r["mel_kJ"] / 1.2 >= dv.design["E_sd_kJ"]) for r in rows)
    assert all(r["height_ok"] == (r["nominal_height_m"] >= dv.design["design_height_m"])
               for r in rows)
    near = check_kits(kits, dv, level="MEL", gamma_e=1.2, protected_distance_m=5.0)
    assert smallest_passing(near) is None
    assert not any(r["elongation_ok"] for r in near if r["max_elongation_m"] >= 4.0)
    # against the SEL (gamma_E 1.0): the 100 kJ class has none and fails
    sel = check_kits(kits, dv, level="SEL", gamma_e=1.0, protected_distance_m=130.0)
    assert not sel[0]["energy_ok"] and "no SEL" in sel[0]["note"]
    # a worse residual-height category than accepted fails
    kit_b = kits[-1]._replace(residual_height_category="B")
    assert not check_kits([kit_b], dv, level="MEL", gamma_e=1.2, protected_distance_m=130.0,
                          min_category="A")[0]["category_ok"]


def test_probabilities_without_factors_equal_exact_fractions(hazard):
    """P(E > MEL | reach) per draw from the 50-per-decade histograms against the exact
    fraction of each draw's samples: they differ by at most the share of the samples
    in the bin holding the threshold (the within-bin interpolation)."""
    path, ds = hazard
    samples = _samples()
    kits = {k.name: k for k in load_kits(KITS)}
    block, _ = design_block(ds, path)
    dv = design_values(ds, 100.0, block, DEFAULTS, 95.0, 1.0)
    kit = kits["generic-1500kJ"]
    p = kit_probabilities(ds, dv, kit, "MEL")
    width = 10 ** (1 / 50)
    for d in range(4):
        e = samples[(d, 1, 2)]["energy_kJ"]
        exact = np.mean(e > kit.mel_kJ)
        in_bin = np.mean((e >= kit.mel_kJ / width) & (e < kit.mel_kJ * width))
        assert abs(p["P_E_gt_MEL"]["per_draw"][d] - exact) <= in_bin + 1e-12
        h = samples[(d, 1, 2)]["bounce_height_m"] + 2.0
        exact_h = np.mean(h > kit.nominal_height_m)
        in_bin_h = np.mean((h - 2 >= (kit.nominal_height_m - 2) / width)
                           & (h - 2 < (kit.nominal_height_m - 2) * width))
        assert abs(p["P_h_gt_nominal_height"]["per_draw"][d] - exact_h) <= in_bin_h + 1e-12
    assert 0.0 < p["P_E_gt_MEL"]["mean"] < 1.0


def test_impacts_are_poisson_counts_of_the_passers(hazard):
    from scipy.stats import poisson

    path, ds = hazard
    kits = {k.name: k for k in load_kits(KITS)}
    block, _ = design_block(ds, path)
    dv = design_values(ds, 100.0, block, DEFAULTS, 95.0, 1.0)
    kit = kits["generic-3000kJ"]
    out = impacts(ds, dv, kit, 2.0, 3.0)
    lam = 2.0 * (N_BLOCKS - 100) / N_BLOCKS
    assert out["impacts_per_yr"]["mean"] == pytest.approx(lam)
    p_sel = kit_probabilities(ds, dv, kit, "SEL")["P_E_gt_SEL"]["per_draw"]
    mu = lam * p_sel * 3.0
    np.testing.assert_allclose(np.mean(poisson.sf(1, mu)),
                               out["P_more_than_one_sel_impact"]["mean"], rtol=1e-12)


def test_shipped_kits_are_the_energy_classes_of_etag_027():
    """MEL and SEL of each class as ETAG 027's table of energy levels gives them (the
    100 kJ class has no SEL); the 5000 kJ row, in the open class "> 4500 kJ", takes the
    table's rule SEL = MEL / 3 (data/README.md)."""
    kits = load_kits(KITS)
    assert [k.mel_kJ for k in kits] == [100, 250, 500, 1000, 1500, 2000, 3000, 4500, 5000]
    assert [k.sel_kJ for k in kits] == [None, 85, 170, 330, 500, 660, 1000, 1500, 1666.7]
    assert all(k.name.startswith("generic-") for k in kits)
    with open(KITS) as fh:
        text = fh.read()
    assert "GENERIC" in text and "NOT products" in text


# -------------------------------------------------------------------- the command

def _run(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr()


def test_command_writes_the_sheet(hazard, tmp_path, capsys):
    path, _ = hazard
    out = tmp_path / "design"
    code, cap = _run([path, "--barrier-x-m", "100", "--kits", KITS, "--out", str(out),
                      "--scan-x-m", "50:150:50"], capsys)
    assert code == 0
    names = sorted(os.listdir(out))
    assert names == ["design.json", "design.md", "design_distributions.png",
                     "design_exceedance.png", "design_profile.png", "design_scan.csv",
                     "design_scan.png"]
    rec = json.loads((out / "design.json").read_text())
    assert rec["kit_checked"]["kit"] == "generic-4500kJ"
    assert rec["protected_distance_m"] == 150.0  # the road at 250 m
    assert {f["factor"] for f in rec["factors"]} == {"gamma_Tr", "gamma_Dp", "gamma_VolF",
                                                     "gamma_gamma", "gamma_E"}
    assert all(f["source"] == SOURCES[f["factor"]] for f in rec["factors"])
    assert rec["impacts"]["impacts_per_yr"]["mean"] == pytest.approx(1.6)
    assert len(rec["scan"]) == 3
    md = (out / "design.md").read_text()
    for text in ("NOT a product", "gamma_Tr", "unverified", "2D", "lateral spread",
                 "generic-4500kJ", "Monte Carlo error", "No flag raised", "[R]"):
        assert text in md, text
    v_err = rec["mc"]["v_p_m_s"]["rel_half_width"]
    assert f"| {200 * v_err:.2g} % (twice the speed's: E_sd ~ v_p^2) |" in md
    assert "generic-4500kJ" in cap.out


def test_failed_calibration_check_is_loud(tmp_path, capsys):
    path, _ = _hazard(tmp_path, attrs={"adequacy_json": {
        "ok": False, "problems": ["only 0 of 2 rows inside"],
        "message": "the model may not be able to fit these data"}})
    out = tmp_path / "d"
    code, cap = _run([path, "--barrier-x-m", "100", "--kits", KITS, "--out", str(out)],
                     capsys)
    assert code == 0
    assert "FAILED ITS OWN PREDICTIVE CHECK" in (out / "design.md").read_text()
    assert "!!! THE CALIBRATION FAILED" in cap.err


def test_failed_posterior_diagnostics_are_loud(tmp_path, capsys):
    """A calibration whose posterior failed its diagnostics (here the GP's
    realisation check) is said so on the sheet and on stderr, even where its
    predictive check raised no flag."""
    path, _ = _hazard(tmp_path, attrs={
        "adequacy_json": {"ok": True, "problems": []},
        "posterior_check_json": {"ok": False, "problems": [
            "the intervals are narrower than the log-likelihood GP's own uncertainty"]}})
    out = tmp_path / "d"
    code, cap = _run([path, "--barrier-x-m", "100", "--kits", KITS, "--out", str(out)],
                     capsys)
    assert code == 0
    md = (out / "design.md").read_text()
    assert "POSTERIOR FAILED ITS DIAGNOSTICS" in md and "GP's own uncertainty" in md
    assert "POSTERIOR FAILED ITS DIAGNOSTICS" in cap.err
    assert json.loads((out / "design.json").read_text())["posterior_check"]["ok"] is False


def test_a_run_that_broke_its_blocks_is_said_so(tmp_path, capsys):
    """A hazard file of a fragmentation run (attribute ``fragmentation``): the sheet
    and stderr say that its values at the barrier are per parent block, the
    largest among its pieces, against the unbroken block's design mass."""
    path, _ = _hazard(tmp_path, attrs={"fragmentation": "CRSP WHAT-IF: E_f = 300 kJ"})
    out = tmp_path / "d"
    code, cap = _run([path, "--barrier-x-m", "100", "--kits", KITS, "--out", str(out)],
                     capsys)
    assert code == 0
    for text in ((out / "design.md").read_text(), cap.err):
        assert "broke its blocks (CRSP WHAT-IF: E_f = 300 kJ)" in text
        assert "largest among its pieces" in text


def test_the_hazard_record_carries_the_posterior_verdict():
    """The hazard file's calibration record keeps the posterior's verdict (the
    design sheet reads it); a fit without a posterior has none."""
    from calib.hazard._results import _posterior_check

    assert _posterior_check({"ok": False, "problems": ["R-hat"]}) == {
        "ok": False, "problems": ["R-hat"]}
    assert _posterior_check(None) is None


BARRIER = {"barrier_x_m": 100.0, "barrier_height_m": 3.0, "barrier_capacity_kJ": 500.0}


def test_residual_exceedance_of_a_run_with_the_barrier(hazard, tmp_path, capsys):
    """The run with the barrier's exceedance and reach beside the run without it (the
    blocks it stops no longer pass 100 m and beyond), with their bands over draws; a
    run on other stations, a "with" run without a barrier, a "without" run with one
    and a barrier elsewhere than the design's are refused before anything is
    computed."""
    from calib.design import residual_exceedance
    from calib.design._design import _residual

    path, ds = hazard
    fewer = {k: v for k, v in _samples().items() if k[2] == 1}  # stopped by the barrier
    with_barrier = synthetic_results(fewer, sizes_m=SIZES, stations_x_m=STATIONS,
                                     n_blocks=N_BLOCKS, attrs=dict(BARRIER))
    t = residual_exceedance(ds, with_barrier)
    at = t[(t.block_size_m == 2.0) & (t.x_m == 100.0)].iloc[0]
    assert at.p_exceed_mean == pytest.approx((N_BLOCKS - 100) / N_BLOCKS)
    assert at.reach_prob_mean == pytest.approx((N_BLOCKS - 100) / N_BLOCKS)
    assert at.p_exceed_mean_with_barrier == 0.0 and at.reach_prob_q95_with_barrier == 0.0
    before = t[(t.block_size_m == 2.0) & (t.x_m == 50.0)].iloc[0]
    assert before.reach_prob_mean_with_barrier == before.reach_prob_mean > 0
    assert np.isnan(residual_exceedance(ds).p_exceed_mean_with_barrier).all()
    road = synthetic_results(_samples(), sizes_m=SIZES, stations_x_m=STATIONS,
                             n_blocks=N_BLOCKS, attrs={"road_x_m": 150.0})
    text = _residual(road, with_barrier)["text"]
    assert "with the barrier" in text and "P(reach)" in text and "capacity 500 kJ" in text
    other = synthetic_results(_samples(), sizes_m=SIZES, stations_x_m=STATIONS[:-1],
                              n_blocks=N_BLOCKS, attrs=dict(BARRIER))
    write_hazard_results(other, str(tmp_path / "other.nc"))
    write_hazard_results(synthetic_results(fewer, sizes_m=SIZES, stations_x_m=STATIONS,
                                           n_blocks=N_BLOCKS), str(tmp_path / "none.nc"))
    write_hazard_results(synthetic_results(fewer, sizes_m=SIZES, stations_x_m=STATIONS,
                                           n_blocks=N_BLOCKS,
                                           attrs=dict(BARRIER, barrier_x_m=150.0)),
                         str(tmp_path / "at150.nc"))
    write_hazard_results(with_barrier, str(tmp_path / "with.nc"))
    for name, message in (("other.nc", "other.nc: its x_m differ"),
                          ("none.nc", "none.nc: not a run with a barrier"),
                          ("at150.nc", "its barrier stands at x = 150 m, the design at x = "
                                       "100 m")):
        with pytest.raises(SystemExit) as e:
            main([path, "--barrier-x-m", "100", "--kits", KITS, "--out", str(tmp_path / "x"),
                  "--with-barrier", str(tmp_path / name)])
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "x").exists()
    with pytest.raises(SystemExit) as e:  # the "without" run has a barrier
        main([str(tmp_path / "with.nc"), "--barrier-x-m", "100", "--kits", KITS, "--out",
              str(tmp_path / "x"), "--with-barrier", str(tmp_path / "with.nc")])
    assert e.value.code == 2 and "has a barrier too" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_density_from_the_file_else_the_default_with_a_warning(hazard, tmp_path):
    """The file's rock density (the calibration's) is the default; without one, 2350
    kg/m^3 and a warning; another density than the run simulated scales the energies
    by mass and says so."""
    path, ds = hazard
    block, warnings = design_block(ds, path)
    assert block.density_kg_m3 == DENSITY and not warnings
    bare = ds.copy()
    del bare.attrs["rock_density_kg_m3"]
    block, warnings = design_block(bare, path)
    assert block.density_kg_m3 == 2350.0 and "no rock density" in warnings[0]
    block, warnings = design_block(ds, path, density_kg_m3=2650.0)
    assert block.energy_scale == pytest.approx(2650.0 / DENSITY)
    assert "simulated blocks of 2350 kg/m^3" in warnings[0]


def test_dem_run_needs_a_thickness_and_scales_by_it(tmp_path, capsys):
    """A DEM file's energies are per cube of side D: with --dem-thickness-m t the design
    block is D^2 t and the simulated energies scale by t / D."""
    cube = [DENSITY * s**3 for s in SIZES]
    path, ds = _hazard(tmp_path, model="dem", block_mass_kg=cube)
    with pytest.raises(SystemExit) as e:
        main([path, "--barrier-x-m", "100", "--kits", KITS, "--out", str(tmp_path / "a")])
    assert e.value.code == 2 and "--dem-thickness-m" in capsys.readouterr().err
    block, _ = design_block(ds, path, thickness_m=1.0)
    assert block.volume_m3 == pytest.approx(4.0)
    assert block.energy_scale == pytest.approx(0.5)


def _kits_file(tmp_path, text):
    p = tmp_path / "kits.csv"
    p.write_text(text)
    return str(p)


HEADER = "kit,mel_kJ,sel_kJ,nominal_height_m,residual_height_category,max_elongation_m\n"
BAD = {
    "unknown kit": (["--kit", "nope"], None, "--kit nope: not in"),
    "outside the profile": (["--barrier-x-m", "400"], None, "outside the profile [0, 300]"),
    "at the release": (["--barrier-x-m", "0"], None, "at or above the release at x = 0 m"),
    "below the road": (["--barrier-x-m", "250"], None, "at or below the road"),
    "not a station": (["--barrier-x-m", "75"], None, "75: not a station of"),
    "no passers": (["--barrier-x-m", "200"], None, "no simulated block of D = 2 m passes"),
    "zero factor": (["--gamma-tr", "0"], None, "--gamma-tr: expected a positive factor"),
    "negative factor": (["--gamma-e", "-1.2"], None, "--gamma-e: expected a positive factor"),
    "empty kits": ([], "", "no header and no kits"),
    "header only": ([], "# comment\n" + HEADER, "no kit rows after the header (line 2)"),
    "malformed kits": ([], HEADER + "a,500,166,3,A,4\nb,abc,1,3,A,4\n",
                       "line 3, column mel_kJ: expected a positive number, got 'abc'"),
    "missing column": ([], "kit,mel_kJ\na,100\n", "line 1: missing column(s) sel_kJ"),
    "bad category": ([], HEADER + "a,500,166,3,D,4\n",
                     "line 2, column residual_height_category"),
    "sel above mel": ([], HEADER + "a,500,600,3,A,4\n", "line 2, column sel_kJ"),
    "size not in the run": (["--block-size-m", "0.7"], None, "--block-size-m 0.7: not a "
                                                             "block size"),
    "free board": (["--free-board-m", "0.2"], None, "--free-board-m 0.2: below the minimum"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_one_line_exit_2_nothing_written(case, hazard, tmp_path, capsys):
    extra, kits_text, needle = BAD[case]
    path, _ = hazard
    kits = KITS if kits_text is None else _kits_file(tmp_path, kits_text)
    argv = [path, "--barrier-x-m", "100", "--kits", kits, "--out", str(tmp_path / "out")]
    argv += extra
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert err.count("\n") == 1 and needle in err, err
    assert not (tmp_path / "out").exists()


def test_hazard_file_of_another_schema_exit_2_in_a_real_process(hazard, tmp_path):
    path, ds = hazard
    old = ds.copy()
    old.attrs["schema"] = "rockfall-hazard-results/0"
    old.to_netcdf(tmp_path / "old.nc", engine="h5netcdf")
    r = subprocess.run([sys.executable, "-m", "calib.design", str(tmp_path / "old.nc"),
                        "--barrier-x-m", "100", "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "old.nc: attribute 'schema'" in r.stderr
    assert not (tmp_path / "o").exists()


def test_percentile_99_option_designs_on_the_99th(hazard, tmp_path, capsys):
    """--percentile 99 (ONR 24810): v_d and h_d from the exact 99th percentiles of the
    pooled passers (0.23 % bins), the sheet says p99, and its Monte Carlo error is the
    99th's (wider than the 95th's on the same blocks)."""
    path, ds = hazard
    samples = _samples()
    pool = {q: np.concatenate([samples[(d, 1, 2)][q] for d in range(4)])
            for q in ("velocity_m_s", "bounce_height_m")}
    out = tmp_path / "p99"
    code, _ = _run([path, "--barrier-x-m", "100", "--kits", KITS, "--out", str(out),
                    "--percentile", "99"], capsys)
    assert code == 0
    rec = json.loads((out / "design.json").read_text())
    speed = DEFAULTS.gamma_Tr * DEFAULTS.gamma_Dp
    v99 = np.quantile(pool["velocity_m_s"], 0.99, method="inverted_cdf")
    h99 = np.quantile(pool["bounce_height_m"], 0.99, method="inverted_cdf") + 2.0
    assert rec["percentile"] == 99.0
    assert rec["design"]["v_d_m_s"] == pytest.approx(v99 * speed, rel=2.3e-3)
    assert rec["design"]["h_d_m"] == pytest.approx(h99 * speed, rel=2.3e-3)
    block, _ = design_block(ds, path)
    p95 = design_values(ds, 100.0, block, DEFAULTS, 95.0, 1.0)
    assert rec["mc"]["h_p_m"]["rel_half_width"] > p95.mc["h_p_m"]["rel_half_width"]
    assert "| p99 simulated |" in (out / "design.md").read_text()
