"""Fragmentation in the hazard run (calib/hazard/_fragments.py) and the CRSP break
record (solvers/crsp/_break.py): every fragment its own block.

The break's invariants (mass conserved, no kinetic energy created, no fragment
below the ground), the run ending at the break, a fragment's result depending on
its own key only, the hazard tables per parent (a block exceeds x when any of its
fragments does) checked against the solver run block by block, chunking
invariance, the DEM's bonded fragments, and the command's one-line refusals.
The paper's 16- and 64-fragment runout ranges are a slow test at the end.
"""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_hazard_fixtures import write_calibration

import solvers.crsp as crsp
from calib.hazard import _fragment_options as opts
from calib.hazard import _fragment_tables as tables
from calib.hazard import _fragments as fr
from calib.hazard import draw_parameters, load_calibration, run_hazard
from calib.hazard.__main__ import main
from calib.hazard._units import draw_key
from calib.model.dem_run import DEM_RUN
from solvers.profile import ground_z, load_profile
from solvers.status import BUDGET, GROUND_TOL_M, INVALID, finished

PROFILE = load_profile("data/postignano_profile.csv")
BASE = dict(Kn=0.40, Kt=0.96, roughness_m=0.4)  # the synthetic base truth (calib.model.effects)
STATIONS = np.arange(20.0, 300.0, 20.0)
E_BREAK_KJ = 300.0
# the hazard command's defaults where they are static, and chunks of 16 blocks on 16
# lanes: every run below shares the compiled programs of the first
SETTINGS = crsp.Settings(max_events=5000)
SPLIT = dataclasses.replace(SETTINGS, split_at_break=True)
N_CHUNK = 16
N_BLOCKS = 2 * N_CHUNK


@pytest.fixture(autouse=True)
def _small_batches(monkeypatch):
    """Fragment batches of 16 lanes: one compiled fragment program for every run here."""
    monkeypatch.setattr(fr, "FRAGMENT_BATCH", 16)


def _one(tree):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], tree)


def _put(tree):
    """Committed to the first device, as the hazard run's units are (the same
    compiled programs then serve both)."""
    return jax.device_put(tree, jax.devices()[0])


def _pass1(p, block, key, offset=0, settings=SPLIT):
    """Blocks ``offset .. offset + 15`` of the run keyed ``key``, as the hazard run's
    first pass runs them (``simulate_tasks`` with one task)."""
    args = _put((_one(p), _one(block), key, PROFILE, jnp.asarray(STATIONS),
                 jnp.asarray(offset, jnp.int32)))
    res = crsp.simulate_tasks(*args[:5], n_per_task=N_CHUNK, pool=N_CHUNK, settings=settings,
                              offset=args[5])
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[0], jax.device_get(res))


def _params(rho=0.5):
    return crsp.params_from_profile(PROFILE, release_x_m=0.0, frag_energy_kJ=E_BREAK_KJ,
                                    frag_radius_ratio=rho, **BASE)


def _parents(rho=0.5, diameter_m=2.0, settings=SPLIT):
    """16 blocks with E_f = 300 kJ (2 m blocks break on Postignano, 0.5 m ones never)."""
    p, block = _params(rho), crsp.make_block(diameter_m / 2)
    return p, block, _pass1(p, block, jax.random.key(5), settings=settings)


@pytest.mark.parametrize("n", [8, 16])
def test_break_conserves_mass_and_creates_no_energy(n):
    """n fragments of mass rho^3 m with rho = n^(-1/3) weigh the block; their kinetic
    energy right after the break is at most the block's just before the impact;
    the break point lies on the ground line."""
    _, block, res = _parents(n ** (-1.0 / 3.0))
    b = res.breakup
    assert b.broken.sum() > N_CHUNK // 2, int(b.broken.sum())
    k = b.broken
    np.testing.assert_allclose(b.n_fragments[k], n, rtol=1e-12)
    np.testing.assert_allclose(b.n_fragments[k] * b.mass_kg[k], float(block.mass_kg),
                               rtol=1e-12)
    assert np.all(b.n_fragments[k] * b.fragment_energy_kJ[k] <= b.energy_before_kJ[k])
    assert np.all(b.fragment_energy_kJ[k] > 0.0)
    ground = np.asarray(ground_z(PROFILE, jnp.asarray(b.x_m[k])))
    assert np.all(b.z_m[k] >= ground - GROUND_TOL_M)


