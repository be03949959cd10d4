"""Reproduce the paper's DEM findings and print a table.

    python scripts/dem_reproduce.py --out figures/ [--n-blocks 64] [--skip-full-stiffness]
        [--sections table1,one_alpha,fragments,damping,stiffness,deposits,breakage]

1. single blocks L = 0.2, 0.9, 1.8 m with Table 1 alphas 0.90, 0.43, 0.30;
2. the same blocks with one alpha (0.43) for all sizes;
3. the 1.8 m block in 4, 16, 64 fragments, alpha per fragment from 0.40*L**-0.5;
4. final fragment positions on the profile (like the paper's Figs. 5 and 6), PNG;
plus the damping-mode difference and the stiffness-scaling check;
"deposits": the 16- and 64-fragment deposits under local damping
(the paper's) and contact dashpots, each relaxed for 5 s with every damping
off (``deposit_check``): how far the fragments move;
"breakage": joint breakage of the 1.8 m block in 4 fragments, c = t
= 1 MPa, at stiffness x1 and x0.01 with unscaled and sqrt-scaled strengths.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import jax
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from solvers.dem import (  # noqa: E402
    STATUS_NAMES,
    Options,
    deposit_check,
    make_block,
    make_params,
    rollout,
    stable_dt,
)
from solvers.dem._integrate import result, simulate_batch  # noqa: E402
from solvers.profile import load_profile  # noqa: E402

SECTIONS = ("table1", "one_alpha", "fragments", "damping", "stiffness", "deposits", "breakage")


def run(params, block, n, seed, max_time_s):
    dt = float(stable_dt(params, block))
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(seed), i))(np.arange(n))
    t0 = time.perf_counter()
    res = jax.block_until_ready(simulate_batch(params, block, keys,
                                               Options(max_steps=int(max_time_s / dt))))
    return res, time.perf_counter() - t0


def summary(res):
    r = np.asarray(res.runout_m).ravel()
    return (f"median {np.median(r):6.1f}  p10-p90 {np.percentile(r, 10):5.0f}-"
            f"{np.percentile(r, 90):4.0f}  min-max {r.min():5.0f}-{r.max():4.0f}  "
            f"stopped {int(np.sum(res.stopped))}/{r.size}")


def figure(profile, res, title, path, paper_range_m=None):
    """Final fragment centres on the profile (like the paper's Figs. 5-6), with
    a histogram of fragment runouts and the paper's range shaded."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax, hx) = plt.subplots(2, 1, figsize=(9, 5.5), height_ratios=[3, 1.3],
                                 sharex=True)
    px, pz = np.asarray(profile.x_m), np.asarray(profile.z_m)
    ax.fill_between(px, pz, pz.min() - 5, color="0.85", lw=0)
    ax.plot(px, pz, "k-", lw=1)
    x, z = np.asarray(res.stop_x_m).ravel(), np.asarray(res.stop_z_m).ravel()
    stopped = np.asarray(res.stopped).ravel()
    ax.plot(x[stopped], z[stopped], "s", ms=3, color="tab:red", label="final fragment centres")
    if (~stopped).any():
        ax.plot(x[~stopped], z[~stopped], "s", ms=3, mfc="none", color="tab:blue",
                label="still moving at the time bound")
    names = {"cliff": "cliff", "talus": "upper accumulation zone",
             "lower": "lower accumulation zone"}
    for i, zone in enumerate(profile.segment_zone_names()):
        xm = 0.5 * (px[i] + px[i + 1])
        ax.text(xm, pz.max() * 0.98, names.get(zone, zone), fontsize=7, ha="center",
                va="top")
        ax.axvline(px[i + 1], color="0.7", lw=0.5)
    release = float(np.asarray(res.stop_x_m).ravel()[0] - np.asarray(res.runout_m).ravel()[0])
    # zoom on the deposit (fragments are 0.2-0.5 m on a 300 m profile)
    lo_x, hi_x = np.percentile(x, 5) - 4.0, np.percentile(x, 95) + 4.0
    ins = ax.inset_axes([0.55, 0.38, 0.43, 0.45])
    ins.fill_between(px, pz, pz.min() - 5, color="0.85", lw=0)
    ins.plot(px, pz, "k-", lw=1)
    ins.plot(x[stopped], z[stopped], "s", ms=3, color="tab:red")
    ins.plot(x[~stopped], z[~stopped], "s", ms=3, mfc="none", color="tab:blue")
    gz = np.interp([lo_x, hi_x], px, pz)
    ins.set_xlim(lo_x, hi_x)
    ins.set_ylim(min(gz.min(), z.min()) - 2.0, max(gz.max(), z.max()) + 2.0)
    ins.tick_params(labelsize=6)
    ins.set_title("deposit (zoom)", fontsize=7)
    ax.set_ylabel("z (m)")
    ax.set_title(title, fontsize=9)
    ax.set_ylim(pz.min() - 5, pz.max() + 5)
    ax.legend(fontsize=7, loc="lower left")
    r = np.asarray(res.runout_m).ravel()
    hx.hist(x, bins=np.arange(px[0], px[-1] + 5, 5.0), color="tab:red")
    if paper_range_m is not None:
        lo, hi = paper_range_m
        for a in (ax, hx):
            a.axvspan(release + lo, release + hi, color="tab:green", alpha=0.15, lw=0)
        hx.text(release + 0.5 * (lo + hi), hx.get_ylim()[1] * 0.9,
                f"paper: {lo:g}-{hi:g} m", fontsize=7, ha="center", va="top")
    hx.set_xlabel(f"x (m); runout = x - {release:.1f} m;  median runout {np.median(r):.0f} m, "
                  f"{int(stopped.sum())}/{r.size} at rest")
    hx.set_ylabel("fragments")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def deposits(prof, scale, max_time_s, relax_s, seeds, out_dir):
    """16- and 64-fragment deposits under both damping modes, and the deposit
    check (every damping off for ``relax_s``). One block per seed, key(seed)."""
    print(f"deposits: L=1.8 m, alpha = 0.40*L**-0.5 per fragment, kn x {scale}, seeds "
          f"{list(seeds)}; deposit check: {relax_s:g} s with alpha = 0 and no dashpot "
          "(paper: 16 -> 110-160 m, 64 -> 40-110 m)")
    for mode in ("unbalanced", "viscous"):
        params = make_params(prof, stiffness_scale=scale, damping=mode)
        for nf in (16, 64):
            blk = make_block(1.8, n_fragments=nf)
            opts = Options(max_steps=int(max_time_s / float(stable_dt(params, blk))))
            roll = jax.jit(lambda k, p=params, b=blk, o=opts: rollout(p, b, k, o))
            check = jax.jit(lambda st, p=params, b=blk: deposit_check(p, b, st, relax_s))
            for seed in seeds:
                t0 = time.perf_counter()
                c, st = jax.block_until_ready(roll(jax.random.key(seed)))
                wall = time.perf_counter() - t0
                res = result(st, c)
                r = np.asarray(res.runout_m)
                chk = check(st)
                d = np.asarray(chk.disp_m)
                print(f"   {mode:10s} {nf:2d} fragments, seed {seed}: "
                      f"{STATUS_NAMES[int(res.status)]} at {float(res.time_s):.1f} s, "
                      f"broken {float(res.joints_broken):.0%}; runout median "
                      f"{np.median(r):.1f} m, p10-p90 {np.percentile(r, 10):.1f}-"
                      f"{np.percentile(r, 90):.1f}, min-max {r.min():.1f}-{r.max():.1f}, "
                      f"at rest {int(np.sum(res.stopped))}/{nf}; deposit check: max "
                      f"{float(chk.max_disp_m):.3g} m, mean {float(chk.mean_disp_m):.3g} m, "
                      f"median {np.median(d):.3g} m, > 1 cm {int(np.sum(d > 0.01))}/{nf}, "
                      f"left profile {int(chk.n_left)}  (wall {wall:.0f} s incl. compile)",
                      flush=True)
                if seed == seeds[0]:
                    res1 = jax.tree.map(lambda a: a[None], res)
                    figure(prof, res1, f"L = 1.8 m block in {nf} fragments, damping {mode}, "
                           f"seed {seed}", os.path.join(out_dir, f"dem_deposit_{mode}_{nf}.png"),
                           (110.0, 160.0) if nf == 16 else (40.0, 110.0))


