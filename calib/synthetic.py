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

__all__ = ["SYNTH_SIZES_M", "synthesize", "synthesize_effect"]

# size classes of synthetic data with hidden effects (0.2-2.0 m, the paper's range)
SYNTH_SIZES_M = (0.2, 0.4, 0.7, 1.0, 1.4, 2.0)


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


def synthesize_effect(profile, effect: str, strength: float, n_obs: int, seed: int,
                      model: str = "crsp", sd_m: float = 5.0):
    """Observations made with a candidate effect switched on, and their truth.

    ``n_obs`` rows spread round-robin over ``SYNTH_SIZES_M``; each row is one
    simulated block plus N(0, sd_m^2) noise (``synthesize``). The blocks use the
    key ``fold_in(key(seed), 7919)``, which no fit uses (fits key their common
    random numbers from their own ``--seed``). Values are clipped to the
    profile's extent (a survey maps the slope, not beyond it).

    Returns:
        (Observations, truth dict: effect, strength, model, parameter names and values).
    """
    from calib import effects

    if n_obs < 1:
        raise ValueError(f"n_obs must be at least 1, got {n_obs}")
    theta = effects.truth(effect, strength, profile, model)
    key = jax.random.fold_in(jax.random.key(seed), 7919)
    k_blocks, k_noise = jax.random.split(key)
    sizes = np.asarray(SYNTH_SIZES_M, float)
    per = -(-n_obs // sizes.size)
    if model == "dem":
        from calib.dem_candidates import DemEffectForward

        fw = DemEffectForward(profile, sizes, per, k_blocks, effect=effect)
        names = effects.effect_box(effect, profile, "dem").names
    else:
        fw = CrspForward(profile, sizes, per, k_blocks, effect=effect)
        names = fw.names
    runs = fw.runouts(theta[None])[0]  # (S, per)
    rows = np.arange(n_obs)
    size_i, block_j = rows % sizes.size, rows // sizes.size
    noise = sd_m * np.asarray(jax.random.normal(k_noise, (n_obs,)))
    # a runout is observed on the mapped profile only (noise cannot move it off)
    y = np.clip(runs[size_i, block_j] + noise, 0.0, float(profile.x_m[-1] - profile.x_m[0]))
    obs = Observations.points(sizes[size_i], y, sd_m,
                              source=(f"synthetic ({model}, effect {effect}, seed {seed})",)
                              * n_obs)
    truth = {"effect": effect, "strength": float(strength), "model": model, "seed": seed,
             "sd_m": sd_m, "parameters": dict(zip(names, map(float, theta)))}
    return obs, truth
