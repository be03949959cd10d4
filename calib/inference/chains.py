"""The NUTS chains of a CRSP fit (``calib.inference.calibrate``): where they
start (``chain_starts``) and which of them the simulator keeps
(``screen_chains``)."""

from __future__ import annotations

import numpy as np

from calib.inference.adequacy import loglik_gap_nats
from calib.inference.bayes import Posterior, keep_chains

__all__ = ["N_SCREEN", "chain_starts", "screen_chains"]

N_SCREEN = 8  # draws per chain simulated by the chain screening


def chain_starts(theta: np.ndarray, ll: np.ndarray, box, n_chains: int
                 ) -> np.ndarray | None:
    """(n_chains, d) NUTS starting points: among the 4 x n_chains design points
    inside ``box`` with the highest simulated log-likelihood, the best one,
    then each time the one farthest (in the box's unit coordinates) from those
    already taken (farthest-point selection; our rule).

    Why (measured on ``tests/test_calib_recovery``'s quick CRSP fit): from
    NumPyro's default starts, spread over the box, both chains ended on a
    plateau at the corner Kn 0.150, S 4.0 m, where the GP knows nothing and
    its gradient vanishes; the simulator gave -1,561 nats there against -215
    at the design's best point. Starts spread over the best design points
    keep R-hat meaningful (the chains still start apart) without asking them
    to cross a plateau. None when no design point lies inside ``box``."""
    lo, hi = np.asarray(box.lo, float), np.asarray(box.hi, float)
    theta = np.asarray(theta, float)
    inside = np.all((theta >= lo) & (theta <= hi), axis=1) & np.isfinite(ll)
    if not inside.any():
        return None
    cand = np.flatnonzero(inside)[np.argsort(-np.asarray(ll)[inside])][:4 * n_chains]
    u = (theta[cand] - lo) / (hi - lo)
    take = [0]
    while len(take) < n_chains:
        d = np.min(np.linalg.norm(u[:, None] - u[take][None], axis=-1), axis=1)
        take.append(int(np.argmax(d)))  # a repeated point when fewer candidates than chains
    return theta[cand[take]]


def screen_chains(posterior: Posterior, simulate, rows
                   ) -> tuple[Posterior, dict, tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    """Keep the chains whose draws the SIMULATOR fits about as well as the best
    chain's; drop the others (the emulator was wrong where they sit).

    Each chain's score is the median, over ``N_SCREEN`` of its draws spread
    evenly over its output, of the rows' summed simulated log-likelihood with
    the design's blocks (``simulate``: theta (T, d) -> (runouts (T, S, n),
    passage speeds or None), ``RowLikelihood.simulate``; ``rows``: the fit's
    ``calib.inference.likelihood.RowLikelihood``). A chain whose
    score trails the best chain's by more than ``adequacy.loglik_gap_nats`` is
    dropped and the diagnostics are recomputed on the others
    (``bayes.keep_chains``).

    Our rule; the idea is that of stacking non-mixing chains by how well they
    predict the data (Yao, Vehtari & Gelman 2022, JMLR 23(79)): here the data's
    likelihood under the simulator decides, and a chain far behind gets no
    weight. Measured on the Tschamut rows (seed 1), while NUTS still sampled the
    quantile emulator inside the focus region: two of four chains sat at its
    corners, where the emulated likelihood was good and the simulated one
    300-1,100 nats below the other two chains' (-220). With the log-likelihood
    GP no chain was dropped there; the screening stays as the check.

    Returns:
        (posterior, the ``bayes.chain_screen`` record, (the screened draws
        (T, d), their runouts (T, S, n), their passage speeds or None)): the
        draws go into the next refinement wave's design.
    """
    c, d = posterior.n_chains, posterior.samples.shape[1]
    n = posterior.samples.shape[0] // c
    pick = np.linspace(0, n - 1, min(N_SCREEN, n)).round().astype(int)
    draws = posterior.samples.reshape(c, n, d)[:, pick].reshape(-1, d)
    runs, speeds = simulate(draws)
    ll = rows.summed(runs, speeds).reshape(c, len(pick))
    score = np.median(ll, axis=1)
    bar = loglik_gap_nats(rows.n_rows, d)
    keep = score >= np.max(score) - bar if np.isfinite(score).any() else np.ones(c, bool)
    record = {"rule": (f"chains whose median simulated log-likelihood over {len(pick)} draws "
                       f"trails the best chain's by more than {bar:.1f} nats are dropped"),
              "threshold_nats": float(bar),
              "chain_loglik": [float(v) if np.isfinite(v) else None for v in score],
              "kept": [bool(k) for k in keep], "n_dropped": int((~keep).sum())}
    if not keep.all():
        posterior = keep_chains(posterior, keep)
    return posterior, record, (draws, runs, speeds)
