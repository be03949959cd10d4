#!/usr/bin/env python3
"""How well does the log-likelihood GP of a CRSP fit know the surface it emulates?

``calib.inference.realisations`` flags a fit whose posterior the GP's own
uncertainty could move beyond its intervals. This script measures that GP
(``calib.inference.loglik_emulator``) on the designs of a real fit, two ways:

* ``run``: ``python -m calib.fit`` with two of its constants changed for the
  study (``--n-blocks-design``: blocks per design point and release,
  ``Budget.n_blocks_design``; ``--cap-per-row``: ``CAP_NATS_PER_ROW``), or
  with a GP whose kernel is fitted on the values capped at
  ``--kernel-cap-per-row`` while it is conditioned on the values at the
  fit's own cap (``kernel_from_cap``: a what-if, not what the fit does), or
  with ``--independent-blocks``: every simulation of the Bayesian stage
  (designs, chain screening, waves) with a block set of its own per parameter
  set instead of the common random numbers (``independent_blocks``), every
  GP fit's inputs (points, summed log-likelihoods, their Monte Carlo variances)
  and the realisation check's posterior draws saved to ``--dump`` (a pickle,
  written at every realisation check: a fit without one writes none).
* ``analyse``: on a dump, for each ``--cap-per-row`` value, (a) the GP fitted
  on the design before each repair wave predicting the points that wave then
  simulated (error and z = error / predictive sd with the Monte Carlo noise,
  near the top: within 30 nats of the best point; and over all), i.e. how honest
  the GP is where the repairs look next; (b) five-fold held-out errors near the
  top; (c) on the last design, the posterior of the GP's mean (importance
  sampling on the realisation check's candidates) and how many of 32
  realisations' medians lie outside its 90 % intervals, per parameter.

Usage (the figures of docs/studies.md, "What the realisation check sees")::

    python scripts/loglik_gp_study.py run --dump s1.pkl -- \\
        data/tschamut2014/observations.csv --model crsp --seed 1 --out results/s1
    python scripts/loglik_gp_study.py run --n-blocks-design 1024 --dump s1b.pkl -- ...
    python scripts/loglik_gp_study.py run --kernel-cap-per-row 2 --dump s1k.pkl -- ...
    python scripts/loglik_gp_study.py analyse s1.pkl --cap-per-row 10,3,2 --kernel-cap-per-row 2

and "Per-zone rolling resistance and independent design blocks"::

    python scripts/loglik_gp_study.py run --independent-blocks --dump i1.pkl -- \\
        data/tschamut2014/observations.csv --model crsp --seed 1 --out results/i1
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import sys

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

NAMES = ("Kn", "Kt", "roughness_m", "rolling_friction_deg")
TOP_NATS = 30.0


def kernel_from_cap(x, ll, noise_var, lo, hi, n_rows, level_of, kernel_cap_per_row: float):
    """``loglik_emulator.fit_loglik_emulator`` with its kernel's hyperparameters
    taken from a fit on the same points capped at ``kernel_cap_per_row`` nats
    per row (length scales as they are; signal and nugget sd rescaled from that
    fit's standardisation to this one's), conditioned on the values at the
    module's own cap: the kernel follows the surface near the top while the
    mean keeps the deep cap's slopes. A what-if of this study."""
    import jax.numpy as jnp

    import calib.inference.loglik_emulator as le
    from calib.inference.emulator import QuantileEmulator, se_kernel

    own = le.CAP_NATS_PER_ROW
    le.CAP_NATS_PER_ROW = kernel_cap_per_row
    try:
        near = le.fit_loglik_emulator(x, ll, noise_var, lo, hi, n_rows, level_of)
    finally:
        le.CAP_NATS_PER_ROW = own
    g, nv_g, cap, ceiling = le._log_deficit(ll, noise_var, n_rows)
    lo, hi = jnp.asarray(lo, jnp.float64), jnp.asarray(hi, jnp.float64)
    xu = (jnp.asarray(x) - lo) / (hi - lo)
    level = g if level_of is None else g[np.asarray(level_of, bool)]
    mu, sd = float(level.mean()), float(max(g.std(), 1e-3))
    log_ls, log_sf, log_sn = (h[0, 0] for h in near.gp.hyp)
    rescale = float(np.log(float(near.gp.y_std[0, 0]) / sd))
    log_sf, log_sn = log_sf + rescale, log_sn + rescale
    k = se_kernel(xu, xu, log_ls, log_sf) + jnp.diag(jnp.exp(2 * log_sn) + nv_g / sd**2 + 1e-8)
    chol = jnp.linalg.cholesky(k)
    alpha = jax.scipy.linalg.cho_solve((chol, True), jnp.asarray((g - mu) / sd))
    hyp = (log_ls[None, None], jnp.asarray(log_sf)[None, None], jnp.asarray(log_sn)[None, None])
    gp = QuantileEmulator(xu, lo, hi, alpha[None, None], chol[None, None], hyp,
                          jnp.full((1, 1), mu), jnp.full((1, 1), sd), np.full(1, np.nan))
    return le.LoglikEmulator(gp, cap, ceiling)


