#!/usr/bin/env python3
"""A reference posterior of CRSP's parameters on a data set, by importance
sampling the simulator itself: no emulator, many blocks per simulated release.

What ``python -m calib.fit`` does and this script does not: the main job fits a
GP to the summed log-likelihood at a few hundred design points scored with
``n_blocks_design`` blocks per simulated entry, and samples the GP
(``calib.inference``). Whether its intervals are right depends on the GP and on
the Monte Carlo noise of the scores it was fitted to (docs/studies.md, "The
simulated log-likelihood's noise and bias"). This script scores the simulator at
tens of thousands of points with many blocks each, which a GPU affords and two
CPU cores do not, so that a fit can be compared with the posterior it
approximates.

Method (importance sampling with self-normalised weights; Owen 2013, "Monte
Carlo theory, methods and examples", ch. 9; the mixture of proposals weighted
by the balance heuristic, Veach & Guibas 1995, Owen & Zhou 2000, JASA 95:135):

* the prior is uniform on the box (``calib.model.priors``), so the posterior
  density is proportional to the likelihood L(theta) on the box;
* stage 0: a scrambled Sobol design over the whole box in the emulator's
  coordinates (``CrspForward.design``'s choice: dense where S is small), scored
  with ``--coarse-blocks`` blocks per entry, only to find where the mass lies;
* rounds r = 1..R: a sub-box B_r, the bounding box of the points scored within
  ``--keep-nats`` of the best score so far, widened by ``--pad`` of its width on
  each side and clipped to the prior box; ``n_r`` Sobol points uniform on B_r,
  scored with ``--fine-blocks`` blocks per entry under each of
  ``--block-sets`` independent block sets (common random numbers within a set);
* every fine point i gets the weight w_i = L(theta_i) / q(theta_i) with the
  mixture density q(theta) = sum_r n_r 1[theta in B_r] / |B_r| / sum_r n_r;
  each block set gives one posterior, and their difference is the Monte Carlo
  error of the reference. Kish's ESS = (sum w)^2 / sum w^2 says how many
  points carry it.

Our choices and their limits: the sub-boxes are found from scores, so mass
lying more than ``--keep-nats`` below the best point, or in a region stage 0
never sampled, is missed; the script reports the weight within 5 % of each
sub-box face that is not a face of the prior box (large there: the box cut
mass off). The log-likelihood of a finite block count is biased low (Jensen's
inequality; the study above): the reference is that of ``--fine-blocks``
blocks. Rows are grouped into simulated releases as ``calib.fit`` groups them,
with the site file's release errors.

Usage (the figures of docs/studies.md, on one NVIDIA H100)::

    python scripts/reference_posterior.py data/tschamut2014/observations.csv \\
        --budget-s 360 --chunk 128 --pool 65536 --task-chunk 384 --out reference.npz
"""

from __future__ import annotations

import argparse
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

def _sobol(dim: int, n: int, seed: int) -> np.ndarray:
    from scipy.stats import qmc

    return qmc.Sobol(dim, scramble=True, seed=seed).random_base2(int(np.ceil(np.log2(n))))[:n]


class Scorer:
    """Summed log-likelihood of the data's rows at parameter points, in chunks
    of ``chunk`` points (one compiled program per block count and profile)."""

    def __init__(self, data: str, release_tolerance_m: float, chunk: int, pool: int | None,
                 task_chunk: int | None):
        from calib.files.inputs import load_inputs
        from calib.inference.calibrate import crsp_prior_box
        from calib.inference.likelihood import RowLikelihood

        inputs = load_inputs(data, None, ".")
        self.entries = inputs.entries(release_tolerance_m)
        self.profile = inputs.profile
        self.rows = RowLikelihood(inputs.obs, self.entries.index)
        self.n_rows = inputs.obs.n_obs
        self.box = crsp_prior_box("fit", inputs.profile, self.entries)  # the fit's
        self.chunk, self.pool, self.task_chunk = chunk, pool, task_chunk
        self.blocks_simulated = 0
        self.sim_seconds = 0.0

    def forward(self, n_blocks: int, key_seed: int):
        from calib.model.forward import CrspForward

        extra = {}
        if self.pool:
            extra["pool"] = self.pool
        if self.task_chunk:
            extra["task_chunk"] = self.task_chunk
        return CrspForward(self.profile, self.entries, n_blocks, jax.random.key(key_seed),
                           box=self.box, **extra)

    def score(self, fw, thetas: np.ndarray) -> np.ndarray:
        """(P,) summed log-likelihood at thetas (P, 4). ``CrspForward`` pads each
        call's tasks to whole task chunks itself, so a short last chunk of
        points reuses the compiled program."""
        out = []
        for c0 in range(0, len(thetas), self.chunk):
            t0 = time.perf_counter()
            runs = fw.runouts(thetas[c0:c0 + self.chunk])
            self.sim_seconds += time.perf_counter() - t0
            self.blocks_simulated += runs.size
            out.append(self.rows.summed(runs))
        return np.concatenate(out)


