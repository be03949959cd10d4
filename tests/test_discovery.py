"""The discrepancy workflow's parts (scores, residuals, warnings) and its two
commands, ``python -m calib.synth`` and ``python -m calib.discover`` (quick)."""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import numpy as np
import pytest
from cli_run import run_cli, run_module
from scipy import stats

from calib.discovery.discovery_warnings import (
    ess_warnings,
    gap_warnings,
    noise_warnings,
    psis_warnings,
)
from calib.discovery.discrepancy import size_classes
from calib.discovery.residuals import locate
from calib.discovery.scores import (
    Z_MIN,
    carrying_rows,
    crps_ensemble,
    cv_elpd,
    effective_rows,
    elpd_difference,
    folds,
    rows_needed,
)
from calib.files.observations import Observations
from solvers.profile import load_profile

PROFILE_CSV = "data/postignano_profile.csv"
PROFILE = load_profile(PROFILE_CSV)


_cli = run_module


def test_crps_of_an_ensemble_matches_the_gaussian_closed_form():
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 2.0, 40_000)
    for y in (3.0, 5.5, -1.0):
        z = (y - 3.0) / 2.0
        exact = 2.0 * (z * (2 * stats.norm.cdf(z) - 1) + 2 * stats.norm.pdf(z) - 1 / np.sqrt(np.pi))
        assert crps_ensemble(x, y) == pytest.approx(exact, rel=0.02)
    assert crps_ensemble(np.full(10, 4.0), 4.0) == pytest.approx(0.0, abs=1e-12)


def test_folds_are_balanced_and_loo_for_few_rows():
    g = np.repeat(np.arange(3), 10)
    f = folds(g, 5, seed=0)
    assert np.all(np.bincount(f) == 6)
    for c in range(3):
        assert np.all(np.bincount(f[g == c], minlength=5) == 2)
    np.testing.assert_array_equal(folds(np.zeros(3), 5, 0), [0, 1, 2])


def test_cv_elpd_by_hand():
    # two design points, three rows, leave-one-out
    ll = np.log(np.array([[0.5, 0.2, 0.1], [0.1, 0.4, 0.3]]))
    out, khat = cv_elpd(ll, np.zeros(2), np.arange(3))
    assert khat.shape == (3,) and np.all(np.isnan(khat))  # too few points for a tail fit
    for i in range(3):
        w = np.exp(ll[:, [j for j in range(3) if j != i]].sum(axis=1))
        w = w / w.sum()
        assert out[i] == pytest.approx(np.log(w @ np.exp(ll[:, i])))
    d, se = elpd_difference(np.array([1.0, 2.0, 3.0]), np.zeros(3))
    assert d == 6.0 and se == pytest.approx(np.sqrt(3 * 1.0))


def test_size_classes_bin_many_sizes():
    sizes = np.geomspace(0.2, 2.0, 40)
    reps, cls = size_classes(sizes, max_classes=8)
    assert reps.size == 8 and cls.min() == 0 and cls.max() == 7
    assert np.all(np.diff(reps) > 0)
    reps, cls = size_classes(np.array([0.2, 2.0, 0.2]))
    np.testing.assert_array_equal(reps, [0.2, 2.0])
    np.testing.assert_array_equal(cls, [0, 1, 0])


def test_locate_flags_the_size_class_that_is_off_and_nothing_else():
    rng = np.random.default_rng(2)
    sizes = np.repeat([0.2, 1.0, 2.0], 20)
    cls = np.repeat([0, 1, 2], 20)
    centre = np.array([120.0, 150.0, 200.0])
    samples = centre[:, None] + 10.0 * rng.standard_normal((3, 4000))
    y = centre[cls] + 10.0 * rng.standard_normal(60)
    ok = locate(Observations.points(sizes, y, 3.0), cls, np.array([0.2, 1.0, 2.0]), samples,
                PROFILE, rng)
    assert ok["flagged"] == [], ok["flagged"]
    y_bad = y + np.where(cls == 2, 25.0, 0.0)  # 2 m blocks travel 25 m further than modelled
    bad = locate(Observations.points(sizes, y_bad, 3.0), cls, np.array([0.2, 1.0, 2.0]),
                 samples, PROFILE, rng)
    flagged = [s["size_m"] for s in bad["by_size"] if s["flag"]]
    assert flagged == [2.0], bad["by_size"]
    assert "2.00 m travel further" in bad["summary"]