def independent_blocks(simulate_tasks, on: list[bool]):
    """``solvers.crsp.simulate_tasks`` that, while ``on[0]``, gives every task a
    block set of its own: block j of task t uses the key index
    ``offset + o_t + j`` with o_t = 256 (crc32 of the task's parameters mod
    2^20), so the same parameters (and release) draw the same blocks and
    different ones independent blocks (up to 256 blocks per task). The fit's
    forward models pass no ``task_offsets`` of their own: they share the
    blocks, the common random numbers (``calib.model.forward``). A what-if of
    this study: with common random numbers the design's Monte Carlo errors are
    one random surface over the box (nearby points share their errors), which
    the GP's noise model, independent from point to point, does not describe
    (Chen, Ankenman & Nelson 2012, "The effects of common random numbers on
    stochastic kriging metamodels", ACM TOMACS 22(2):7)."""
    import zlib

    import jax.numpy as jnp

    def wrapped(params, block, key, *a, **k):
        if not on[0] or k.get("task_offsets") is not None:
            return simulate_tasks(params, block, key, *a, **k)
        leaves = [np.asarray(v, np.float64) for v in jax.tree_util.tree_leaves(params)]
        n = leaves[0].shape[0]
        rows = np.concatenate([v.reshape(n, -1) for v in leaves], axis=1)
        offs = np.array([zlib.crc32(r.tobytes()) % (1 << 20) for r in rows]) * 256
        return simulate_tasks(params, block, key, *a, task_offsets=jnp.asarray(offs, jnp.int32),
                              **k)
    return wrapped


def run(args, fit_args: list[str]) -> int:
    """``calib.fit`` with the study's constants, its GP inputs dumped."""
    import calib.inference.bayes_stage as bs
    import calib.inference.calibrate as cal
    import calib.inference.loglik_emulator as le
    from calib.fit import main

    if args.cap_per_row is not None:
        le.CAP_NATS_PER_ROW = args.cap_per_row
    if args.n_blocks_design is not None:
        presets = cal.presets

        def more_blocks(model, quick):
            b = presets(model, quick)
            return dataclasses.replace(b, n_blocks_design=args.n_blocks_design)
        cal.presets = more_blocks
    out = {"emu": [], "rw": [], "cap_per_row": le.CAP_NATS_PER_ROW,
           "kernel_cap_per_row": args.kernel_cap_per_row,
           "independent_blocks": args.independent_blocks}
    if args.independent_blocks:
        import calib.model.forward as fwd

        on = [False]
        fwd.crsp.simulate_tasks = independent_blocks(fwd.crsp.simulate_tasks, on)
        stage = bs.bayes_stage

        def stage_independent(*a, **k):
            on[0] = True
            try:
                return stage(*a, **k)
            finally:
                on[0] = False
        cal.bayes_stage = stage_independent
    fit = bs.fit_loglik_emulator
    if args.kernel_cap_per_row is not None:
        def fit(x, ll, noise_var, lo, hi, n_rows, level_of=None):
            return kernel_from_cap(x, ll, noise_var, lo, hi, n_rows, level_of,
                                   args.kernel_cap_per_row)

    def fit_dumped(x, ll, noise_var, lo, hi, n_rows, level_of=None):
        out["emu"].append(dict(x=np.asarray(x), ll=np.asarray(ll), nv=np.asarray(noise_var),
                               lo=np.asarray(lo), hi=np.asarray(hi), n_rows=n_rows,
                               level_of=None if level_of is None else np.asarray(level_of)))
        return fit(x, ll, noise_var, lo, hi, n_rows, level_of)
    bs.fit_loglik_emulator = fit_dumped
    check = bs.realisation_check

    def check_dumped(emu, to_input, box, samples, names, key, *a, **k):
        out["rw"].append(dict(draws=np.asarray(samples), box_lo=np.asarray(box.lo),
                              box_hi=np.asarray(box.hi), n_emu=len(out["emu"])))
        with open(args.dump, "wb") as f:
            pickle.dump(out, f)
        return check(emu, to_input, box, samples, names, key, *a, **k)
    bs.realisation_check = check_dumped
    return main(fit_args)


def _predict(emu, x):
    import jax.numpy as jnp
    m, v = jax.vmap(emu.predict)(jnp.asarray(x))
    return np.asarray(m), np.asarray(v)


def _scores(m, v, ll, nv, cap, top):
    y = np.maximum(ll, cap)
    err, z = m - y, (m - y) / np.sqrt(v + nv + 1e-9)
    rms = lambda a: float(np.sqrt(np.mean(a**2))) if len(a) else float("nan")  # noqa: E731
    return (f"top {int(top.sum())}: rmse {rms(err[top]):.1f} nats, z_rms {rms(z[top]):.2f}; "
            f"all {len(y)}: rmse {rms(err):.0f}, z_rms {rms(z):.2f}")


