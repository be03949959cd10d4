"""DEM benchmark figures (called by ``python -m solvers.bench``).

Block-steps per second = sum over blocks of the steps each block ran, divided
by the wall time of the second (compiled) call. Runs use kn = ks = 50 GPa/m
scaled by ``stiffness_scale`` (0.01 unless stated; see the scaling check in
scripts/dem_reproduce.py).
"""

from __future__ import annotations

import math
import time

import jax
import numpy as np

from solvers.dem._integrate import simulate_batch, simulate_batch_jit
from solvers.dem._params import STATUS_NAMES, Options, make_block, make_params, stable_dt
from solvers.profile import load_profile, make_profile

__all__ = ["run_benchmarks"]

PROFILE_CSV = "data/postignano_profile.csv"


def _timed(params, block, keys, options):
    jax.block_until_ready(simulate_batch(params, block, keys, options))  # compile + run
    t0 = time.perf_counter()
    res = jax.block_until_ready(simulate_batch(params, block, keys, options))
    return res, time.perf_counter() - t0


def _refined(profile, n_seg):
    """The same polyline resampled into ~n_seg segments (for the search benchmark)."""
    x = np.asarray(profile.x_m)
    xs = np.unique(np.concatenate([x, np.linspace(x[0], x[-1], n_seg + 1)]))
    zs = np.interp(xs, x, np.asarray(profile.z_m))
    zone = profile.segment_zone_names()
    seg_zone = [zone[min(np.searchsorted(x, xi, side="right") - 1, len(zone) - 1)]
                for xi in xs[:-1]]
    mats = {z: {c: float(getattr(profile, c)[i]) for c in
                ("Kn", "Kt", "roughness_m", "rolling_friction_deg", "phi_deg")}
            for i, z in enumerate(profile.zone_names)}
    return make_profile(xs, zs, seg_zone, mats)


def run_benchmarks(quick: bool = False, fragments_only: bool = False,
                   options: Options = Options(), fragment_scale: float = 0.01) -> dict:
    """DEM throughput and paper-reproduction figures. ``quick`` shrinks batch
    sizes (for CI smoke runs).

    Args:
        quick: smaller batches, 16 instead of 64 fragments.
        fragments_only: run only the fragmented-block figure.
        options: base options of the fragment run (e.g. ``pair_search="knn",
            adaptive=False`` reproduces the scheme before the pair-list change).
        fragment_scale: stiffness scale of the fragment run.

    Returns:
        dict of name -> {figure: value}, all plain Python numbers.
    """
    profile = load_profile(PROFILE_CSV)
    out: dict = {}
    keys = jax.random.split(jax.random.key(0), 1000)
    if fragments_only:
        return _fragment_figure(profile, keys, quick, options, fragment_scale, out)
    scale = 0.01
    params = make_params(profile, stiffness_scale=scale)
    block = make_block(0.9, alpha=0.43)
    dt = float(stable_dt(params, block))
    n_blocks = 100 if quick else 1000
    opts = Options(max_steps=int(math.ceil(120.0 / dt)))
    res, wall = _timed(params, block, keys[:n_blocks], opts)
    steps = int(np.sum(res.n_steps))
    out["single_0.9m_to_rest"] = {
        "n_blocks": n_blocks, "stiffness_scale": scale, "dt_s": dt, "wall_s": wall,
        "block_steps": steps, "block_steps_per_s": steps / wall,
        "lane_steps_per_s": n_blocks * int(np.max(res.n_steps)) / wall,
        "stopped": int(np.sum(res.stopped)), "median_runout_m": float(np.median(res.runout_m))}

    # full paper stiffness: throughput and time-to-rest for a smaller batch
    p_full = make_params(profile)
    dt_full = float(stable_dt(p_full, block))
    nb = 32 if quick else 128
    res, wall = _timed(p_full, block, keys[:nb],
                       Options(max_steps=int(math.ceil(120.0 / dt_full))))
    steps = int(np.sum(res.n_steps))
    out["single_0.9m_full_stiffness"] = {
        "n_blocks": nb, "stiffness_scale": 1.0, "dt_s": dt_full, "wall_s": wall,
        "block_steps_per_s": steps / wall, "projected_1000_blocks_s": wall * 1000 / nb,
        "median_runout_m": float(np.median(res.runout_m))}

    # local vs brute-force segment search on an 80-segment version of the profile
    fine = _refined(profile, 80)
    p_fine = make_params(fine, stiffness_scale=scale)
    nb = 64 if quick else 256
    for mode in ("all", "local"):
        o = Options(max_steps=5000 if quick else 20000, segment_search=mode)
        res, wall = _timed(p_fine, block, keys[:nb], o)
        out[f"segment_search_{mode}_80seg"] = {
            "n_blocks": nb, "wall_s": wall,
            "block_steps_per_s": float(np.sum(res.n_steps)) / wall}

    return _fragment_figure(profile, keys, quick, options, fragment_scale, out)


def _fragment_figure(profile, keys, quick, options, fragment_scale, out):
    """One 1.8 m block in 64 (quick: 16) fragments to rest, under local damping
    (the paper's; capped at 120 s simulated: its deposit on the 40 deg talus is
    held by damping, which the rest test does not declare at rest) and under
    contact dashpots (e from alpha; 400 s cap); compile timed apart."""
    for damping, cap_s, tag in (("unbalanced", 120.0, ""), ("viscous", 400.0, "_viscous")):
        _fragment_run(profile, keys, quick, options, fragment_scale, out, damping, cap_s, tag)
    return out


def _fragment_run(profile, keys, quick, options, fragment_scale, out, damping, cap_s, tag):
    nf = 16 if quick else 64
    fblock = make_block(1.8, n_fragments=nf)
    pf = make_params(profile, stiffness_scale=fragment_scale, damping=damping)
    dt_f = float(stable_dt(pf, fblock))
    fopts = options._replace(max_steps=int(math.ceil(cap_s / dt_f)))
    t0 = time.perf_counter()
    compiled = simulate_batch_jit.lower(pf, fblock, keys[:1], fopts).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = jax.block_until_ready(compiled(pf, fblock, keys[:1]))
    wall = time.perf_counter() - t0
    r = np.asarray(res.runout_m[0])
    out[f"fragments_{nf}_to_rest{tag}"] = {
        "n_fragments": nf, "damping": damping, "max_time_s": cap_s,
        "stiffness_scale": fragment_scale, "dt_s": dt_f,
        "pair_search": fopts.pair_search, "adaptive": fopts.adaptive,
        "compile_s": compile_s, "wall_s": wall, "steps": int(res.n_steps[0]),
        "us_per_step": 1e6 * wall / int(res.n_steps[0]),
        "fragment_steps_per_s": nf * int(res.n_steps[0]) / wall,
        "status": STATUS_NAMES[int(res.status[0])], "simulated_s": float(res.time_s[0]),
        "stopped": int(np.sum(res.stopped)), "median_runout_m": float(np.median(r)),
        "runout_p10_m": float(np.percentile(r, 10)), "runout_p90_m": float(np.percentile(r, 90)),
        "runout_min_m": float(r.min()), "runout_max_m": float(r.max())}


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run_benchmarks(quick="--quick" in sys.argv,
                                    fragments_only="--fragments-only" in sys.argv), indent=1))