MIN_WIDTH = 1e-3  # a sub-box grows by at least this fraction of the prior box width


def sub_box(thetas: np.ndarray, scores: np.ndarray, keep_nats: float, pad: float,
            lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box of the points scored within ``keep_nats`` of the best,
    widened by ``pad`` of its width on each side (at least ``MIN_WIDTH`` of the
    prior box's width, so that one point alone, or points on a line, still span
    a box of positive volume) and clipped to the prior box [lo, hi]."""
    keep = thetas[scores >= np.max(scores) - keep_nats]
    b_lo, b_hi = keep.min(0), keep.max(0)
    grow = np.maximum(pad * (b_hi - b_lo), MIN_WIDTH * (hi - lo))
    return np.maximum(lo, b_lo - grow), np.minimum(hi, b_hi + grow)


def mixture_log_density(thetas: np.ndarray, boxes: list, counts: list) -> np.ndarray:
    """log q(theta), the density of the points drawn: the mixture of the uniform
    sub-boxes ``boxes`` [(lo, hi)] with ``counts`` points each (module docstring)."""
    q = np.zeros(len(thetas))
    for (lo, hi), n in zip(boxes, counts):
        inside = np.all((thetas >= lo) & (thetas <= hi), axis=1)
        q += n * inside / np.prod(hi - lo)
    return np.log(q / sum(counts))


def summarise(thetas, ll, log_q, box, boxes, n_draws: int = 4000, seed: int = 0) -> dict:
    """Posterior summaries of one block set's scores ``ll`` (N,) at ``thetas`` (N, d);
    None where no point has a finite score (a row got no simulated block at all).

    The mass at the prior bounds is ``calib.inference.adequacy.bound_mass`` (the
    main job's rule) on ``n_draws`` draws resampled with the weights; ``khat`` is
    the Pareto k-hat of the weights' tail (``calib.inference.importance``: above
    0.7 the estimate is not to be trusted), the weights themselves are not smoothed."""
    from calib.inference.adequacy import bound_mass
    from calib.inference.importance import ess, psis_weights, weighted_quantile

    lw = ll - log_q
    lw = np.where(np.isfinite(lw), lw, -np.inf)
    if not np.isfinite(lw).any():
        return None
    w = np.exp(lw - lw.max())
    w /= w.sum()
    draws = thetas[np.random.default_rng(seed).choice(len(w), n_draws, p=w)]
    out = {"ess": ess(w), "khat": psis_weights(lw)[1], "best_ll": float(ll.max()),
           "best_theta": thetas[np.argmax(ll)], "quantiles": [],
           "bound_mass": bound_mass(draws, box), "edge_mass": []}
    lo, hi = np.asarray(box.lower), np.asarray(box.upper)
    last_lo, last_hi = boxes[-1]
    for j in range(thetas.shape[1]):
        out["quantiles"].append(np.array([weighted_quantile(thetas[:, j], w, q)
                                          for q in (0.05, 0.5, 0.95)]))
        # weight within 5 % of a face of the last sub-box that is not a prior bound
        bw = last_hi[j] - last_lo[j]
        e_lo = w[thetas[:, j] <= last_lo[j] + 0.05 * bw].sum() if last_lo[j] > lo[j] else 0.0
        e_hi = w[thetas[:, j] >= last_hi[j] - 0.05 * bw].sum() if last_hi[j] < hi[j] else 0.0
        out["edge_mass"].append((e_lo, e_hi))
    return out


def run(data: str, budget_s: float, coarse_blocks: int, fine_blocks: int, block_sets: int,
        rounds: int, keep_nats: float, pad: float, chunk: int, seed: int,
        coarse_share: float = 0.2, release_tolerance_m: float = 1.0, pool: int | None = None,
        task_chunk: int | None = None, max_points: int = 1 << 20, start_box=None,
        log=print) -> dict:
    """Stage 0 and ``rounds`` sub-box rounds (module docstring) within ``budget_s``.

    Returns:
        dict with the fine points ``thetas`` (N, 4), their scores ``ll`` (block
        sets, N) nats, ``log_q`` (N,), the sub-``boxes`` and their point
        ``counts``, stage 0's ``coarse_theta`` and ``coarse_ll``, one summary per
        block set (``sets``, ``summarise``), ``seconds``, the simulator's
        ``blocks_per_s`` and ``blocks_per_point`` of a fine point.
    """
    t_start = time.perf_counter()
    sc = Scorer(data, release_tolerance_m, chunk, pool, task_chunk)
    box = sc.box
    lo, hi = np.asarray(box.lower), np.asarray(box.upper)
    log(f"{sc.n_rows} rows, {len(sc.entries.sizes_m)} simulated releases; backend "
        f"{jax.default_backend()}")

    # stage 0: where the mass lies (the emulator's coordinates, as calib.fit's design)
    coarse_fw = sc.forward(coarse_blocks, 1000 + seed)
    if start_box is not None:  # the first round's sub-box given: no stage 0
        b0 = np.clip(np.asarray(start_box, float), lo, hi)
        coarse_share = 0.0
        x0 = np.empty((0, box.dim))
    else:
        z = _sobol(box.dim, max_points, seed)
        x0 = np.clip(coarse_fw.from_input(coarse_fw.input_box.from_unit(z)), lo, hi)
    share = coarse_share * budget_s
    coarse_ll, coarse_theta = [], []
    t0 = time.perf_counter()
    for c0 in range(0, len(x0), chunk):
        coarse_theta.append(x0[c0:c0 + chunk])
        coarse_ll.append(sc.score(coarse_fw, coarse_theta[-1]))
        if time.perf_counter() - t0 > share:
            break
    if start_box is not None:  # its corners stand for stage 0's points
        coarse_theta, coarse_ll = b0, np.zeros(2)
    else:
        coarse_theta, coarse_ll = np.concatenate(coarse_theta), np.concatenate(coarse_ll)
        log(f"stage 0: {len(coarse_ll)} points x {coarse_blocks} blocks per release, best "
            f"{coarse_ll.max():.1f} nats at {np.round(coarse_theta[np.argmax(coarse_ll)], 3)} "
            f"({time.perf_counter() - t0:.0f} s)")

    fws = [sc.forward(fine_blocks, 2000 + seed + k) for k in range(block_sets)]
    ref_theta, ref_ll = coarse_theta, coarse_ll
    boxes, counts, thetas, lls = [], [], [], []
    for r in range(rounds):
        if r == 0 and start_box is not None:
            b_lo, b_hi = b0
        else:
            b_lo, b_hi = sub_box(ref_theta, ref_ll, keep_nats, pad, lo, hi)
        u = _sobol(box.dim, max_points, seed + 100 + r)
        pts = b_lo + u * (b_hi - b_lo)
        t0 = time.perf_counter()
        got, got_ll = [], []
        for c0 in range(0, len(pts), chunk):
            p = pts[c0:c0 + chunk]
            got.append(p)
            got_ll.append(np.stack([sc.score(fw, p) for fw in fws]))
            if time.perf_counter() - t0 > (1 - coarse_share) * budget_s / rounds:
                break
        got, got_ll = np.concatenate(got), np.concatenate(got_ll, axis=1)
        boxes.append((b_lo, b_hi))
        counts.append(len(got))
        thetas.append(got)
        lls.append(got_ll)
        ref_theta = np.concatenate(thetas)
        ref_ll = np.concatenate(lls, axis=1).mean(0)
        log(f"round {r + 1}: {len(got)} points x {fine_blocks} blocks x {block_sets} block "
            f"sets on the sub-box " + ", ".join(
                f"{n} {a:.3g}-{b:.3g}" for n, a, b in zip(box.names, b_lo, b_hi))
            + f" ({time.perf_counter() - t0:.0f} s)")
    thetas = np.concatenate(thetas)
    lls = np.concatenate(lls, axis=1)
    log_q = mixture_log_density(thetas, boxes, counts)
    sets = [summarise(thetas, lls[k], log_q, box, boxes) for k in range(block_sets)]
    seconds = time.perf_counter() - t_start
    return {"names": box.names, "thetas": thetas, "ll": lls, "log_q": log_q,
            "boxes": boxes, "counts": counts, "coarse_theta": coarse_theta,
            "coarse_ll": coarse_ll, "sets": sets, "seconds": seconds,
            "blocks_per_s": sc.blocks_simulated / max(sc.sim_seconds, 1e-9),
            "blocks_per_point": fine_blocks * len(sc.entries.sizes_m)}


def report(res: dict, log=print) -> None:
    names = res["names"]
    for k, s in enumerate(res["sets"]):
        if s is None:
            log(f"block set {k + 1}: no point has a finite score (at every point some row "
                "got no finished block near it): raise --fine-blocks")
            continue
        log(f"block set {k + 1}: ESS {s['ess']:.0f} of {len(res['thetas'])} points (k-hat "
            f"{s['khat']:.2f}), best "
            f"{s['best_ll']:.1f} nats at {np.round(s['best_theta'], 3)}")
        for j, n in enumerate(names):
            q = s["quantiles"][j]
            b = s["bound_mass"][n]
            e = s["edge_mass"][j]
            log(f"  {n:22s} 5/50/95 % {q[0]:.4g} / {q[1]:.4g} / {q[2]:.4g}   within 2 % of a "
                f"bound {b['lower']:.3f} / {b['upper']:.3f}"
                f"{' FLAGGED' if b['flagged'] else ''}   within 5 % of the sub-box's inner "
                f"faces {e[0]:.3f} / {e[1]:.3f}")
    log(f"simulator: {res['blocks_per_s']:,.0f} blocks/s ({res['blocks_per_point']:,} "
        f"blocks per fine point); {res['seconds']:.0f} s in all")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description="Reference posterior of CRSP's Kn, Kt, S and phi_r on an observations "
                    "file by importance sampling the simulator (no emulator).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("data", help="observations CSV (as calib.fit takes it)")
    p.add_argument("--budget-s", type=float, default=420.0,
                   help="wall time for the scoring (each stage stops after the chunk that "
                        "ends its share)")
    p.add_argument("--coarse-share", type=float, default=0.2,
                   help="share of --budget-s for stage 0; the rounds share the rest equally")
    p.add_argument("--coarse-blocks", type=int, default=256,
                   help="blocks per simulated release in stage 0 (calib.fit's design count)")
    p.add_argument("--fine-blocks", type=int, default=4096,
                   help="blocks per simulated release in the rounds")
    p.add_argument("--block-sets", type=int, default=2,
                   help="independent block sets scoring every fine point")
    p.add_argument("--rounds", type=int, default=2, help="sub-box rounds")
    p.add_argument("--keep-nats", type=float, default=15.0,
                   help="a sub-box bounds the points scored within this of the best")
    p.add_argument("--pad", type=float, default=0.15,
                   help="a sub-box is widened by this fraction of its width on each side")
    p.add_argument("--chunk", type=int, default=256, help="points per simulator call")
    p.add_argument("--pool", type=int, default=0,
                   help="CRSP lanes per call (0: solvers.crsp.default_pool)")
    p.add_argument("--task-chunk", type=int, default=0,
                   help="tasks per compiled call (0: CrspForward's default)")
    p.add_argument("--start-box", help="the first round's sub-box as lo,lo,lo,lo:hi,hi,hi,hi "
                   "(Kn, Kt, roughness_m, rolling_friction_deg), e.g. from an earlier run; "
                   "no stage 0")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--release-tolerance-m", type=float, default=1.0,
                   help="as calib.fit's option of the same name")
    p.add_argument("--out", help="write the points and scores to this .npz")
    a = p.parse_args(argv)
    if a.block_sets < 1 or a.rounds < 1 or a.chunk < 1:
        p.error("--block-sets, --rounds and --chunk must be >= 1")
    if not 0 < a.coarse_share < 1 or a.budget_s <= 0:
        p.error("--coarse-share must lie in (0, 1) and --budget-s be > 0")
    if min(a.coarse_blocks, a.fine_blocks) < 2:
        p.error("--coarse-blocks and --fine-blocks must be >= 2")
    start_box = None
    if a.start_box:
        try:
            start_box = [[float(v) for v in side.split(",")] for side in a.start_box.split(":")]
        except ValueError:
            p.error(f"--start-box {a.start_box!r}: expected numbers")
        if len(start_box) != 2 or any(len(side) != 4 for side in start_box) or any(
                h <= lo_ for lo_, h in zip(*start_box)):
            p.error(f"--start-box {a.start_box!r}: expected 4 lower and 4 higher bounds "
                    "as lo,lo,lo,lo:hi,hi,hi,hi")
    from calib.files.inputs import InputError

    try:
        res = run(a.data, a.budget_s, a.coarse_blocks, a.fine_blocks, a.block_sets, a.rounds,
                  a.keep_nats, a.pad, a.chunk, a.seed, a.coarse_share, a.release_tolerance_m,
                  a.pool or None, a.task_chunk or None, start_box=start_box,
                  log=lambda s: print(s, flush=True))
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    report(res, log=lambda s: print(s, flush=True))
    if a.out:
        np.savez_compressed(a.out, names=np.array(res["names"]), thetas=res["thetas"],
                            ll=res["ll"], log_q=res["log_q"],
                            box_lo=np.array([b[0] for b in res["boxes"]]),
                            box_hi=np.array([b[1] for b in res["boxes"]]),
                            counts=np.array(res["counts"]), coarse_theta=res["coarse_theta"],
                            coarse_ll=res["coarse_ll"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