@pytest.fixture(scope="module")
def synth_files(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    proc = _cli("calib.synth", "--effect", "size_dissipation", "--strength", "2",
                "--n-obs", "36", "--seed", "11", "--profile", PROFILE_CSV,
                "--out", str(out / "synth.csv"))
    return proc, out


def test_synth_writes_data_truth_and_profile_but_hides_the_effect(synth_files):
    proc, out = synth_files
    assert proc.returncode == 0, proc.stderr
    assert {"synth.csv", "synth.truth.json", "synth_profile.csv", "synth_materials.csv"} <= \
        set(os.listdir(out))
    text = (out / "synth.csv").read_text()
    assert text.splitlines()[0] == ("block_size_m,runout_m,runout_sd_m,runout_min_m,"
                                    "runout_max_m,source")
    assert len(text.splitlines()) == 37
    assert "size" not in text.split("\n", 1)[1] and "dissipation" not in text
    truth = json.loads((out / "synth.truth.json").read_text())
    assert truth["effect"] == "size_dissipation" and truth["strength"] == 2.0
    assert truth["parameters"]["gamma"] == pytest.approx(0.5)


@pytest.mark.parametrize("args, needle", [
    (["--effect", "vegetation_belt", "--model", "dem"], "not available for the DEM"),
    (["--effect", "none", "--n-obs", "0"], "--n-obs"),
    (["--effect", "none", "--strength", "-1"], "--strength"),
    (["--effect", "bogus"], "invalid choice"),
    (["--effect", "none", "--sd-m", "0"], "--sd-m: expected a positive number of metres"),
])
def test_synth_bad_input_is_one_line_exit_2_nothing_written(tmp_path, args, needle, capsys):
    """``main`` in this process (a real process's exit status:
    ``test_synth_bad_input_exit_2_in_a_real_process``)."""
    from calib.synth import main

    rc, _, err = run_cli(main, ["--profile", PROFILE_CSV, *args,
                                "--out", str(tmp_path / "s.csv")], capsys)
    assert rc == 2
    assert needle in err and len(err.strip().splitlines()) == 1, err
    assert os.listdir(tmp_path) == []


def test_synth_bad_input_exit_2_in_a_real_process(tmp_path):
    proc = _cli("calib.synth", "--profile", PROFILE_CSV, "--effect", "none", "--n-obs", "0",
                "--out", str(tmp_path / "s.csv"))
    assert proc.returncode == 2
    assert "--n-obs" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert os.listdir(tmp_path) == []


@pytest.fixture(scope="module")
def discover_run(synth_files):
    _, out = synth_files
    proc = _cli("calib.discover", str(out / "synth.csv"), "--quick", "--out",
                str(out / "disc"), "--no-progress")
    return proc, out / "disc"


# slow: a quick `calib.discover` on synthetic rows, 48 s; the default run keeps the command's
# report of each step (tests/test_discovery_sequence.py) and the synthetic data it reads
@pytest.mark.slow
def test_discover_names_a_strong_hidden_effect_and_shrinks_the_gap(discover_run):
    proc, out = discover_run
    print(proc.stdout)
    assert proc.returncode == 0, proc.stderr
    assert {"discovery.json", "residuals.png", "candidates.png", "before_after.png"} <= \
        set(os.listdir(out))
    assert not [n for n in os.listdir(out) if n.startswith(".")]
    r = json.loads((out / "discovery.json").read_text())
    for k in ("named_effect", "candidates", "gap_metric", "gap_before", "gap_after", "where",
              "warnings"):
        assert k in r
    low = [e for e, f in r["fits"].items() if f["ess"] < 10]
    assert all(f["loglik_noise_sd_nats"] > 0 for f in r["fits"].values())  # measured (CRSP)
    noisy = noise_warnings(r["candidates"], r["budget"]["n_blocks"],
                           r["steps"][0]["n_compared"])
    psis = psis_warnings(r["candidates"])
    # named: no concentration warning; a later step's warnings say which step
    first = [w for w in r["warnings"] if not w.startswith("step ")]
    assert len(first) == bool(low) + len(psis) + len(noisy)
    if noisy:
        assert first[-1] == noisy[0]
    if low:
        assert all(e in first[0] for e in low)
    if psis:
        assert first[int(bool(low))] == psis[0]
    # discovery kept going: a second step on top of size_dissipation (the decision
    # itself is not asserted: whether a second effect clears its bar on these
    # data is not known in advance), and the command that calibrates the result
    st = r["steps"]
    assert st[0]["named"] == "size_dissipation" and st[0]["n_compared"] == 4
    assert len(st) >= 2 and st[1]["baseline"] == "size_dissipation"
    assert st[1]["n_compared"] == 3 and {c["effect"] for c in st[1]["candidates"]} == {
        "none", "fragmentation", "rolling_resistance", "vegetation_belt"}
    assert r["named_effects"][0] == "size_dissipation" and st[-1]["named"] in ("none",
                                                                                st[-1]["best"])
    assert r["refit_command"].startswith("python -m calib.fit ") and (
        " --model crsp --method both --rolling-resistance profile --effect size_dissipation" in
        r["refit_command"])
    assert f"calibrate the final model: {r['refit_command']}" in proc.stdout
    for c in r["candidates"]:  # k-hat per fold, flagged above 0.7, in the json and summary
        assert len(c["khat_by_fold"]) == r["budget"]["k_folds"]
        assert set(c["psis_flagged_folds"]) >= {j for j, k in enumerate(c["khat_by_fold"])
                                               if k is not None and k > 0.7}
        assert len(r["fits"][c["effect"]]["khat_by_fold"]) == r["budget"]["k_folds"]
    assert "k-hat" in proc.stdout
    for w in r["warnings"]:
        assert f"warning: {w[:40]}" in proc.stdout
    assert {c["effect"] for c in r["candidates"]} == {
        "none", "size_dissipation", "fragmentation", "rolling_resistance", "vegetation_belt"}
    for c in r["candidates"]:
        assert {"effect", "score", "gap"} <= set(c)
    assert r["named_effect"] == "size_dissipation"
    n = r["n_observations"]
    for c in r["candidates"]:
        if c["effect"] != "none":
            assert 0 < c["effective_rows"] <= n
            assert all(0 <= i < n for i in c["carrying_rows"])
    named = next(c for c in r["candidates"] if c["effect"] == "size_dissipation")
    assert named["effective_rows"] > rows_needed(n)  # the 2-se bar, restated
    assert r["gap_after"] < r["gap_before"]
    # where: size classes, on the side the hidden effect puts them (restitution
    # x (d / 1 m)^0.5: blocks below 1 m lose more, so they travel shorter than the
    # baseline says), and the residuals rise with size. With the likelihood's
    # defensive component the baseline fits the extremes better and the trend
    # over all rows is not significant (measured 2026-11-25: 0.4, 0.7 and 1.0 m
    # flagged at z -3.4, -4.4, -3.4; rho +0.30, p_adj 1); without it, it was.
    flagged = [c for c in r["where"]["by_size"] if c["flag"]]
    assert flagged and all(c["z"] < 0 and c["size_m"] <= 1.0 for c in flagged), flagged
    assert r["where"]["size_trend"]["spearman_rho"] > 0
    assert "named effect: size_dissipation" in proc.stdout


def test_loglik_noise_sd_is_the_spread_of_the_summed_rows():
    from calib.discovery.loglik_noise import loglik_noise_sd

    reps = np.array([[-1.0, -2.0, -3.0], [-2.0, -2.0, -3.0], [-1.0, -1.0, -1.0]])
    assert loglik_noise_sd(reps) == pytest.approx(np.std([-6.0, -7.0, -3.0], ddof=1))


@pytest.mark.slow  # 32 s
def test_crsp_replicates_are_independent_block_sets_of_the_fit_size():
    from calib.model.forward import CrspForward

    fw = CrspForward(PROFILE, np.array([0.5, 2.0]), 16, jax.random.key(0))
    theta = np.array([0.41, 0.87, 0.5])
    a = fw.replicates(theta, 3, jax.random.key(7))
    assert a.shape == (3, 2, 16) and np.all(np.isfinite(a)) and np.all(a > 0)
    assert not np.allclose(a[0], a[1]) and not np.allclose(a[1], a[2])
    np.testing.assert_array_equal(a, fw.replicates(theta, 3, jax.random.key(7)))
    assert not np.allclose(a[0], fw.runouts(theta[None])[0])  # not the common numbers
    # replicate r is blocks r*16 .. r*16+15 of one 48-block set drawn from that key
    wide = dataclasses.replace(fw, n_blocks=48, key=jax.random.key(7))
    np.testing.assert_array_equal(a[1], wide.runouts(theta[None])[0][:, 16:32])


def _row(effect, gain, se, sd):
    return {"effect": effect, "delta_vs_none": gain, "se_delta": se, "loglik_noise_sd_nats": sd}


def test_noise_warning_only_when_noise_could_flip_the_verdict():
    from calib.discovery.discovery_warnings import noise_warnings

    base = _row("none", 0.0, 0.0, 2.2)
    # null seed 5004 (60 rows): fragmentation +5.1 +- 2.4 against 4.8, noise hypot(8.5, 2.2)
    (w,) = noise_warnings([base, _row("fragmentation", 5.1, 2.4, 8.5),
                           _row("vegetation_belt", 1.0, 2.0, 6.9)], 128)
    assert "fragmentation gains +5.1" in w and "threshold of 4.8" in w and "8.8 nats" in w
    assert "vegetation_belt" not in w and "--n-blocks 512" in w
    # a gain far beyond the threshold, or a loss far below it: no warning
    assert noise_warnings([base, _row("rolling_resistance", 846.0, 290.0, 60.0)], 128) == []
    assert noise_warnings([base, _row("size_dissipation", -30.0, 3.0, 1.0)], 128) == []
    # not measured (the DEM), or no effect candidate: no warning
    assert noise_warnings([_row("none", 0.0, 0.0, float("nan")),
                           _row("size_dissipation", 4.1, 0.1, float("nan"))], 8) == []
    assert noise_warnings([base], 128) == []


def test_ess_warnings_name_the_degenerate_fits_only():
    from calib.discovery.discovery_warnings import ess_warnings

    assert ess_warnings({"none": (40.0, 384), "fragmentation": (12.0, 512)}) == []
    (w,) = ess_warnings({"none": (1.5, 384), "fragmentation": (30.0, 512),
                         "vegetation_belt": (8.0, 512)})
    assert "none 1.5 of 384" in w and "vegetation_belt 8.0 of 512" in w
    assert "fragmentation" not in w


def test_the_two_se_bar_is_a_bar_on_the_effective_rows():
    rng = np.random.default_rng(1)
    for n in (5, 60, 180):
        for k in range(20):
            d = rng.standard_normal(n) * 0.5 + 0.3
            d[:k % 5] += rng.exponential(50.0, k % 5)  # a few rows carrying most of it
            gain, se = elpd_difference(d, np.zeros(n))
            ne = effective_rows(d)
            assert (gain / se) ** 2 == pytest.approx((n - 1) * ne / (n - ne), rel=1e-9)
            if gain > 0:
                assert (gain > Z_MIN * se) == (ne > rows_needed(n))
    assert rows_needed(60) == pytest.approx(240 / 63)
    assert effective_rows(np.full(7, 2.0)) == pytest.approx(7.0)
    assert effective_rows(np.r_[9.0, np.zeros(9)]) == pytest.approx(1.0)
    assert np.isnan(effective_rows(np.zeros(3)))
    # rows carrying 90 % of the gain, largest first; none for a loss
    np.testing.assert_array_equal(carrying_rows(np.r_[0.1, 50.0, -0.2, 30.0, 0.1]), [1, 3])
    np.testing.assert_array_equal(carrying_rows(np.r_[1.0, 1.0, 1.0]), [0, 1, 2])
    assert carrying_rows(np.r_[-1.0, 0.5]).size == 0


def test_concentration_warning_names_the_sizes_that_carry_an_unnamed_gain():
    from calib.discovery.discovery_warnings import concentration_warnings

    sizes = np.tile([0.2, 0.4, 0.7, 1.0, 1.4, 2.0], 10)
    # rolling resistance, seed 8003 (60 runout rows): +393.1 +- 210.3 from four 0.2 m rows
    rr = {**_row("rolling_resistance", 393.1, 210.3, 4.0), "effective_rows": 3.36,
          "carrying_rows": [0, 6, 12, 18]}
    base = _row("none", 0.0, 0.0, 27.9)
    (w,) = concentration_warnings([base, rr, {**_row("size_dissipation", 164.8, 98.4, 28.7),
                                              "effective_rows": 2.9, "carrying_rows": [1]}],
                                  sizes)
    assert w.startswith("rolling_resistance gains +393.1 nats (1.87 se) but is not named")
    assert "4 of the 60 rows" in w and "(0.2 m x4)" in w and "more than 3.8" in w
    assert "size_dissipation" not in w
    # speed rows follow the runout rows and are labelled as such
    (w,) = concentration_warnings([base, {**rr, "carrying_rows": [0, 60, 61]}], sizes,
                                  np.r_[2.0, 2.0, 0.2])
    assert "runout rows of 0.2 m x1; speed rows of 2 m x2" in w and "of the 63 rows" in w
    # named (gain > 2 se), a small gain, or a record without the fields: no warning
    assert concentration_warnings([base, {**rr, "se_delta": 150.0}], sizes) == []
    assert concentration_warnings([base, {**rr, "delta_vs_none": 3.9, "se_delta": 2.5}],
                                  sizes) == []
    assert concentration_warnings([base, _row("rolling_resistance", 393.1, 210.3, 4.0)],
                                  sizes) == []


@pytest.mark.parametrize("args, needle", [
    (["no/such.csv"], "no such file"),
    (["data/postignano.csv", "--effects", "teleportation"], "--effects"),
    (["data/postignano.csv", "--model", "dem", "--effects", "vegetation_belt"], "--effects"),
    (["data/postignano.csv", "--profile", "no/profile.csv"], "no such profile"),
    (["data/postignano.csv", "--n-blocks", "1"], "--n-blocks"),
    (["data/postignano.csv", "--rolling-resistance", "fit", "--effects", "rolling_resistance"],
     "already fits the rolling resistance"),
    (["data/postignano.csv", "--model", "dem", "--rolling-resistance", "fit"],
     "--rolling-resistance fit"),
    (["data/postignano.csv", "--design-scale", "0.5"], "--design-scale: expected a number"),
    (["data/postignano.csv", "--design-scale", "nan"], "--design-scale: expected a number"),
    (["data/postignano.csv", "--model", "dem", "--design-scale", "2"], "fixed grids"),
])
def test_discover_bad_input_is_one_line_exit_2_nothing_written(tmp_path, args, needle, capsys):
    """``main`` in this process (the command as a process: test_discover_help_explains
    and the runs above)."""
    from calib.discover import main

    out = tmp_path / "d"
    rc, _, err = run_cli(main, [*args, "--out", str(out), "--no-progress"], capsys)
    assert rc == 2
    assert needle in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_design_scale_multiplies_the_main_designs_points():
    """``scaled_design``: the Sobol, warm and adaptive stages times the factor
    (rounded), everything else, the fold stages too, as before."""
    from calib.inference.budget import discovery_budget, scaled_design

    base = discovery_budget("crsp")
    twice = scaled_design(base, 2.0)
    assert (twice.n_sobol, twice.n_warm, twice.n_refine) == (256, 256, (128, 128, 128, 128))
    assert twice.n_design == 2 * base.n_design
    assert dataclasses.replace(twice, n_sobol=base.n_sobol, n_warm=base.n_warm,
                               n_refine=base.n_refine) == base
    assert scaled_design(base, 1.5).n_sobol == 192
    assert scaled_design(base, 1.0) == base


@pytest.mark.slow  # 21 s inside the default run (2026-12-06); it keeps scaled_design's own test
def test_discover_design_scale_reaches_every_fit(tmp_path, capsys):
    """``--design-scale 2`` at the quick budget: the budget recorded and every
    candidate's design carry twice the points (15 s on 2 cores)."""
    from calib.discover import main

    out = tmp_path / "d"
    rc, _, err = run_cli(main, ["data/postignano.csv", "--quick", "--design-scale", "2",
                                "--effects", "fragmentation", "--out", str(out),
                                "--no-progress"], capsys)
    assert rc == 0, err
    doc = json.loads((out / "discovery.json").read_text())
    assert (doc["budget"]["n_sobol"], doc["budget"]["n_refine"]) == (64, [64, 64])
    assert {e: f["n_design"] for e, f in doc["fits"].items()} == {"none": 192,
                                                                  "fragmentation": 256}


def test_the_khat_warning_points_to_more_design_points_not_more_blocks():
    """More blocks per point sharpen the posterior and can raise k-hat (measured at
    Tschamut); the warning names what helps."""
    row = {"effect": "size_dissipation", "psis_flagged_folds": [0], "khat_by_fold": [0.9, 0.3]}
    (w,) = psis_warnings([row])
    assert "--design-scale 2;" in w and "can raise k-hat" in w
    (w,) = psis_warnings([row], design_scale=3.0)  # a rerun already scaled: doubled again
    assert "--design-scale 6;" in w
    (w,) = psis_warnings([row], design_scale=8.0)
    assert "already at the largest --design-scale, 8" in w


def test_the_warnings_of_a_fixed_grid_run_suggest_no_design_scale():
    """The DEM candidates' designs are fixed grids, which --design-scale refuses:
    their warnings say so instead of suggesting a rerun that exits 2."""
    row = {"effect": "fragmentation", "psis_flagged_folds": [1], "khat_by_fold": [0.2, 1.4]}
    for (w,) in (psis_warnings([row], design_scale=None),
                 ess_warnings({"fragmentation": (2.0, 40)}, design_scale=None)):
        assert "--design-scale" not in w and "fixed grids have no points to add" in w


def test_discover_help_explains():
    proc = _cli("calib.discover", "--help")
    assert proc.returncode == 0
    for word in ("--model", "--effects", "named_effect", "gap"):
        assert word in proc.stdout


@pytest.mark.slow
def test_notebook_03_discrepancy_runs_at_small_size(tmp_path):
    """notebooks/03_discrepancy.py (jupytext) executes top to bottom (quick budgets),
    its closing section fitting, scoring and running the hazard of the baseline and of
    the baseline with the effect.

    Slow (645 s on 2 cores, 2026-11-28); run with ``pytest -m slow``."""
    import jupytext
    import nbclient

    nb = jupytext.read("notebooks/03_discrepancy.py")
    os.environ["NOTEBOOK_SMALL"] = "1"
    try:
        nbclient.NotebookClient(nb, timeout=900, kernel_name="python3",
                                resources={"metadata": {"path": os.getcwd()}}).execute()
    finally:
        del os.environ["NOTEBOOK_SMALL"]
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                   for o in c.get("outputs", []))
    assert "hidden: rolling_resistance | named:" in text
    assert "of which from the speeds" in text  # section 2: runouts and passage speeds
    assert "passage speeds (methods: bayes)" in text and "belt_start_m" in text  # refitted
    assert "size_dissipation" in text and "named:" in text
    print(text[-2500:])  # the closing sections' figures, shown with -rP or on failure
    # section 4: the named effect fitted, scored on held-back rows and run for the hazard
    assert text.count("held-out CRPS") == 2 and "mean |P - P_truth|" in text  # both fits


