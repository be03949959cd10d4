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
"""

from __future__ import annotations

import argparse
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)


def loglik_spread(data: str, thetas: np.ndarray, n_blocks: int, replicates: int,
                  release_tolerance_m: float = 1.0, profile: str | None = None,
                  out: str = ".") -> dict:
    """Summed log-likelihood of the rows of ``data`` at ``thetas`` (P, 4) under
    ``replicates`` block sets of ``n_blocks`` blocks per simulated entry.

    Returns:
        dict with ``summed`` (R, P) nats, ``mean`` and ``sd`` (P,) over the sets
        (sd with ddof 1), ``bootstrap_sd`` (P,) of the first set
        (``RowLikelihood.noise_var``) and ``seconds``.
    """
    from calib.files.inputs import load_inputs
    from calib.inference.likelihood import RowLikelihood
    from calib.model.forward import CrspForward
    from calib.model.priors import CRSP_ROLLING_BOX

    inputs = load_inputs(data, profile, out)
    entries = inputs.entries(release_tolerance_m)
    rows = RowLikelihood(inputs.obs, entries.index)
    t0 = time.perf_counter()
    summed, boot = [], None
    for r in range(replicates):
        fw = CrspForward(inputs.profile, entries, n_blocks, jax.random.key(100 + r),
                         box=CRSP_ROLLING_BOX)
        runs = fw.runouts(np.asarray(thetas, float))
        summed.append(rows.summed(runs))
        if boot is None:
            boot = np.sqrt(rows.noise_var(runs))
    summed = np.array(summed)
    return {"summed": summed, "mean": summed.mean(0),
            "sd": summed.std(0, ddof=1) if replicates > 1 else np.full(summed.shape[1], np.nan),
            "bootstrap_sd": boot, "seconds": time.perf_counter() - t0}


def _theta(text: str) -> np.ndarray:
    try:
        v = np.array([float(s) for s in text.split(",")])
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected Kn,Kt,roughness_m,"
                                         "rolling_friction_deg") from None
    if v.size != 4:
        raise argparse.ArgumentTypeError(f"{text!r}: expected 4 numbers, got {v.size}")
    return v


def _counts(text: str) -> list[int]:
    try:
        n = [int(s) for s in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected integers") from None
    if min(n) < 2:
        raise argparse.ArgumentTypeError(f"{text!r}: every block count must be >= 2")
    return n


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description="Mean and Monte Carlo sd of the summed CRSP log-likelihood of a data "
                    "set's rows at given parameter points, per block count.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("data", help="observations CSV (as calib.fit takes it)")
    p.add_argument("--theta", type=_theta, action="append", required=True,
                   help="Kn,Kt,roughness_m,rolling_friction_deg (repeat for several points)")
    p.add_argument("--n-blocks", type=_counts, default=[256, 1024],
                   help="blocks per simulated entry, comma-separated")
    p.add_argument("--replicates", type=int, default=8, help="independent block sets")
    p.add_argument("--release-tolerance-m", type=float, default=1.0,
                   help="as calib.fit's option of the same name")
    p.add_argument("--profile", help="profile CSV (default: as calib.fit finds it)")
    a = p.parse_args(argv)
    if a.replicates < 2:
        p.error("--replicates must be >= 2")
    from calib.files.inputs import InputError

    thetas = np.array(a.theta)
    for n in a.n_blocks:
        try:
            s = loglik_spread(a.data, thetas, n, a.replicates, a.release_tolerance_m,
                              a.profile)
        except InputError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"{n} blocks per entry, {a.replicates} block sets ({s['seconds']:.0f} s)")
        for j, t in enumerate(thetas):
            print(f"  theta {','.join(f'{v:g}' for v in t):28s} mean {s['mean'][j]:9.1f}"
                  f"  sd {s['sd'][j]:5.2f}  bootstrap sd of one set {s['bootstrap_sd'][j]:5.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