def test_split_ends_the_run_at_the_break_and_changes_nothing_else():
    """With split_at_break a broken block ends at its break (status BUDGET, never a
    runout); a block that does not break (0.5 m blocks carry less than 300 kJ)
    runs exactly as without the split."""
    _, _, res = _parents()
    k = res.breakup.broken
    assert np.all(res.status[k] == BUDGET)
    np.testing.assert_array_equal(res.stop_x_m[k], res.breakup.x_m[k])
    _, _, small = _parents(diameter_m=0.5)
    _, _, plain = _parents(diameter_m=0.5, settings=SETTINGS)
    assert not small.breakup.broken.any()
    np.testing.assert_array_equal(small.runout_m, plain.runout_m)
    np.testing.assert_array_equal(small.status, plain.status)


def _fragments_of(p, block, res, key, rows, offset=0, order=None):
    """The n fragments of the broken blocks ``rows`` (of a pass starting at block
    ``offset``), run by the solver directly, 16 at a time: (their blocks' rows,
    the solver's ``Result`` with leading axis n x len(rows))."""
    n = int(round(float(res.breakup.n_fragments[rows[0]])))
    par = np.repeat(rows, n)
    idx = np.tile(np.arange(n), rows.size)
    order = np.arange(par.size) if order is None else order
    outs = []
    for a in range(0, par.size, 16):
        sel = order[a:a + 16]
        pad = np.concatenate([sel, np.repeat(sel[-1:], 16 - sel.size)])
        keys = jax.vmap(lambda j, i: crsp.fragment_key(jax.random.fold_in(key, j), i))(
            jnp.asarray(offset + par[pad], jnp.uint32), jnp.asarray(idx[pad], jnp.uint32))
        many = jax.tree_util.tree_map(  # NumPy: no weak types, as the hazard run's
            lambda a: np.broadcast_to(np.asarray(a), (16,) + np.shape(a)), (p, block))
        rec = jax.tree_util.tree_map(lambda a: jnp.asarray(a[par[pad]]), res.breakup)
        out = crsp.simulate_fragments(*_put((*many, rec, keys,
                                             jnp.ones(16, bool),  # no barrier: all open
                                             PROFILE, jnp.asarray(STATIONS))), SETTINGS)
        outs.append(jax.tree_util.tree_map(lambda x: np.asarray(x)[:sel.size],
                                           jax.device_get(out)))
    out = jax.tree_util.tree_map(lambda *x: np.concatenate(x), *outs)
    back = np.argsort(order)
    return par, jax.tree_util.tree_map(lambda x: x[back], out)


def test_fragments_stay_above_ground_and_depend_on_their_own_key_only():
    """Every fragment ends finished and on or above the ground, each on its own
    path; a fragment gives the same result whichever fragments share its batch."""
    p, block, res = _parents()
    rows = np.flatnonzero(res.breakup.broken)[:4]
    key = jax.random.key(5)
    par, out = _fragments_of(p, block, res, key, rows)
    assert np.all(out.status != INVALID)
    assert np.all(finished(out.status)), np.unique(out.status)
    ground = np.asarray(ground_z(PROFILE, jnp.asarray(out.stop_x_m)))
    assert np.all(out.stop_z_m >= ground - GROUND_TOL_M)
    assert len(np.unique(out.stop_x_m[:8])) > 1  # the 8 fragments of one block differ
    _, rev = _fragments_of(p, block, res, key, rows, order=np.arange(par.size)[::-1])
    np.testing.assert_allclose(rev.stop_x_m, out.stop_x_m, rtol=0, atol=1e-9)