def test_stop_positions_are_measured_from_the_release():
    """Rows released at 150 m stopping 10 m further are stops on the lower slope
    (x 160 m), not on the cliff (x 10 m) where a profile-start origin put them."""
    prof = load_profile("data/postignano_profile.csv")
    obs = Observations.points(np.full(6, 1.0), np.full(6, 10.0), 1.0)
    samples = np.full((1, 200), 10.0)
    rng = np.random.default_rng(0)
    res = locate(obs, np.zeros(6, int), np.array([1.0]), samples, prof, rng, release_x_m=150.0)
    where = {p["zone"]: p["observed"] for p in res["by_slope_part"]}
    parts = [(p["x_from_m"], p["x_to_m"], p["observed"]) for p in res["by_slope_part"]]
    assert sum(o for a, e, o in parts if a <= 160.0 < e) == 6, parts
    assert where.get("cliff", 0) == 0


def test_candidates_on_the_rolling_baseline():
    """With the rolling resistance in the baseline (calib.fit's default), every
    candidate carries it as its 4th parameter, the rolling_resistance effect is
    left out (one parameter, not two), and a candidate's forward model keeps
    that box through dataclasses.replace and fits it in the solver."""
    from calib.discovery.candidates import crsp_candidates
    from calib.model.effects import full_box
    from calib.model.priors import CRSP_BOX, CRSP_ROLLING_BOX

    cands = crsp_candidates(PROFILE, base=CRSP_ROLLING_BOX)
    assert [c.effect for c in cands] == ["none", "size_dissipation", "fragmentation",
                                         "vegetation_belt"]
    for c in cands:
        assert c.box.names[:4] == CRSP_ROLLING_BOX.names
        fw = c.forward(np.array([1.0]), 8, jax.random.key(0))
        assert fw.box.names == c.box.names and fw.n_rolling == 1
        assert dataclasses.replace(fw, n_blocks=4).box.names == c.box.names
    with pytest.raises(ValueError, match="one parameter"):
        full_box("rolling_resistance", PROFILE, base=CRSP_ROLLING_BOX)
    plain = crsp_candidates(PROFILE)
    assert "rolling_resistance" in [c.effect for c in plain]
    assert all(c.box.names[:3] == CRSP_BOX.names and "rolling_friction_deg" not in c.box.names
               for c in plain)
    # the rolling angle reaches the solver: 40 deg stops 1 m blocks sooner than 5 deg
    fw = cands[1].forward(np.array([1.0]), 64, jax.random.key(0))
    r = fw.runouts(np.array([[0.41, 0.87, 0.5, 5.0, 0.0], [0.41, 0.87, 0.5, 40.0, 0.0]]))
    assert np.nanmedian(r[1]) < np.nanmedian(r[0])


