"""Synthetic observations made by the solvers themselves, with a known truth.

Used to prove that the calibration recovers what generated the data (tests,
notebooks). Each row is the runout of ONE simulated block of the given size,
plus Gaussian measurement noise of standard deviation ``sd_m`` (and the row's
tolerance is that sd), so the rows follow exactly the observation model of
``calib.likelihood``. The generating key must differ from any key the fit uses
(the fit's common random numbers would otherwise replay the data's blocks).
"""

from __future__ import annotations

import jax
import numpy as np

from calib.forward import CrspForward, DemForward
from calib.observations import Observations

__all__ = ["synthesize"]


def synthesize(forward_cls, profile, truth, sizes_m, n_per_size: int, sd_m: float,
               key: jax.Array, **forward_kw) -> Observations:
    """Observations of ``n_per_size`` blocks per size simulated at ``truth``.

    Args:
        forward_cls: ``CrspForward`` or ``DemForward``.
        profile: slope profile.
        truth: parameter vector (CRSP: Kn, Kt, roughness_m; DEM: the law's parameters).
        sizes_m: block sizes (average diameters), m.
        n_per_size: rows per size.
        sd_m: measurement noise (and stated tolerance), m.
        key: PRNG key of the data (blocks and noise).
        forward_kw: extra arguments of the forward model (e.g. ``form``).
    """
    if forward_cls not in (CrspForward, DemForward):
        raise TypeError("forward_cls must be CrspForward or DemForward")
    k_blocks, k_noise = jax.random.split(key)
    sizes = np.asarray(sizes_m, float)
    fw = forward_cls(profile, sizes, n_per_size, k_blocks, **forward_kw)
    runs = fw.runouts(np.asarray(truth, float)[None])[0]  # (S, n)
    noise = sd_m * np.asarray(jax.random.normal(k_noise, runs.shape))
    y = np.maximum(runs + noise, 0.0)
    return Observations.points(np.repeat(sizes, n_per_size), y.reshape(-1), sd_m,
                               source=(f"synthetic truth {list(map(float, truth))}",) * y.size)