def _calibration(tmp_path):
    return write_calibration(tmp_path, crsp=(BASE["Kn"], BASE["Kt"], BASE["roughness_m"]))


def _spec(n=8, energy=E_BREAK_KJ):
    return opts.Fragmentation("crsp", n, energy_kJ=energy, what_if=True, description="test")


def _hazard(path, chunk_blocks, spec, sizes=(2.0,)):
    cal = load_calibration(path, "crsp")
    draws = draw_parameters(cal, 1, 0)
    return run_hazard(cal, draws, PROFILE, np.asarray(sizes), STATIONS, N_BLOCKS, 0,
                      chunk_blocks=chunk_blocks, pool=N_CHUNK, settings=SETTINGS,
                      fragments=spec)


def test_hazard_counts_parents_by_their_furthest_fragment(tmp_path):
    """run_hazard's per-parent and per-fragment counts, in two chunks of 16 blocks,
    equal those formed from the solver run block by block: the blocks with the run
    ending at a break, every fragment keyed from its block's key in the draw."""
    c = _hazard(_calibration(tmp_path), N_CHUNK, _spec())
    f = c.fragments.counts
    p, block, key = _params(), crsp.make_block(1.0), draw_key(0, 0)
    parent_beyond = np.zeros((N_BLOCKS, STATIONS.size), bool)
    parent_reach = np.zeros((N_BLOCKS, STATIONS.size), bool)
    beyond, reach, n_broken = [], [], 0
    for offset in (0, N_CHUNK):
        res = _pass1(p, block, key, offset)
        rows = np.flatnonzero(res.breakup.broken)
        n_broken += rows.size
        par, out = _fragments_of(p, block, res, key, rows, offset)
        assert np.all(finished(out.status))  # so every broken block is finished
        b = out.stop_x_m[:, None] > STATIONS
        beyond.append(b)
        reach.append(out.stations.passed)
        np.logical_or.at(parent_beyond, offset + par, b)
        np.logical_or.at(parent_reach, offset + par, out.stations.passed)
        parent_reach[offset:offset + N_CHUNK] |= res.stations.passed  # before any break
        whole = ~res.breakup.broken & finished(res.status)
        parent_beyond[offset:offset + N_CHUNK] |= whole[:, None] & (
            res.stop_x_m[:, None] > STATIONS)
    np.testing.assert_array_equal(c.exceed[0, 0], parent_beyond.sum(axis=0))
    np.testing.assert_array_equal(c.reach[0, 0], parent_reach.sum(axis=0))
    np.testing.assert_array_equal(f["frag_n_exceed"][0, 0], np.concatenate(beyond).sum(axis=0))
    np.testing.assert_array_equal(f["frag_n_reach"][0, 0], np.concatenate(reach).sum(axis=0))
    assert f["frag_n_broken"][0, 0] == n_broken > 0
    assert f["frag_n_fragments"][0, 0] == 8 * n_broken
    # a parent exceeds x when any of its fragments does: never fewer than a fragment
    # count can explain, never more than its fragments and whole blocks allow
    n_ex, whole = c.exceed[0, 0], f["frag_n_exceed_whole"][0, 0]
    assert np.all(n_ex >= np.ceil(f["frag_n_exceed"][0, 0] / 8) + whole)
    assert np.all(n_ex <= f["frag_n_exceed"][0, 0] + whole)