class _Line:
    """A cheap forward model: runout = scale * 100 m * size^slope + 10 m noise
    (common random numbers per size class), for workflow-level tests."""

    def __init__(self, sizes_m, n_blocks, key):
        self.sizes = self.sizes_m = np.asarray(sizes_m, float)  # the workflow reads sizes_m
        self.noise = np.asarray(jax.random.normal(key, (self.sizes.size, n_blocks)))

    def mean(self, theta):
        """(N, C) mean runout of every size class at every point."""
        theta = np.atleast_2d(theta)
        slope = theta[:, 1:2] if theta.shape[1] > 1 else np.zeros((theta.shape[0], 1))
        return theta[:, :1] * 100.0 * self.sizes[None, :] ** slope

    def runouts(self, theta):
        return self.mean(theta)[:, :, None] + 10.0 * self.noise[None]


def test_a_fold_with_a_large_khat_reaches_the_discovery_record():
    from calib.discovery.candidate_fit import Candidate
    from calib.discovery.discovery_warnings import psis_warnings
    from calib.discovery.discrepancy import discover
    from calib.inference.budget import DiscoveryBudget as Budget
    from calib.model.priors import Box
    from solvers.cli import json_ready as _clean

    # 60 tight rows: the likelihood is far narrower than the 32-point design, so
    # the weights of every fold rest on one or two points (k-hat > 0.7)
    sizes = np.repeat([0.5, 1.0, 2.0], 20)
    rng = np.random.default_rng(0)
    y = 100.0 * sizes**0.3 + rng.normal(0, 10, sizes.size)
    nan = np.full(sizes.size, np.nan)
    obs = Observations(sizes, y, np.full(sizes.size, 1.0), nan, nan,
                       np.zeros(sizes.size, bool), ("synthetic",) * sizes.size)
    cands = [Candidate("none", Box(("scale",), (0.5,), (2.0,)), _Line),
             Candidate("size_dissipation", Box(("scale", "slope"), (0.5, -0.5), (2.0, 0.5)),
                       _Line)]
    budget = Budget(n_sobol=32, n_warm=0, n_refine=(), n_blocks=16, n_draws=4,
                    n_blocks_check=16, k_folds=3, noise_reps=0, smooth_loglik=False)
    d = discover(cands, obs, PROFILE, jax.random.key(0), budget)
    for f in d.fits.values():
        assert f.khat_folds.shape == (3,)
        assert np.isnan(f.smoothing_noise_var_nats2)  # the simulated sums: no smoothing
    rows = {r["effect"]: r for r in d.table}
    assert all(len(r["khat_by_fold"]) == 3 for r in rows.values())
    flagged = [r for r in rows.values() if r["psis_flagged_folds"]]
    assert flagged
    for r in rows.values():  # flagged exactly where k-hat > min(0.7, 1 - 1/log10 S)
        k = np.array(r["khat_by_fold"])
        assert r["psis_flagged_folds"] == [int(j) for j in np.flatnonzero(k > r["khat_bar"])]
        assert r["khat_bar"] == pytest.approx(1 - 1 / np.log10(32))  # 32 design points
    # into the json record (non-finite k-hat -> null, the flag list stays) and its warning
    record = _clean({"candidates": d.table})
    (w,) = psis_warnings(record["candidates"])
    assert all(r["effect"] in w for r in flagged) and "k-hat" in w


