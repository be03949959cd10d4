#!/usr/bin/env python3
"""How noisy, and how biased, is the simulated log-likelihood a CRSP fit emulates?

The main job (``python -m calib.fit``) scores every design point with
``n_blocks_design`` blocks per simulated entry (``calib.inference.budget``) and
fits a GP to the summed log-likelihood (``calib.inference.loglik_emulator``),
taking each point's Monte Carlo variance from a bootstrap over that point's
blocks (``RowLikelihood.noise_var``). This script measures, at given parameter
points, what that estimate is worth: the summed log-likelihood of the rows under
``--replicates`` independent block sets (keys 100, 101, ...) for each block count,
its mean and sd over the sets, and the bootstrap sd of the first set (what the
GP is told). The likelihood is a kernel estimate from simulated runouts
(``calib.inference.likelihood``); its logarithm is biased low with few blocks
(Jensen's inequality), by an amount that depends on the point: the change of the
mean with the block count shows it.

Usage (the figures of docs/studies.md)::

    python scripts/loglik_noise.py data/tschamut2014/observations.csv \\
        --theta 0.51,0.94,0.113,32.6 --theta 0.55,0.92,0.108,9.8 \\
        --theta 0.38,0.973,0.109,36.2 --n-blocks 256,1024,4096

A theta is Kn, Kt, roughness_m, rolling_friction_deg (``CRSP_ROLLING_BOX``).
Rows are grouped into simulated releases as ``calib.fit`` groups them
(``--release-tolerance-m``, its default 1 m), with the site file's release errors.

``--extra-sd-m E`` (comma-separated values) scores the point rows with the
tolerance sqrt(sd^2 + E^2) in place of their own sd: a what-if on the
observation model (a wider kernel averages over more simulated blocks, so the
score is less noisy, and the likelihood is flatter), not what ``calib.fit``
does; E = 0 is its score.

``--knn-k K`` scores the point rows with a kernel at least as wide as the
distance to the K-th nearest simulated runout (``nearest_neighbour_loglik``):
another what-if on the observation model, not what ``calib.fit`` does.

``--rolling-threshold-m-s T`` (comma-separated values) runs the solver with
that rolling threshold in place of the site's (``calib.files.site``; without
one the solver's ``solvers.crsp.ROLLING_THRESHOLD_M_S``: a rebound or a landing slower than
it, normal to the mean slope, keeps the rock on the ground, where it rolls
against the rolling resistance), and ``--entries`` prints every simulated
release's 5/50/95 % runouts: whether that numerical cutoff changes the
results (docs/studies.md, "The rolling threshold"): how a site's
``rolling_threshold_m_s`` is chosen.

``--allocate-cost C`` scores the points once more with each simulated release's
block count chosen among ``--n-blocks`` by its measured share of the noise at
the first ``--theta`` (``release_allocation``), within C times the blocks of
the first count: whether blocks spent where the noise is make a quieter score
than the same blocks spread evenly.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

# bound at import: scripts/fit_with_neighbour_kernel.py replaces the module's name
from calib.inference.likelihood import log_likelihood as _tolerance_kernel  # noqa: E402


def loglik_spread(data: str, thetas: np.ndarray, n_blocks: int, replicates: int,
                  release_tolerance_m: float = 1.0, profile: str | None = None,
                  out: str = ".", extra_sd_m: float = 0.0, knn_k: int = 0,
                  rolling_threshold_m_s: float | None = None, row_shapes: bool = False) -> dict:
    """Summed log-likelihood of the rows of ``data`` at ``thetas`` (P, 4) under
    ``replicates`` block sets of ``n_blocks`` blocks per simulated entry, the
    point rows' tolerance widened to sqrt(sd^2 + ``extra_sd_m``^2); with
    ``knn_k`` > 0 the point rows are scored by ``nearest_neighbour_loglik``
    (the bootstrap sd is then not computed: NaN); the solver run with
    ``rolling_threshold_m_s`` (None: the site's, ``calib.files.site``); with
    ``row_shapes`` each row's block in its ``shape`` column's CRSP class
    (``calib.fit --row-shapes``), else spheres.

    Returns:
        dict with ``summed`` (R, P) nats, ``mean`` and ``sd`` (P,) over the sets
        (sd with ddof 1), ``bootstrap_sd`` (P,) of the first set
        (``RowLikelihood.noise_var``), ``pointwise`` (R, P, n_rows) each row's
        log-likelihood, ``entry_quantiles_m`` (3, P, E) the 5/50/95 % quantiles
        of each simulated entry's runouts in the first set, ``row_entry``
        (n_rows,), ``row_label`` (n_rows,) the run id or the file's line, the
        observed ``runout_m`` (n_rows,), ``n_blocks`` and ``seconds``.
    """
    from calib.files.inputs import load_inputs
    from calib.inference.likelihood import RowLikelihood
    from calib.model.forward import CrspForward
    from calib.model.priors import CRSP_ROLLING_BOX

    inputs = load_inputs(data, profile, out)
    entries = inputs.entries(release_tolerance_m, row_shapes)
    obs = inputs.obs
    if extra_sd_m:
        obs = dataclasses.replace(obs, runout_sd_m=np.hypot(obs.runout_sd_m, extra_sd_m))
    rows = RowLikelihood(obs, entries.index)
    threshold = (inputs.site.rolling_threshold_m_s if rolling_threshold_m_s is None
                 else rolling_threshold_m_s)
    t0 = time.perf_counter()
    summed, pointwise, boot, quantiles = [], [], None, None
    for r in range(replicates):
        fw = CrspForward(inputs.profile, entries, n_blocks, jax.random.key(100 + r),
                         box=CRSP_ROLLING_BOX, rolling_threshold_m_s=threshold)
        runs = fw.runouts(np.asarray(thetas, float))
        if knn_k:
            idx = np.asarray(entries.index)
            pw = np.asarray(jax.vmap(lambda r: nearest_neighbour_loglik(
                r[idx], *rows.rows, knn_k))(runs))
        else:
            pw = np.asarray(rows.pointwise(runs))
        summed.append(pw.sum(axis=1))
        pointwise.append(pw)
        if boot is None:
            boot = np.sqrt(rows.noise_var(runs)) if not knn_k else np.full(len(thetas), np.nan)
            quantiles = np.nanquantile(runs, [0.05, 0.5, 0.95], axis=-1)
    summed = np.array(summed)
    ids = obs.run_id if obs.run_id is not None else np.full(obs.n_obs, "")
    labels = np.array([str(i) if i else f"line {k + 2}" for k, i in enumerate(ids)])
    return {"summed": summed, "pointwise": np.array(pointwise), "entry_quantiles_m": quantiles,
            "n_blocks": n_blocks,
            "row_entry": np.asarray(entries.index), "row_label": labels,
            "runout_m": np.asarray(obs.runout_m, float), "mean": summed.mean(0),
            "sd": summed.std(0, ddof=1) if replicates > 1 else np.full(summed.shape[1], np.nan),
            "bootstrap_sd": boot, "seconds": time.perf_counter() - t0}


def nearest_neighbour_loglik(samples, y_m, sd_m, lo_m, hi_m, is_interval, k: int,
                             extra_var_m2=0.0):
    """``calib.inference.likelihood.log_likelihood`` with each point row's kernel at
    least as wide as the distance from the observation to its k-th nearest
    simulated runout (JAX, jit-able; same arguments, and ``k`` a Python int).

    Row i's kernel sd is h_i = max(s_i, d_(k)), d_(k) the k-th smallest |y_i - r_j|
    over its finished samples (the farthest finished one where fewer than k
    finish; s_i where none does); interval rows are unchanged. A what-if on the
    observation model (a balloon kernel estimate: Loftsgaarden & Quesenberry
    1965, Ann. Math. Statist. 36, 1049-1051; Terrell & Scott 1992, Ann. Statist.
    20, 1236-1265): at least k samples lie within one width of the observation,
    so a row in a thinly populated tail draws on k blocks, not on the few a 2 m
    kernel reaches; the price is a likelihood that falls off slowly where the
    model puts few blocks. Not what ``calib.fit`` does
    (``scripts/fit_with_neighbour_kernel.py`` fits with it).
    """
    import jax.numpy as jnp

    d = jnp.where(jnp.isfinite(samples), jnp.abs(samples - y_m[:, None]), jnp.inf)
    near = -jax.lax.top_k(-d, min(k, samples.shape[-1]))[0]  # the k smallest distances
    kth = jnp.max(jnp.where(jnp.isfinite(near), near, 0.0), axis=-1)
    sd = jnp.where(is_interval, sd_m, jnp.maximum(sd_m, kth))
    return _tolerance_kernel(samples, y_m, sd, lo_m, hi_m, is_interval, extra_var_m2)


def tail_mixture(base: dict, more: dict) -> dict:
    """The score with more blocks only where the rows lie in their release's tails.

    ``base`` and ``more``: ``loglik_spread`` at two block counts (same data,
    points and replicates). A simulated entry is a tail entry at a point when
    one of its rows' observed runout lies outside that entry's simulated 5-95 %
    range in ``base``'s first set; its rows take their log-likelihood from
    ``more``, the other rows from ``base``.

    Returns:
        dict with ``summed`` (R, P), ``mean`` and ``sd`` (P,), ``n_tail_entries``
        (P,) and ``cost`` (P,): the blocks simulated relative to ``base``
        alone, (n_base (E - T) + n_more T) / (n_base E).
    """
    q05, q95 = base["entry_quantiles_m"][0], base["entry_quantiles_m"][2]  # (P, E)
    e_of, y = base["row_entry"], base["runout_m"]
    n_entries = q05.shape[1]
    n_base = base["n_blocks"]
    summed, n_tail, cost = [], [], []
    for j in range(q05.shape[0]):
        outside = np.isfinite(y) & ((y < q05[j, e_of]) | (y > q95[j, e_of]))
        tail = np.zeros(n_entries, bool)
        tail[e_of[outside]] = True
        from_more = tail[e_of]
        summed.append(np.where(from_more, more["pointwise"][:, j], base["pointwise"][:, j])
                      .sum(axis=1))
        n_tail.append(int(tail.sum()))
        cost.append((n_base * (n_entries - tail.sum()) + more["n_blocks"] * tail.sum())
                    / (n_base * n_entries))
    summed = np.array(summed).T
    return {"summed": summed, "mean": summed.mean(0), "sd": summed.std(0, ddof=1),
            "n_tail_entries": np.array(n_tail), "cost": np.array(cost)}


def release_allocation(runs: list[dict], cost: float, pilot: int = 0) -> dict:
    """The score with each simulated release's block count chosen by its measured
    share of the noise, at a fixed cost.

    ``runs``: ``loglik_spread`` at several block counts (same data, points and
    replicates), the first the base count. At the ``pilot`` point, each entry's
    variance over the replicates of the summed log-likelihood of its rows is
    measured at every count. Starting from the base count everywhere, the
    upgrade (an entry to its next count) with the largest fall in that variance
    per added block is made, then the next, while the blocks stay within
    ``cost`` times the base's: a greedy version of Neyman allocation (block
    count proportional to an entry's per-block sd; Cochran 1977, "Sampling
    Techniques", Sect. 5.5) on the measured variances. Each point's score then
    takes each entry's rows from its chosen count. The choice is made on the
    replicates that measure it, so at the pilot the sd is optimistic; the other
    points are the test.

    Returns:
        dict with ``n_blocks`` (E,) the chosen count per entry, ``cost`` the
        blocks relative to the base, ``summed`` (R, P), ``mean`` and ``sd`` (P,).
    """
    counts = [r["n_blocks"] for r in runs]
    e_of = runs[0]["row_entry"]
    n_entries = int(e_of.max()) + 1
    # (count, R, P, E): the summed log-likelihood of each entry's rows
    per_entry = np.stack([np.stack([r["pointwise"][:, :, e_of == e].sum(axis=2)
                                    for e in range(n_entries)], axis=2) for r in runs])
    var = per_entry[:, :, pilot].var(axis=1, ddof=1)  # (count, E)
    level = np.zeros(n_entries, int)
    budget = cost * counts[0] * n_entries
    spent = counts[0] * n_entries
    while True:
        best, gain = None, 0.0
        for e in range(n_entries):
            k = level[e]
            if k + 1 < len(counts) and spent + counts[k + 1] - counts[k] <= budget:
                g = (var[k, e] - var[k + 1, e]) / (counts[k + 1] - counts[k])
                if g > gain:
                    best, gain = e, g
        if best is None:
            break
        spent += counts[level[best] + 1] - counts[level[best]]
        level[best] += 1
    summed = sum(per_entry[level[e], :, :, e] for e in range(n_entries))  # (R, P)
    return {"n_blocks": np.array([counts[k] for k in level]),
            "cost": spent / (counts[0] * n_entries), "summed": summed,
            "mean": summed.mean(0), "sd": summed.std(0, ddof=1)}


def _theta(text: str) -> np.ndarray:
    try:
        v = np.array([float(s) for s in text.split(",")])
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected Kn,Kt,roughness_m,"
                                         "rolling_friction_deg") from None
    if v.size != 4:
        raise argparse.ArgumentTypeError(f"{text!r}: expected 4 numbers, got {v.size}")
    return v


def _label(theta: np.ndarray) -> str:
    """A parameter point as typed: Kn,Kt,roughness_m,rolling_friction_deg."""
    return ",".join(f"{v:g}" for v in theta)


def _comma_list(cast, lowest, what: str):
    """An argparse type: comma-separated values of ``cast``, each >= ``lowest``."""
    def parse(text: str) -> list:
        try:
            values = [cast(s) for s in text.split(",")]
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r}: expected comma-separated values, each a {what}") from None
        if min(values) < lowest:
            raise argparse.ArgumentTypeError(f"{text!r}: every {what} must be >= {lowest:g}")
        return values

    return parse


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description="Mean and Monte Carlo sd of the summed CRSP log-likelihood of a data "
                    "set's rows at given parameter points, per block count.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("data", help="observations CSV (as calib.fit takes it)")
    p.add_argument("--theta", type=_theta, action="append", required=True,
                   help="Kn,Kt,roughness_m,rolling_friction_deg (repeat for several points)")
    p.add_argument("--n-blocks", type=_comma_list(int, 2, "block count"), default=[256, 1024],
                   help="blocks per simulated entry, comma-separated")
    p.add_argument("--replicates", type=int, default=8, help="independent block sets")
    p.add_argument("--extra-sd-m", type=_comma_list(float, 0.0, "width (m)"), default=[0.0],
                   help="widen the point rows' tolerance to sqrt(sd^2 + E^2), comma-"
                        "separated E values in m (a what-if; 0 is calib.fit's score)")
    p.add_argument("--knn-k", type=_comma_list(int, 0, "neighbour count"), default=[0],
                   help="also score the point rows with a kernel at least as wide as the "
                        "distance to the k-th nearest simulated runout, comma-separated k "
                        "values (a what-if on the observation model; 0 is calib.fit's score)")
    p.add_argument("--rolling-threshold-m-s", type=_comma_list(float, 1e-6, "speed (m/s)"),
                   default=None,
                   help="run the solver with these rolling thresholds, comma-separated, m/s "
                        "(a what-if; None: the site's, else the solver's "
                        "solvers.crsp.ROLLING_THRESHOLD_M_S)")
    p.add_argument("--entries", action="store_true",
                   help="also print every simulated release's 5/50/95 %% runouts (first set)")
    p.add_argument("--rows", type=int, default=0,
                   help="also print, per point, the rows whose log-likelihood varies most "
                        "between block sets, with their release's simulated 5/50/95 %% "
                        "runouts (first set)")
    p.add_argument("--tail-blocks", type=int, default=0,
                   help="also score each block count's rows with this many blocks for the "
                        "releases whose rows lie outside their simulated 5-95 %% range "
                        "(the others keep the block count): the spread and the cost of that "
                        "allocation (0: not done)")
    p.add_argument("--allocate-cost", type=_comma_list(float, 1.0, "cost factor"), default=[],
                   help="also score the points with each release's block count chosen among "
                        "--n-blocks by its share of the noise at the first --theta, within "
                        "this many times the blocks of the first count (comma-separated "
                        "factors; none: not done)")
    p.add_argument("--release-tolerance-m", type=float, default=1.0,
                   help="as calib.fit's option of the same name")
    p.add_argument("--profile", help="profile CSV (default: as calib.fit finds it)")
    p.add_argument("--row-shapes", action="store_true",
                   help="as calib.fit's option of the same name: each row's block in its shape "
                        "column's CRSP class (default: spheres)")
    a = p.parse_args(argv)
    if a.replicates < 2:
        p.error("--replicates must be >= 2")
    if a.tail_blocks and a.tail_blocks < 2:
        p.error("--tail-blocks must be 0 or >= 2")
    from calib.files.inputs import InputError

    thetas = np.array(a.theta)
    for extra, knn_k, thr in [(e, k, t) for e in a.extra_sd_m for k in a.knn_k
                              for t in (a.rolling_threshold_m_s or [None])]:
        runs = []
        for n in a.n_blocks:
            try:
                s = loglik_spread(a.data, thetas, n, a.replicates, a.release_tolerance_m,
                                  a.profile, extra_sd_m=extra, knn_k=knn_k,
                                  rolling_threshold_m_s=thr, row_shapes=a.row_shapes)
            except InputError as e:
                print(f"error: {e}", file=sys.stderr)
                return 2
            runs.append(s)
            kernel = f", kernel to the {knn_k}-th nearest runout" if knn_k else ""
            cutoff = f", rolling threshold {thr:g} m/s" if thr is not None else ""
            print(f"{n} blocks per entry, {a.replicates} block sets, extra sd {extra:g} m"
                  f"{kernel}{cutoff} ({s['seconds']:.0f} s)")
            for j, t in enumerate(thetas):
                print(f"  theta {_label(t):28s} mean "
                      f"{s['mean'][j]:9.1f}  sd {s['sd'][j]:5.2f}  bootstrap sd of one set "
                      f"{s['bootstrap_sd'][j]:5.2f}")
                if a.entries:
                    q = np.round(s["entry_quantiles_m"][:, j]).astype(int)
                    print("    releases' 5/50/95 % runouts (m): "
                          + "  ".join(f"{lo}/{mid}/{hi}" for lo, mid, hi in q.T))
                row_sd = s["pointwise"][:, j].std(axis=0, ddof=1)
                for i in np.argsort(row_sd)[::-1][:a.rows]:
                    e = s["row_entry"][i]
                    q = s["entry_quantiles_m"][:, j, e]
                    print(f"    row {s['row_label'][i]:8s} observed {s['runout_m'][i]:6.1f} m"
                          f"  log-lik mean {s['pointwise'][:, j, i].mean():7.2f} sd "
                          f"{row_sd[i]:4.2f}  its release simulated {q[0]:.0f} / {q[1]:.0f} / "
                          f"{q[2]:.0f} m")
            if a.tail_blocks:
                more = loglik_spread(a.data, thetas, a.tail_blocks, a.replicates,
                                     a.release_tolerance_m, a.profile, extra_sd_m=extra,
                                     knn_k=knn_k, row_shapes=a.row_shapes)
                mix = tail_mixture(s, more)
                print(f"  with {a.tail_blocks} blocks for the tail releases "
                      f"({more['seconds']:.0f} s):")
                for j, t in enumerate(thetas):
                    print(f"  theta {_label(t):28s} mean "
                          f"{mix['mean'][j]:9.1f}  sd {mix['sd'][j]:5.2f}  tail releases "
                          f"{mix['n_tail_entries'][j]}  blocks x{mix['cost'][j]:.2f}")
        for cost in a.allocate_cost:
            alloc = release_allocation(runs, cost)
            chosen = ", ".join(f"{c} x{int((alloc['n_blocks'] == c).sum())}"
                               for c in a.n_blocks if (alloc["n_blocks"] == c).any())
            print(f"  each release's blocks by its share of the noise at the first point, "
                  f"within x{cost:g} of {a.n_blocks[0]} per release: {chosen} "
                  f"(blocks x{alloc['cost']:.2f})")
            for j, t in enumerate(thetas):
                print(f"  theta {_label(t):28s} mean {alloc['mean'][j]:9.1f}  sd "
                      f"{alloc['sd'][j]:5.2f}" + ("  (chosen here)" if j == 0 else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