def test_command_writes_fragment_tables(tmp_path):
    """--fragmentation crsp --frag-energy-kJ: fragments.csv, the frag_* variables of
    hazard.nc, and a summary that calls the run a what-if; the mass beyond x is the
    whole blocks' plus 1/n of the fragments'."""
    import pandas as pd
    import xarray as xr

    out = tmp_path / "out"
    rc = main([_calibration(tmp_path), "--n-posterior", "1", "--n-blocks", str(N_BLOCKS),
               "--block-sizes-m", "2.0", "--stations-m", "20:280:20", "--road-x-m", "40",
               "--chunk-blocks", str(N_CHUNK), "--pool", str(N_CHUNK),
               "--fragmentation", "crsp", "--frag-energy-kJ", "300", "--out", str(out),
               "--no-progress"])
    assert rc == 0
    summary = (out / "summary.txt").read_text()
    assert "WHAT-IF" in summary and "n = 8 fragments" in summary
    table = pd.read_csv(out / "fragments.csv")
    assert list(table.columns) == ["model"] + list(tables.FRAGMENT_COLUMNS)
    with xr.open_dataset(out / "hazard.nc", engine="h5netcdf") as ds:
        assert set(fr.VARIABLES) <= set(ds.data_vars)
        assert int(ds.attrs["fragmentation_what_if"]) == 1
        n = int(ds.attrs["n_blocks_per_draw"])
        mass = (ds["frag_n_exceed_whole"] + ds["frag_n_exceed"] / 8).values[0, 0] / n
        p_parent = ds["n_exceed"].values[0, 0] / n
    np.testing.assert_allclose(table["mass_fraction_beyond_mean"], mass)
    np.testing.assert_allclose(table["p_exceed_parent_mean"], p_parent)
    assert np.all(table["mass_fraction_beyond_mean"] <= table["p_exceed_parent_mean"] + 1e-12)


def test_command_breaks_the_blocks_of_a_volume_law(tmp_path):
    """--fragmentation crsp with --volume-law and a release zone: fragments.csv has
    one row per volume class and station, and the summary's fragment lines name the
    classes (each block breaks into fragments of its own diameter)."""
    import pandas as pd

    out = tmp_path / "out"
    rc = main([_calibration(tmp_path), "--n-posterior", "1", "--n-blocks", str(N_BLOCKS),
               "--volume-law", "lognormal:median_m3=1,sigma=1", "--volume-classes-m3",
               "0.5,8", "--release-zone-m", "0:5", "--stations-m", "20:280:20",
               "--road-x-m", "40", "--chunk-blocks", str(N_CHUNK), "--pool", str(N_CHUNK),
               "--fragmentation", "crsp", "--frag-energy-kJ", "300", "--out", str(out),
               "--no-progress"])
    assert rc == 0
    table = pd.read_csv(out / "fragments.csv")
    assert len(table) == 3 * 14 and table["block_size_m"].nunique() == 3
    lines = [ln for ln in (out / "summary.txt").read_text().splitlines()
             if ln.startswith("  class ") and "P(break)" in ln]
    assert len(lines) == 3 and all("x each block's diameter" in ln for ln in lines), lines