def breakage(prof, n, time_s):
    """Joint breakage of the 1.8 m block in 4 fragments (c = t = 1 MPa) within the
    first ``time_s`` of the fall, x1 against x0.01 with and without strength scaling."""
    print(f"breakage: L=1.8 m in 4 fragments, c = t = 1 MPa, {n} blocks, first {time_s:g} s "
          "(key(0) split); mean fraction of joints broken (standard error)")
    keys = jax.random.split(jax.random.key(0), n)
    for scale, expo in ((1.0, 0.5), (0.01, 0.0), (0.01, 0.5)):
        p = make_params(prof, stiffness_scale=scale, c_joint_pa=1e6, t_joint_pa=1e6,
                        joint_strength_exponent=expo)
        blk = make_block(1.8, n_fragments=4)
        res = simulate_batch(p, blk, keys, Options(max_steps=int(time_s / float(
            stable_dt(p, blk)))))
        b = np.asarray(res.joints_broken)
        print(f"   x{scale:g}, strengths x scale^{expo:g}: broken {b.mean():.3f} "
              f"({b.std(ddof=1) / math.sqrt(n):.3f})", flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--n-blocks", type=int, default=64)
    ap.add_argument("--stiffness-scale", type=float, default=0.01)
    ap.add_argument("--max-time-s", type=float, default=400.0)
    ap.add_argument("--fragment-seeds", type=int, default=2)
    ap.add_argument("--skip-full-stiffness", action="store_true")
    ap.add_argument("--sections", default=",".join(SECTIONS),
                    help=f"comma-separated subset of {','.join(SECTIONS)}")
    ap.add_argument("--deposit-seeds", default="0", help="seeds of the deposit runs, e.g. 0,1")
    ap.add_argument("--relax-s", type=float, default=5.0, help="deposit-check time, s")
    args = ap.parse_args()
    sections = set(args.sections.split(","))
    if not sections <= set(SECTIONS):
        ap.error(f"--sections: unknown {sorted(sections - set(SECTIONS))}")
    os.makedirs(args.out, exist_ok=True)
    prof = load_profile("data/postignano_profile.csv")
    p = make_params(prof, stiffness_scale=args.stiffness_scale)
    n = args.n_blocks
    print(f"kn = ks = 50 GPa/m x {args.stiffness_scale}; damping = unbalanced (UDEC); "
          f"{n} blocks per row; runout = x_stop - x_release (m); observed band 110-220 m")
    if "deposits" in sections:
        deposits(prof, args.stiffness_scale, args.max_time_s, args.relax_s,
                 [int(v) for v in args.deposit_seeds.split(",")], args.out)
    if "breakage" in sections:
        breakage(prof, 16, 6.0)
    if "table1" in sections:
        print("1. Table 1 alphas")
        for L, a in ((0.2, 0.90), (0.9, 0.43), (1.8, 0.30)):
            res, w = run(p, make_block(L, alpha=a), n, 0, args.max_time_s)
            print(f"   L={L:3.1f} alpha={a:.2f}: {summary(res)}  ({w:.0f} s)", flush=True)
    if "one_alpha" in sections:
        print("2. one alpha (0.43) for all sizes")
        for L in (0.2, 0.9, 1.8):
            res, w = run(p, make_block(L, alpha=0.43), n, 0, args.max_time_s)
            print(f"   L={L:3.1f} alpha=0.43: {summary(res)}  ({w:.0f} s)", flush=True)
    if "fragments" in sections:
        fragments(prof, p, args)
    if "damping" in sections:
        damping(prof, args, n)
    if "stiffness" in sections and not args.skip_full_stiffness:
        stiffness(prof, args, n)


def fragments(prof, p, args):
    print("3. L=1.8 m in fragments, alpha = 0.40*L**-0.5 per fragment "
          "(paper: 16 -> 110-160 m, 64 -> 40-110 m)")
    for nf in (4, 16, 64):
        blk = make_block(1.8, n_fragments=nf)
        seeds = args.fragment_seeds if nf < 64 else 1
        res, w = run(p, blk, seeds, 0, args.max_time_s)
        br = float(np.mean(res.joints_broken))
        print(f"   {nf:2d} fragments (alpha {float(blk.alpha[0]):.2f}, {seeds} run(s)): "
              f"{summary(res)}  broken joints {br:.0%}  ({w:.0f} s)", flush=True)
        if nf in (16, 64):
            figure(prof, res, f"L = 1.8 m block in {nf} fragments ({seeds} run(s)), alpha "
                   f"{float(blk.alpha[0]):.2f} per fragment: final positions "
                   f"(cf. paper Fig. {5 if nf == 16 else 6})",
                   os.path.join(args.out, f"dem_fragments_{nf}.png"),
                   (110.0, 160.0) if nf == 16 else (40.0, 110.0))


def damping(prof, args, n):
    print("damping mode, L=0.9 alpha=0.43 (viscous: e = sqrt((1 - alpha)/(1 + alpha)))")
    for mode in ("unbalanced", "contact", "viscous"):
        pm = make_params(prof, stiffness_scale=args.stiffness_scale, damping=mode)
        res, w = run(pm, make_block(0.9, alpha=0.43), n, 0, args.max_time_s)
        print(f"   {mode:10s}: {summary(res)}", flush=True)


def stiffness(prof, args, n):
    print("stiffness scaling check, L=0.9 alpha=0.43 (same keys)")
    meds = {}
    for s in (1.0, 0.1, args.stiffness_scale):
        ps = make_params(prof, stiffness_scale=s)
        blk = make_block(0.9, alpha=0.43)
        res, w = run(ps, blk, n, 0, args.max_time_s)
        r = np.asarray(res.runout_m).ravel()
        meds[s] = r
        print(f"   scale {s:g}: dt {float(stable_dt(ps, blk)):.2e} s  mean {r.mean():6.1f} "
              f"(se {r.std(ddof=1) / math.sqrt(r.size):.1f})  {summary(res)}  wall {w:.0f} s",
              flush=True)
    d = meds[1.0].mean() - meds[args.stiffness_scale].mean()
    se = math.sqrt(meds[1.0].var(ddof=1) / n + meds[args.stiffness_scale].var(ddof=1) / n)
    print(f"   mean difference full - scaled: {d:+.1f} m = {d / se:+.2f} standard errors")


if __name__ == "__main__":
    main()
