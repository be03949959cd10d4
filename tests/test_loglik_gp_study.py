"""``scripts/loglik_gp_study.py`` (docs/studies.md, "What the realisation check
sees"): on a dump of a known smooth log-likelihood, its analysis reports the
GP's errors at the points a wave added (the figures checked against the same
computation here), five-fold held out, and the realisations' medians against
the mean GP's posterior."""

from __future__ import annotations

import pickle
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cli_run import load_script

from calib.inference.loglik_emulator import fit_loglik_emulator
from calib.model.priors import CRSP_ROLLING_BOX
from calib.model.warp import warp

NAMES = CRSP_ROLLING_BOX.names
PEAK = np.array([0.45, 0.93, 0.11, 33.0])


@pytest.mark.slow  # a study script's check, about 40 s of GP fits and compilation: -m slow
def test_the_study_scores_a_smooth_loglik_gp_as_honest(tmp_path, capsys):
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(CRSP_ROLLING_BOX.lo), np.asarray(CRSP_ROLLING_BOX.hi)
    theta = lo + (hi - lo) * rng.random((96, 4))
    # 16 first-design points and a wave of 32 near the top: the GP's ceiling is
    # the best simulated value, so a first design must reach the peak too
    theta[48:] = PEAK + 0.05 * (hi - lo) * rng.standard_normal((48, 4))
    theta = np.clip(theta, lo, hi)
    x = np.asarray(warp(NAMES, theta))
    xlo, xhi = x.min(0), x.max(0)
    x0 = np.asarray(warp(NAMES, PEAK))
    ll = -60.0 - 40.0 * np.sum(((x - x0) / (xhi - xlo)) ** 2 * 4.0, axis=1)
    nv = np.full(len(ll), 1.0)
    ll = ll + rng.standard_normal(len(ll))
    fits = [dict(x=x[:n], ll=ll[:n], nv=nv[:n], lo=xlo, hi=xhi, n_rows=20, level_of=None)
            for n in (64, 96)]
    draws = np.clip(PEAK + 0.02 * (hi - lo) * rng.standard_normal((400, 4)), lo, hi)
    dump = tmp_path / "d.pkl"
    with open(dump, "wb") as f:
        pickle.dump({"emu": fits, "cap_per_row": 10.0,
                     "rw": [dict(draws=draws, box_lo=lo, box_hi=hi, n_emu=2)]}, f)
    assert load_script("loglik_gp_study").main(["analyse", str(dump), "--cap-per-row", "10"]) == 0
    out = capsys.readouterr().out
    wave = re.search(r"64 -> 96: top (\d+): rmse ([\d.]+) nats, z_rms ([\d.]+)", out)
    assert wave and int(wave.group(1)) >= 24, out
    # the same figures computed here: the GP fitted on the first 64 points at the wave's
    emu = fit_loglik_emulator(x[:64], ll[:64], nv[:64], xlo, xhi, 20)
    m, v = jax.vmap(emu.predict)(jnp.asarray(x[64:]))
    top = ll[64:] > ll.max() - 30.0
    err = np.asarray(m)[top] - np.maximum(ll[64:], emu.cap)[top]
    z = err / np.sqrt(np.asarray(v)[top] + nv[64:][top] + 1e-9)
    assert int(wave.group(1)) == top.sum()
    assert float(wave.group(2)) == pytest.approx(np.sqrt(np.mean(err**2)), abs=0.051)
    assert float(wave.group(3)) == pytest.approx(np.sqrt(np.mean(z**2)), abs=0.0051)
    assert "five-fold held out on the last design: top" in out
    counts = re.search(r"medians of (\d+) realisations outside it: Kn (\d+), Kt (\d+), "
                       r"roughness_m (\d+), rolling_friction_deg (\d+)", out)
    assert counts and int(counts.group(1)) == 32, out
    assert all(0 <= int(c) <= 32 for c in counts.groups()[1:])


@pytest.mark.slow  # a study script's check (GP fits): run with -m slow
def test_a_kernel_from_the_fits_own_cap_is_the_fits_gp():
    """``kernel_from_cap`` at the module's own cap is ``fit_loglik_emulator``."""
    import calib.inference.loglik_emulator as le

    rng = np.random.default_rng(1)
    x = rng.random((40, 2))
    ll = -50.0 - 300.0 * np.sum((x - 0.4) ** 2, axis=1) + rng.standard_normal(40)
    nv = np.ones(40)
    args = (x, ll, nv, np.zeros(2), np.ones(2), 10, None)
    own = fit_loglik_emulator(*args)
    same = load_script("loglik_gp_study").kernel_from_cap(*args, le.CAP_NATS_PER_ROW)
    pts = jnp.asarray(rng.random((16, 2)))
    for a, b in zip(jax.vmap(own.predict)(pts), jax.vmap(same.predict)(pts), strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-6, atol=1e-6)
    other = load_script("loglik_gp_study").kernel_from_cap(*args, 2.0)
    assert le.CAP_NATS_PER_ROW == 10.0 and other.cap == own.cap  # the module's cap restored


def test_independent_blocks_give_each_parameter_set_its_own_block_set():
    study = load_script("loglik_gp_study")
    seen = []

    def inner(params, block, key, *a, **k):
        seen.append(k.get("task_offsets"))
        return "result"
    on = [False]
    tasks = study.independent_blocks(inner, on)
    params = {"kn": jnp.asarray([0.3, 0.3, 0.4]), "kt": jnp.asarray([0.9, 0.9, 0.9])}
    assert tasks(params, None, None) == "result" and seen[-1] is None  # off: shared blocks
    on[0] = True
    tasks(params, None, None)
    offs = np.asarray(seen[-1])
    assert offs[0] == offs[1] and offs[0] != offs[2]  # same parameters, same blocks
    assert np.all(offs % 256 == 0) and np.all(offs < 2**28)  # 256 blocks per task, no overlap
    tasks(params, None, None, task_offsets=jnp.zeros(3, jnp.int32))
    assert np.all(np.asarray(seen[-1]) == 0)  # a caller's own offsets are kept