@pytest.mark.parametrize("argv, expected", [
    (["--fragments", "16"], "--fragments 16: bonded fragments are the DEM's"),
    (["--fragmentation", "crsp"], "has no fitted fragmentation effect"),
    (["--fragmentation", "crsp", "--frag-energy-kJ", "100", "--frag-radius-ratio", "0.4"],
     "is not a whole number of fragments"),
    (["--frag-energy-kJ", "100"], "--frag-energy-kJ: give --fragmentation crsp"),
    (["--fragmentation", "crsp", "--frag-energy-kJ", "-1"], "expected a positive energy"),
    (["--model", "dem", "--fragments", "12"], "expected a perfect square"),
    (["--model", "dem", "--fragmentation", "crsp"], "the DEM breaks bonded fragments"),
])
def test_command_refuses_bad_fragment_options_in_one_line(tmp_path, capsys, argv, expected):
    path = write_calibration(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main([path, "--out", str(tmp_path / "out"), "--no-progress"] + argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err, err
    assert not (tmp_path / "out").exists()


def _released(path, release, spec=None):
    """``_hazard``'s run (two chunks of 16 blocks, one draw, E_f = 300 kJ, 8
    fragments) with the blocks' release conditions drawn by ``release``."""
    cal = load_calibration(path, "crsp")
    return run_hazard(cal, draw_parameters(cal, 1, 0), PROFILE, None, STATIONS, N_BLOCKS, 0,
                      chunk_blocks=N_CHUNK, pool=N_CHUNK, settings=SETTINGS,
                      fragments=spec or _spec(), release=release)


def test_crsp_fragments_take_the_release_conditions(tmp_path):
    """CRSP's break rule on blocks with release conditions drawn per block
    (``_fragments.seeded_fragment_chunk``): 2 m blocks released at one point in the
    solver's release state break into the fragments of the fixed-size run, every
    parent and fragment count equal to the bit; released at 30-31 m, below the
    station at 20 m, no parent and no fragment passes it."""
    from calib.model.release import ReleaseState, ReleaseZone, Seeder

    path = _calibration(tmp_path)
    plain = _hazard(path, N_CHUNK, _spec())
    point = _released(path, Seeder.fixed_sizes([2.0], ReleaseZone("point", (0.0,))))
    for k in ("exceed", "reach", "e30", "e300", "n_unfinished", "n_left_profile"):
        np.testing.assert_array_equal(getattr(point, k), getattr(plain, k), err_msg=k)
    for k, v in plain.fragments.counts.items():
        np.testing.assert_array_equal(point.fragments.counts[k], v, err_msg=k)
    assert plain.fragments.counts["frag_n_broken"][0, 0] > 0
    below = _released(path, Seeder.fixed_sizes([2.0], ReleaseZone("uniform", (30.0, 31.0)),
                                                ReleaseState(0.5, 0.2, 1.0, 0.2)))
    assert plain.reach[0, 0, 0] > 0 and plain.fragments.counts["frag_n_reach"][0, 0, 0] > 0
    assert below.reach[0, 0, 0] == 0 and below.fragments.counts["frag_n_reach"][0, 0, 0] == 0
    assert below.fragments.counts["frag_n_broken"][0, 0] > 0


@pytest.mark.parametrize("released", [False, True], ids=["fixed", "zone"])
def test_no_fragment_passes_an_unlimited_barrier(tmp_path, released):
    """A barrier of unlimited height and capacity at x = 150 m stops every piece: a
    fragment whose block broke before it meets it (``_barrier_open``), so neither a
    parent nor a fragment reaches or ends beyond it; upslope of it the counts are
    those of the run without it (common random numbers). For blocks of fixed sizes
    at one point and for blocks released over a zone."""
    from calib.hazard._run import Barrier
    from calib.model.release import ReleaseState, ReleaseZone, Seeder

    cal = load_calibration(_calibration(tmp_path), "crsp")
    seeder = (Seeder.fixed_sizes([2.0], ReleaseZone("uniform", (0.0, 5.0)),
                                 ReleaseState(1.0, 0.5, 1.0, 0.5)) if released else None)

    def run(barrier):
        return run_hazard(cal, draw_parameters(cal, 1, 0), PROFILE,
                          None if released else np.array([2.0]), STATIONS, N_BLOCKS, 0,
                          chunk_blocks=N_CHUNK, pool=N_CHUNK, settings=SETTINGS,
                          fragments=_spec(), release=seeder, barrier=barrier)

    without, with_ = run(None), run(Barrier(150.0))
    beyond, upslope = STATIONS > 150.0, STATIONS < 150.0
    f, g = with_.fragments.counts, without.fragments.counts
    assert g["frag_n_broken"][0, 0] > 0 and g["frag_n_reach"][0, 0, beyond].sum() > 0
    assert with_.reach[..., beyond].sum() == 0 and with_.exceed[..., beyond].sum() == 0
    assert f["frag_n_reach"][..., beyond].sum() == 0 and f["frag_n_exceed"][..., beyond].sum() == 0
    np.testing.assert_array_equal(with_.reach[..., upslope], without.reach[..., upslope])
    np.testing.assert_array_equal(f["frag_n_reach"][..., upslope], g["frag_n_reach"][..., upslope])


def test_blocks_of_a_volume_law_break_by_their_own_mass(tmp_path):
    """Fragments of blocks drawn from a volume law, two classes: a class's blocks
    break when their own impact energy exceeds E_f, so the class of the larger
    volumes breaks at least as often (the smallest less often than the largest:
    the same keys break blocks of one mass alike), and n fragments per break are
    counted; a parent exceeds x when a piece does, bounded by its fragments
    (``test_hazard_counts_parents_by_their_furthest_fragment``'s bounds)."""
    from calib.model.release import ReleaseZone, Seeder, parse_volume_law, volume_classes

    law = parse_volume_law("lognormal:median_m3=1,sigma=1")
    seeder = Seeder(law, tuple(volume_classes(law, [0.05, 0.5, 8.0])),
                    ReleaseZone("point", (0.0,)))
    c = _released(_calibration(tmp_path), seeder)
    f = c.fragments.counts
    broken = f["frag_n_broken"][0]
    assert np.all(np.diff(broken) >= 0) and broken[0] < broken[-1], broken
    np.testing.assert_array_equal(f["frag_n_fragments"][0], 8 * broken)
    n_ex, whole = c.exceed[0], f["frag_n_exceed_whole"][0]
    assert np.all(n_ex >= np.ceil(f["frag_n_exceed"][0] / 8) + whole)
    assert np.all(n_ex <= f["frag_n_exceed"][0] + whole)


def _fitted(tmp_path, log10_energy):
    """A CRSP calibration that fitted the fragmentation effect (``crsp.effects``, its
    column ``log10_frag_energy_kJ``), written as calib.fit writes it."""
    path = write_calibration(tmp_path, crsp=(BASE["Kn"], BASE["Kt"], BASE["roughness_m"],
                                             log10_energy),
                             crsp_names=("Kn", "Kt", "roughness_m", "log10_frag_energy_kJ"),
                             name="fitted.json")
    with open(path) as fh:
        doc = json.load(fh)
    doc["crsp"]["effects"] = ["fragmentation"]
    with open(path, "w") as fh:
        json.dump(doc, fh)
    return path


def test_fitted_fragmentation_runs_each_draws_break_energy(tmp_path):
    """--fragmentation crsp on a calibration that fitted the effect runs its fitted
    E_f (here 10^2.4771 = 300 kJ): not a what-if, and the counts of the what-if at
    300 kJ; a radius ratio other than the solver's makes it a what-if."""
    import argparse

    path = _fitted(tmp_path, math.log10(E_BREAK_KJ))
    cal = load_calibration(path, "crsp")
    draws = draw_parameters(cal, 1, 0)
    args = argparse.Namespace(fragmentation="crsp", frag_energy_kJ=None, frag_radius_ratio=None,
                              fragments=None)
    spec = opts.fragmentation_from_args(args, cal, draws, PROFILE)
    assert spec.energy_kJ is None and not spec.what_if and spec.n_per_break == 8
    assert "WHAT-IF" not in spec.description and "fitted" in spec.description
    fitted = _hazard(path, N_CHUNK, spec)
    what_if = _hazard(_calibration(tmp_path), N_CHUNK, _spec())
    np.testing.assert_array_equal(fitted.exceed, what_if.exceed)
    for k, v in fitted.fragments.counts.items():
        np.testing.assert_array_equal(v, what_if.fragments.counts[k], err_msg=k)
    args.frag_radius_ratio = 0.25
    spec = opts.fragmentation_from_args(args, cal, draws, PROFILE)
    assert spec.what_if and spec.n_per_break == 64


def test_dem_bonded_fragments_are_counted_per_fragment(tmp_path):
    """--model dem --fragments 4: every block is 4 fragments (counted whether their
    joints broke or not), a parent reaches x when any fragment does, and a time
    bound of 4 s (the blocks are still on the talus) leaves every fragment and so
    every parent unfinished, counted as such and not as runouts."""
    path = write_calibration(tmp_path, crsp=None)
    cal = load_calibration(path, "dem")
    draws = draw_parameters(cal, 1, 0)
    spec = opts.Fragmentation("dem", 4, description="test")
    run = dataclasses.replace(DEM_RUN, max_time_s=4.0)
    c = run_hazard(cal, draws, PROFILE, np.array([0.8]), STATIONS, 2, 0, dem_run=run,
                   fragments=spec)
    f = c.fragments.counts
    assert f["frag_n_fragments"][0, 0] == 8
    assert f["frag_n_exceed_whole"].sum() == 0
    assert f["frag_n_unfinished"][0, 0] == 8 and c.n_unfinished[0, 0] == 2
    assert c.exceed.sum() == 0 and f["frag_n_exceed"].sum() == 0
    assert f["frag_n_reach"][0, 0, 0] > 0  # the fragments passed x = 20 m
    np.testing.assert_array_equal(c.reach[0, 0] > 0, f["frag_n_reach"][0, 0] > 0)
    assert np.all(c.reach[0, 0] >= np.ceil(f["frag_n_reach"][0, 0] / 4))
    assert math.isclose(float(c.fragments.variables()["frag_size_m"][0]), 0.4)


def _dem_fragments_released(tmp_path, zone, state=None):
    """--model dem --fragments 4, two 0.8 m blocks for 4 s, released by ``zone``
    (None: the plain run)."""
    from calib.model.release import ReleaseState, Seeder

    path = write_calibration(tmp_path, crsp=None)
    cal = load_calibration(path, "dem")
    draws = draw_parameters(cal, 1, 0)
    spec = opts.Fragmentation("dem", 4, description="test")
    run = dataclasses.replace(DEM_RUN, max_time_s=4.0)
    seeder = (None if zone is None
              else Seeder.fixed_sizes([0.8], zone, state or ReleaseState()))
    return run_hazard(cal, draws, PROFILE, None if seeder else np.array([0.8]), STATIONS, 2,
                      0, dem_run=run, fragments=spec, release=seeder)


def test_dem_bonded_fragments_take_the_release_conditions(tmp_path):
    """The DEM's bonded blocks through the release path: at one point in the
    solver's release state every parent and fragment count is the plain run's,
    to the bit; released at 30-31 m, below the station at 20 m, no parent and no
    fragment passes that station, where the plain run's from 0 m do."""
    from calib.model.release import ReleaseState, ReleaseZone

    plain = _dem_fragments_released(tmp_path, None)
    point = _dem_fragments_released(tmp_path, ReleaseZone("point", (0.0,)))
    for k in ("exceed", "reach", "e30", "e300", "n_unfinished"):
        np.testing.assert_array_equal(getattr(point, k), getattr(plain, k), err_msg=k)
    for k, v in plain.fragments.counts.items():
        np.testing.assert_array_equal(point.fragments.counts[k], v, err_msg=k)
    below = _dem_fragments_released(tmp_path, ReleaseZone("uniform", (30.0, 31.0)),
                                    ReleaseState(0.5, 0.2, 1.0, 0.2))
    assert plain.reach[0, 0, 0] > 0 and plain.fragments.counts["frag_n_reach"][0, 0, 0] > 0
    assert below.reach[0, 0, 0] == 0 and below.fragments.counts["frag_n_reach"][0, 0, 0] == 0
    assert below.fragments.counts["frag_n_fragments"][0, 0] == 8


# ------------------------------------------------------------------ the paper (slow)

PAPER_RANGES_M = {16: (110.0, 160.0), 64: (40.0, 110.0)}  # seed paper, Sect. 4.2


_SIXTEEN_SHORT = pytest.mark.xfail(
    strict=True, reason="measured 2026-12-07 with the least-overlap pair contact and its shear "
    "springs (this run and the 64-fragment one together 328 s on 2 cores): 4 of 4 blocks "
    "broke, all 64 fragments at rest; p10-p90 of their runouts at the 1 m stations 109-120 m: "
    "the lower end about 1 m short of the paper's 110 m, the upper part of 110-160 m not "
    "reached. (With friction regularised in the slip speed: one fragment of the 4th block "
    "crept at 0.4 mm/s after 1200 s simulated, p10-p90 108.1-119.7 m; with the earlier "
    "corner contact all at rest, 108-119 m)")


_SIXTY_FOUR_AT_THE_FOOT = pytest.mark.xfail(
    strict=True, reason="measured 2026-12-07 with the least-overlap pair contact and its shear "
    "springs (the same run as python -m calib.hazard on a calibration of a = 0.40, b = 0.5 "
    "with --fragments 64 --n-blocks 1 --n-posterior 1 --block-sizes-m 1.8 --dem-max-time-s 400 "
    "--stations-m 1:300:1 --seed 0): the block broke, all 64 fragments at rest, p10-p90 of "
    "their runouts at the 1 m stations 103-112 m: a queue at the foot of the 40 deg talus, "
    "its upper end about 2 m beyond the paper's 110 m, its lower end far from the paper's "
    "40 m. (With friction regularised in the slip speed all 64 were still moving at 400 s, "
    "between 100 and 120 m; 1743 s)")


@pytest.mark.slow
@pytest.mark.parametrize("n_fragments, n_blocks", [
    pytest.param(16, 4, marks=_SIXTEEN_SHORT), pytest.param(64, 1, marks=_SIXTY_FOUR_AT_THE_FOOT)])
def test_fragment_runouts_of_a_1_8_m_block_against_the_paper(tmp_path, n_fragments, n_blocks):
    """Paper Sect. 4.2 (Figs. 5-6): the 1.8 m block in 16 fragments stops between 110
    and 160 m, in 64 fragments between 40 and 110 m. Here through the hazard run:
    ``--model dem --fragments N`` on Postignano, released at the profile's first
    vertex, the Table 1 trend alpha = 0.40 L^-0.5 at each fragment's side (the
    paper assigns alpha by fragment size), the toolkit's stiffness (x 0.01) and
    at least 400 s of simulated time (as tests/test_dem_paper.py), 4 blocks of 16
    fragments, one block of 64 (as the paper's one block; four took over 100 min on 2
    cores): every fragment at rest, and the 10th-90th percentiles of the fragments'
    runouts, read from the 1 m stations, inside the paper's range."""
    path = write_calibration(tmp_path, crsp=None, dem=(0.40, 0.5))
    cal = load_calibration(path, "dem")
    draws = draw_parameters(cal, 1, 0)
    stations = np.arange(1.0, 300.0, 1.0)
    spec = opts.Fragmentation("dem", n_fragments, description="paper")
    c = run_hazard(cal, draws, PROFILE, np.array([1.8]), stations, n_blocks, 0,
                   dem_run=dataclasses.replace(DEM_RUN, max_time_s=400.0), fragments=spec)
    f = c.fragments.counts
    n = int(f["frag_n_fragments"][0, 0])

    def first_below(share, level):  # the first station fewer than ``level`` of them pass
        idx = np.flatnonzero(share < level)
        return float(stations[idx[0]]) if idx.size else math.inf

    beyond, passed = f["frag_n_exceed"][0, 0] / n, f["frag_n_reach"][0, 0] / n
    p10, p90 = first_below(beyond, 0.9), first_below(beyond, 0.1)
    # every figure in the message: the runouts of the finished fragments, and the
    # furthest stations all of them passed (the place of one still moving)
    measured = json.dumps({"unfinished": int(f["frag_n_unfinished"][0, 0]), "fragments": n,
                           "broken": int(f["frag_n_broken"][0, 0]), "p10_m": p10,
                           "p90_m": p90, "passed_p10_m": first_below(passed, 0.9),
                           "passed_p90_m": first_below(passed, 0.1)})
    lo, hi = PAPER_RANGES_M[n_fragments]
    assert int(f["frag_n_unfinished"][0, 0]) == 0, measured
    assert lo <= p10 and p90 <= hi, measured