class _NoisyLine(_Line):
    """``_Line`` that can re-simulate one point with fresh blocks (its noise
    variance is then measured, as for CRSP)."""

    def replicate_sims(self, theta, n, key):
        noise = np.asarray(jax.random.normal(key, (n, self.sizes.size, self.noise.shape[1])))
        return self.mean(theta)[0][None, :, None] + 10.0 * noise, None


@pytest.mark.slow  # a smoothed fit for one record field, 17 s inside the default run; the
# smoothing itself runs in tests/test_discovery_proposals.py's default tests
def test_the_fit_records_the_noise_variance_its_smoothing_assumed():
    """The variance of the summed log-likelihood that the GP smoothing of the
    weights assumed is each fit's ``smoothing_noise_var_nats2`` (measured over
    ``noise_reps`` block sets at the Sobol stage's best point); NaN where the
    weights use the simulated sums."""
    from calib.discovery.candidate_fit import Candidate, fit_candidate
    from calib.inference.budget import DiscoveryBudget as Budget
    from calib.model.priors import Box

    sizes = np.repeat([0.5, 1.0, 2.0], 8)
    y = 100.0 * sizes ** 0.3 + np.random.default_rng(1).normal(0, 10, sizes.size)
    nan = np.full(sizes.size, np.nan)
    obs = Observations(sizes, y, np.full(sizes.size, 10.0), nan, nan,
                       np.zeros(sizes.size, bool), ("synthetic",) * sizes.size)
    classes, row_class = size_classes(obs.block_size_m)
    cand = Candidate("none", Box(("scale",), (0.5,), (2.0,)), _NoisyLine)
    fold = folds(row_class, 3, seed=0)
    kw = dict(n_sobol=32, n_warm=0, n_refine=(), n_blocks=16, n_draws=4,
              n_blocks_check=16, k_folds=3, noise_reps=4)
    smooth = fit_candidate(cand, obs, classes, row_class, jax.random.key(0), Budget(**kw), fold)
    assert smooth.smoothing_noise_var_nats2 > 0  # NaN without smoothing: the test above