def analyse(args) -> int:
    import jax.numpy as jnp
    from scipy.special import logsumexp

    import calib.inference.loglik_emulator as le
    import calib.inference.realisations as rz
    from calib.inference.importance import weighted_quantile
    from calib.model.priors import Box
    from calib.model.warp import warp

    with open(args.dump, "rb") as f:
        d = pickle.load(f)
    fits, last = d["emu"], d["emu"][-1]
    best = float(np.max(last["ll"]))
    print(f"{args.dump}: {len(fits)} GP fits, the last on {len(last['ll'])} points, "
          f"best {best:.1f} nats; dumped with {d.get('cap_per_row', 10.0)} nats per row")
    for cap in args.cap_per_row:
        le.CAP_NATS_PER_ROW = cap
        print(f"\ncap {cap} nats per row ({cap * last['n_rows']:.0f} nats):")
        print(" (a) the GP before each wave, at the points the wave added")
        for a, b in zip(fits[:-1], fits[1:], strict=True):
            n0, x, ll, nv = len(a["ll"]), b["x"], b["ll"], b["nv"]
            if len(ll) == n0 or not np.array_equal(x[:n0], a["x"]):
                continue  # a refocused box: not the same design grown
            lv = None if b["level_of"] is None else b["level_of"][:n0]
            emu = le.fit_loglik_emulator(x[:n0], ll[:n0], nv[:n0], b["lo"], b["hi"],
                                         b["n_rows"], lv)
            m, v = _predict(emu, x[n0:])
            top = ll[n0:] > best - TOP_NATS
            print(f"   {n0} -> {len(ll)}: " + _scores(m, v, ll[n0:], nv[n0:], emu.cap, top))
        x, ll, nv, n = last["x"], last["ll"], last["nv"], len(last["ll"])
        ms, vs, idx = [], [], []
        for k in range(5):
            test = np.arange(k, n, 5)
            train = np.setdiff1d(np.arange(n), test)
            lv = None if last["level_of"] is None else last["level_of"][train]
            emu = le.fit_loglik_emulator(x[train], ll[train], nv[train], last["lo"],
                                         last["hi"], last["n_rows"], lv)
            m, v = _predict(emu, x[test])
            ms.append(m)
            vs.append(v)
            idx.append(test)
        i = np.concatenate(idx)
        print(" (b) five-fold held out on the last design: "
              + _scores(np.concatenate(ms), np.concatenate(vs), ll[i], nv[i], emu.cap,
                        ll[i] > best - TOP_NATS))
        rw = d["rw"][-1]
        box = Box(NAMES, tuple(rw["box_lo"]), tuple(rw["box_hi"]))
        emu = le.fit_loglik_emulator(x, ll, nv, last["lo"], last["hi"], last["n_rows"],
                                     last["level_of"])

        def to_input(t):
            return warp(NAMES, t)
        theta, log_q = rz._candidates(rw["draws"], box, np.random.default_rng(args.seed))
        ey = np.asarray(jax.vmap(lambda t: emu.predict(to_input(t))[0])(jnp.asarray(theta)))
        inside = np.all((theta >= box.lo) & (theta <= box.hi), axis=1)
        lw = np.where(inside, ey - log_q, -np.inf)
        w = np.exp(lw - logsumexp(lw))
        q = np.array([[weighted_quantile(c, w, p) for c in theta.T] for p in (0.05, 0.95)])
        med = rz.realisation_medians(emu, to_input, box, rw["draws"],
                                     jax.random.PRNGKey(args.seed))
        out = ((med < q[0]) | (med > q[1])).sum(axis=0)
        print(f" (c) the mean GP's posterior (importance sampling, ESS {1 / np.sum(w**2):.0f}): "
              + ", ".join(f"{nm} {lo:.3g}-{hi:.3g}" for nm, lo, hi in zip(NAMES, *q, strict=True)))
        print(f"     medians of {len(med)} realisations outside it: "
              + ", ".join(f"{nm} {int(o)}" for nm, o in zip(NAMES, out, strict=True)))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    fit_args = []
    if "--" in argv:
        k = argv.index("--")
        argv, fit_args = argv[:k], argv[k + 1:]
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="calib.fit with the study's constants; arguments after --")
    r.add_argument("--dump", required=True, help="pickle the GP inputs here")
    r.add_argument("--n-blocks-design", type=int, default=None,
                   help="blocks per design point and release (default: the budget's)")
    r.add_argument("--cap-per-row", type=float, default=None,
                   help="the GP's cap, nats per row (default: CAP_NATS_PER_ROW)")
    r.add_argument("--kernel-cap-per-row", type=float, default=None,
                   help="fit the GP's kernel on the values capped here (kernel_from_cap)")
    r.add_argument("--independent-blocks", action="store_true",
                   help="a block set of its own per parameter set in the Bayesian stage "
                        "(independent_blocks), not the common random numbers")
    a = sub.add_parser("analyse", help="the GP's errors on a dump")
    a.add_argument("dump")
    a.add_argument("--cap-per-row", type=lambda s: [float(v) for v in s.split(",")],
                   default=[10.0], help="comma-separated caps to refit with")
    a.add_argument("--seed", type=int, default=3, help="candidates' and realisations' seed")
    args = p.parse_args(argv)
    return run(args, fit_args) if args.cmd == "run" else analyse(args)


if __name__ == "__main__":
    sys.exit(main())
