#!/usr/bin/env python3
"""What if the ground under each block were uncertain within the raster's error?

A profile cut from a coarse or proxy raster is one guess of the ground; the
tracked rocks at rest say how far off it is (docs/studies.md, "The terrain
proxy's vertical error at Tschamut": sd 0.15 m where the raster's slope is
below 10 deg, 0.59 m on steeper ground, 5 m cells). RocFall's practitioners
vary each rock's slope within such an error (its per-rock slope variation).
This script runs ``python -m calib.fit`` or ``python -m calib.validate`` with
every CRSP forward simulation split into ``--groups`` equal parts, part g on
the profile with its vertex heights moved by a field of that error
(``perturbed_profile``), so a parameter set's blocks see ``--groups`` grounds:

    e(x) = sd(x_k) n_gk at the knots x_k = x_0 + k * spacing, linear between,
    n_gk ~ N(0, 1), keyed by (seed, g, k) only; sd(x_k) = the gentle or steep
    sd by the profile's slope over [x_k - spacing/2, x_k + spacing/2].

Our choices, a what-if of this study and not what the toolkit does:

* knots independent of each other (the raster's error between points is
  not measured); by default 10 m apart, the scale below which the proxy's
  README calls slope details uncertain: errors of 0.6 m 10 m apart tilt a
  segment by about 5 deg, 5 m apart (one raster cell) by about 10 deg;
* the grounds are the same for every parameter set (common random numbers,
  as the blocks are), part g keeps the block indices it has without the
  split, so with sd 0 the results are the unsplit run's exactly;
* a block's release height stays relative to the ground under it, drawn with
  the site's release error as today: at the release point the raster's error
  is counted twice (both are the raster's error there).

The profile's vertices here are 1 m apart and the knots fall on vertices, so
the moved ground is the field exactly; a profile whose vertices do not hold
every knot gets the field at its vertices only.

Usage (docs/studies.md, "The ground within the raster's error")::

    python scripts/terrain_variation_study.py fit -- \\
        data/tschamut2014/observations.csv --model crsp --seed 1 --out results/t1
    python scripts/terrain_variation_study.py validate -- \\
        results/t1/calibration.json held.csv --out results/t1/val
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)


def knot_field(x_m: np.ndarray, z_m: np.ndarray, group: int, *, spacing_m: float,
               sd_gentle_m: float, sd_steep_m: float, slope_break_deg: float,
               seed: int) -> np.ndarray:
    """e (V,) at the vertices ``x_m`` of ground ``z_m`` for part ``group``."""
    x0, x1 = float(x_m[0]), float(x_m[-1])
    knots = x0 + spacing_m * np.arange(int(np.ceil((x1 - x0) / spacing_m)) + 1)
    half = 0.5 * spacing_m
    rise = np.interp(knots + half, x_m, z_m) - np.interp(knots - half, x_m, z_m)
    steep = np.degrees(np.arctan(np.abs(rise) / spacing_m)) >= slope_break_deg
    sd = np.where(steep, sd_steep_m, sd_gentle_m)
    n = np.random.default_rng([seed, group]).standard_normal(knots.shape)
    return np.interp(x_m, knots, sd * n)


def perturbed_profile(profile, group: int, **field):
    """``profile`` with its vertex heights moved by part ``group``'s field."""
    import jax.numpy as jnp

    x = np.asarray(profile.x_m, float)
    z = np.asarray(profile.z_m, float)
    return dataclasses.replace(profile, z_m=jnp.asarray(z + knot_field(x, z, group, **field)))


def vary_terrain(simulate_tasks, groups: int, **field):
    """``solvers.crsp.simulate_tasks`` whose ``n_per_task`` blocks run in ``groups``
    parts, part g (block indices ``offset + g q .. ``) on ``perturbed_profile(g)``;
    results joined along the block axis in block order. A call with ``n_slots``,
    ``task_offsets`` or more positional arguments runs unvaried (the calibration's
    forward models make none)."""
    import jax.numpy as jnp

    cache = {}

    def wrapped(params, block, key, profile, stations_x_m, n_per_task, *a, **k):
        if k.get("n_slots") is not None or k.get("task_offsets") is not None or a:
            return simulate_tasks(params, block, key, profile, stations_x_m, n_per_task, *a, **k)
        sizes = [len(s) for s in np.array_split(np.arange(int(n_per_task)), groups) if len(s)]
        offset = k.pop("offset", 0)
        parts, start = [], 0
        for g, n in enumerate(sizes):
            ck = (id(profile), g)
            if ck not in cache:
                cache[ck] = (profile, perturbed_profile(profile, g, **field))
            parts.append(simulate_tasks(params, block, key, cache[ck][1], stations_x_m, n,
                                        offset=offset + start, **k))
            start += n
        return jax.tree_util.tree_map(lambda *v: jnp.concatenate(v, axis=1), *parts)
    return wrapped


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    tool_args: list[str] = []
    if "--" in argv:
        k = argv.index("--")
        argv, tool_args = argv[:k], argv[k + 1:]
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("cmd", choices=("fit", "validate"),
                   help="python -m calib.fit or calib.validate, its arguments after --")
    p.add_argument("--groups", type=int, default=8, help="grounds per parameter set")
    p.add_argument("--spacing-m", type=float, default=10.0,
                   help="knot spacing, m (the Tschamut proxy's README: slope details finer than "
                        "~10 m are uncertain)")
    p.add_argument("--sd-gentle-m", type=float, default=0.15,
                   help="the field's sd where the slope is below --slope-break-deg, m")
    p.add_argument("--sd-steep-m", type=float, default=0.6,
                   help="the field's sd on steeper ground, m")
    p.add_argument("--slope-break-deg", type=float, default=10.0,
                   help="slope over a knot's cell from which --sd-steep-m applies, deg")
    p.add_argument("--seed", type=int, default=0, help="the grounds' seed")
    args = p.parse_args(argv)
    import calib.model.forward as fwd

    fwd.crsp.simulate_tasks = vary_terrain(
        fwd.crsp.simulate_tasks, args.groups, spacing_m=args.spacing_m,
        sd_gentle_m=args.sd_gentle_m, sd_steep_m=args.sd_steep_m,
        slope_break_deg=args.slope_break_deg, seed=args.seed)
    if args.cmd == "fit":
        from calib.fit import main as tool
    else:
        from calib.validate import main as tool
    return tool(tool_args)


if __name__ == "__main__":
    sys.exit(main())