def test_gap_warning_when_the_named_effect_widens_the_gap():
    """Tschamut (2026-11-24): size_dissipation was named with the gap growing from
    16.65 to 30.78 m; that is warned about. A shrinking gap, or no effect
    named, says nothing."""
    (w,) = gap_warnings("size_dissipation", 16.65, 30.78)
    assert "widens the gap" in w and "16.65 m before, 30.78 m after (x1.85)" in w
    assert gap_warnings("size_dissipation", 30.0, 12.0) == []
    assert gap_warnings("none", 16.65, 30.78) == []
    assert gap_warnings("fragmentation", float("nan"), 3.0) == []


def test_candidate_set_is_the_commands_choice_of_candidates():
    """candidate_set (what calib.discover and the notebook run): every CRSP effect
    after the baseline, combinable; the DEM's default pair, not combinable; the
    rolling baseline leaves the rolling_resistance effect out; bad choices are
    refused naming the option."""
    from calib.discovery.candidates import DEM_DEFAULT, candidate_set
    from calib.model.effects import CRSP_EFFECTS

    cands, combine = candidate_set("crsp", None, PROFILE)
    assert [c.effect for c in cands] == list(CRSP_EFFECTS) and combine is not None
    assert combine(("fragmentation",)).effect == "fragmentation"
    cands, combine = candidate_set("dem", None, PROFILE)
    assert tuple(c.effect for c in cands) == DEM_DEFAULT and combine is None
    cands, _ = candidate_set("crsp", "fragmentation", PROFILE, "fit")
    assert [c.effect for c in cands] == ["none", "fragmentation"]
    assert "rolling_resistance" not in [c.effect for c in candidate_set(
        "crsp", None, PROFILE, "fit")[0]]
    for args, needle in ((("crsp", "foo"), "--effects: foo"),
                         (("crsp", ""), r"--effects: \(empty\)"),
                         (("dem", None, "fit"), "--rolling-resistance fit"),
                         (("crsp", ["rolling_resistance"], "fit"), "already fits")):
        model, effects, *rolling = args
        with pytest.raises(ValueError, match=needle):
            candidate_set(model, effects, PROFILE, *rolling)


def test_synthetic_rows_written_by_the_library_read_back_as_the_command_writes(tmp_path):
    """observations_csv_text / velocities_csv_text (calib.synth's files): the rows
    load back rounded to 1 mm (1 mm/s), sizes and tolerances exact."""
    from calib.discovery.synthetic import observations_csv_text, velocities_csv_text
    from calib.files.observations import Velocities, load_observations, load_velocities

    obs = Observations.points([0.2, 0.7, 2.0], [101.23456, 150.0004, 219.9996], 5.0)
    path = tmp_path / "rows.csv"
    path.write_text(observations_csv_text(obs, 3))
    back = load_observations(str(path))
    np.testing.assert_array_equal(back.block_size_m, obs.block_size_m)
    np.testing.assert_array_equal(back.runout_m, [101.235, 150.0, 220.0])
    np.testing.assert_array_equal(back.runout_sd_m, obs.runout_sd_m)
    assert all("seed 3" in s for s in back.source)
    vel = Velocities(np.array([110.0, 110.0]), np.array([0.2, 2.0]),
                     np.array([12.34567, 20.0]), np.array([1.0, 1.0]), ("", ""))
    vpath = tmp_path / "speeds.csv"
    vpath.write_text(velocities_csv_text(vel, 3))
    vback = load_velocities(str(vpath))
    np.testing.assert_array_equal(vback.velocity_m_s, [12.346, 20.0])
    np.testing.assert_array_equal(vback.station_x_m, vel.station_x_m)



def test_the_step_table_names_the_folds_scored_on_fresh_draws(capsys):
    """A step's table says which folds were scored on fresh draws of their
    training posterior (``fresh_draw_folds`` of each candidate row) and that
    '!' marks a fold above the sample-size bar, not above 0.7."""
    from calib.discover import _print_step

    def row(effect, fresh, flagged):
        return {"effect": effect, "score": -230.0, "delta_vs_none": 0.0 if effect == "none"
                else 5.0, "se_delta": None if effect == "none" else 2.0, "gap": 6.0,
                "loglik_noise_sd_nats": 1.0, "khat_by_fold": [0.2, 0.66, 0.1, 0.3, 0.4],
                "psis_flagged_folds": flagged, "fresh_draw_folds": fresh}

    st = {"step": 1, "baseline": "none", "n_compared": 2, "z": 2.28, "se_nats": 2.0,
          "gain_nats": 5.0, "best": "fragmentation", "threshold_nats": 4.6,
          "named": "fragmentation", "gap_before": 6.0, "gap_after": 5.0,
          "candidates": [row("fragmentation", [3], [1]), row("none", [0, 2, 4], [])]}
    _print_step(st, 0, True)
    out = capsys.readouterr().out
    assert "! marks one above the bar min(0.7, 1 - 1/log10 S)" in out
    assert "0.66!" in out
    assert ("(scored on fresh draws of their training posterior, the design's weights being "
            "above the bar: fragmentation fold 3; none folds 0, 2, 4;") in out
    st["candidates"] = [row("fragmentation", [], []), row("none", [], [])]
    _print_step(st, 0, True)
    assert "fresh draws" not in capsys.readouterr().out


def test_dem_candidates_run_the_sites_simulated_time():
    """``calib.discover --model dem`` runs its candidates with the site file's DEM
    simulated time (Postignano's 200 s), as ``calib.fit`` does; without one, the
    toolkit's ``DEM_RUN``."""
    from calib.discover import _dem_run
    from calib.discovery.candidates import candidate_set
    from calib.files.site import load_site
    from calib.model.dem_run import DEM_RUN

    site = load_site(PROFILE_CSV)
    run = _dem_run(site)
    assert run == dataclasses.replace(DEM_RUN, max_time_s=200.0)
    assert _dem_run(dataclasses.replace(site, dem_max_time_s=None)) is None
    for given, want in ((run, run), (None, DEM_RUN)):
        cands, _ = candidate_set("dem", "size_dissipation", PROFILE, dem_run=given)
        for c in cands:
            fw = c.forward(np.array([0.5]), 2, jax.random.key(0))
            assert fw.run == want, c.effect
