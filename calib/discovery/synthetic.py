"""Synthetic observations made by the solvers themselves, with a known truth.

Used to prove that the calibration recovers what generated the data (tests,
notebooks). Each row is the runout of ONE simulated block of the given size,
plus Gaussian measurement noise of standard deviation ``sd_m`` (and the row's
tolerance is that sd), so the rows follow exactly the observation model of
``calib.inference.likelihood``. The generating key must differ from any key the fit uses
(the fit's common random numbers would otherwise replay the data's blocks).
Only finished blocks make rows (``calib.model.unfinished``): an unfinished block is
replaced by the next finished one of its size.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from calib.files.observations import Observations, Velocities
from calib.model.forward import CrspForward, DemForward

__all__ = ["LIVE_P_EXCEED", "SYNTH_SIZES_M", "compare_exceedance", "observations_csv_text",
           "synthesize", "synthesize_effect", "synthesize_velocities", "truth_exceedance",
           "velocities_csv_text"]

# size classes of synthetic data with hidden effects (0.2-2.0 m, the paper's range)
SYNTH_SIZES_M = (0.2, 0.4, 0.7, 1.0, 1.4, 2.0)
# a station is live for a size where the truth or a fit exceeds it with more than this
# probability (``compare_exceedance``): below it, fits differ by Monte Carlo error alone
LIVE_P_EXCEED = 0.005


def _finished_runouts(fw, theta, n: int) -> np.ndarray:
    """(S, n) runouts of the first n finished blocks of each size at ``theta``.

    Block j is the same block whatever the forward model's block count (its key
    is fold_in(key, j), ``calib.model.forward``), so with every block finished these
    are blocks 0 .. n - 1, as ``fw.runouts`` gives them; otherwise up to 8 n
    blocks are simulated to replace the unfinished ones.

    Raises:
        ValueError: fewer than n of 8 n blocks of some size finished.
    """
    m = n
    while True:
        runs = (fw if m == n else dataclasses.replace(fw, n_blocks=m)).runouts(
            np.asarray(theta, float)[None])[0]
        ok = np.isfinite(runs)
        if np.all(ok.sum(axis=-1) >= n):
            return np.stack([r[k][:n] for r, k in zip(runs, ok)])
        if m >= 8 * n:
            s = int(np.argmin(ok.sum(axis=-1)))
            raise ValueError(f"only {int(ok[s].sum())} of {m} simulated blocks of "
                             f"{float(fw.sizes_m[s]):g} m finished at the truth; raise the "
                             f"solver's budget")
        m *= 2


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
    runs = _finished_runouts(fw, truth, n_per_size)  # (S, n)
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
    from calib.model import effects

    if n_obs < 1:
        raise ValueError(f"n_obs must be at least 1, got {n_obs}")
    theta = effects.truth(effect, strength, profile, model)
    key = jax.random.fold_in(jax.random.key(seed), 7919)
    k_blocks, k_noise = jax.random.split(key)
    sizes = np.asarray(SYNTH_SIZES_M, float)
    per = -(-n_obs // sizes.size)
    if model == "dem":
        from calib.discovery.dem_candidates import DemEffectForward

        fw = DemEffectForward(profile, sizes, per, k_blocks, effect=effect)
        names = effects.effect_box(effect, profile, "dem").names
    else:
        fw = CrspForward(profile, sizes, per, k_blocks, effect=effect)
        names = fw.names
    runs = _finished_runouts(fw, theta, per)  # (S, per)
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


def synthesize_velocities(profile, effect: str, strength: float, n_obs: int, seed: int,
                          stations_x_m, sd_m_s: float = 1.0) -> Velocities:
    """Passage speeds made with a candidate effect switched on (CRSP).

    ``n_obs`` rows spread round-robin over (station, size) pairs, sizes
    ``SYNTH_SIZES_M``. Each row is the speed of one simulated block at its first
    passage of the station plus N(0, sd_m_s^2) noise (clipped at 0), the
    tolerance being ``sd_m_s``. Only blocks that pass are observed (a speed
    needs a passage), as ``calib.inference.likelihood.velocity_log_likelihood`` assumes.
    The blocks use the key ``fold_in(key(seed), 7927)``: other blocks than the
    runout rows' (7919) and than any fit's.

    Raises:
        ValueError: a station that too few simulated blocks of some size reach.
    """
    from calib.model import effects

    if n_obs < 1:
        raise ValueError(f"n_obs must be at least 1, got {n_obs}")
    stations = np.unique(np.asarray(stations_x_m, float).reshape(-1))
    if stations.size == 0:
        raise ValueError("expected at least one station")
    theta = effects.truth(effect, strength, profile)
    k_blocks, k_noise = jax.random.split(jax.random.fold_in(jax.random.key(seed), 7927))
    sizes = np.asarray(SYNTH_SIZES_M, float)
    pairs = [(k, i) for k in range(stations.size) for i in range(sizes.size)]
    rows = [pairs[r % len(pairs)] for r in range(n_obs)]
    need = -(-n_obs // len(pairs))
    fw = CrspForward(profile, sizes, 4 * need + 16, k_blocks, effect=effect,
                     stations_x_m=tuple(stations))
    speeds = fw.simulate(theta[None])[1][0]  # (S, K, n)
    taken = {}
    v = np.empty(n_obs)
    for r, (k, i) in enumerate(rows):
        passed = speeds[i, k][np.isfinite(speeds[i, k])]
        j = taken.get((k, i), 0)
        if j >= passed.size:
            raise ValueError(f"only {passed.size} of {speeds.shape[-1]} simulated blocks of "
                             f"{sizes[i]:g} m pass the station at {stations[k]:g} m; choose "
                             f"a station that blocks reach")
        v[r] = passed[j]
        taken[(k, i)] = j + 1
    noise = sd_m_s * np.asarray(jax.random.normal(k_noise, (n_obs,)))
    x = np.array([stations[k] for k, _ in rows])
    d = np.array([sizes[i] for _, i in rows])
    return Velocities(x, d, np.maximum(v + noise, 0.0), np.full(n_obs, float(sd_m_s)),
                      (f"synthetic (crsp, effect {effect}, seed {seed})",) * n_obs)


def observations_csv_text(obs: Observations, seed: int) -> str:
    """Synthetic rows as an observations CSV (the schema of ``data/postignano.csv``,
    ``calib.files.observations``): runouts to 1 mm, each row's source naming
    the seed. What ``python -m calib.synth`` writes and the workflow reads."""
    lines = ["block_size_m,runout_m,runout_sd_m,runout_min_m,runout_max_m,source"]
    lines += [f"{d:g},{y:.3f},{s:g},,,synthetic: calib.synth seed {seed}"
              for d, y, s in zip(obs.block_size_m, obs.runout_m, obs.runout_sd_m)]
    return "\n".join(lines) + "\n"


def velocities_csv_text(vel: Velocities, seed: int) -> str:
    """Synthetic passage speeds as a CSV of ``calib.files.observations.load_velocities``
    (speeds to 1 mm/s, each row's source naming the seed)."""
    lines = ["station_x_m,block_size_m,velocity_m_s,velocity_sd_m_s,source"]
    lines += [f"{x:g},{d:g},{v:.3f},{s:g},synthetic: calib.synth seed {seed}"
              for x, d, v, s in zip(vel.station_x_m, vel.block_size_m, vel.velocity_m_s,
                                    vel.velocity_sd_m_s)]
    return "\n".join(lines) + "\n"


def truth_exceedance(profile, effect: str, strength: float, sizes_m, stations_x_m,
                     n_blocks: int, seed: int) -> np.ndarray:
    """The true model's exceedance on a synthetic site, (sizes, stations): the
    fraction of ``n_blocks`` CRSP blocks per size, released at the profile's first
    vertex with the parameters ``synthesize_effect`` makes rows with
    (``calib.model.effects.truth``), whose stop lies beyond each station
    (x0 + runout > x; unfinished blocks left out). No observation noise: this is
    the exceedance a calibration's hazard run should find."""
    from calib.model import effects

    theta = effects.truth(effect, strength, profile, "crsp")
    fw = CrspForward(profile, [float(d) for d in sizes_m], n_blocks, jax.random.key(seed),
                     effect=None if effect == "none" else effect)
    stop = float(profile.x_m[0]) + np.asarray(fw.runouts(np.atleast_2d(theta)))[0]
    return np.array([[np.mean(r[np.isfinite(r)] > x) for x in np.asarray(stations_x_m)]
                     for r in stop])


def compare_exceedance(tables: dict, truth_p: np.ndarray, sizes_m, stations_x_m,
                       road_x_m: float) -> dict:
    """How close fitted hazard runs come to the truth's exceedance (``truth_exceedance``).

    Args:
        tables: {label: exceedance table} (``calib.hazard.exceedance_table``: columns
            block_size_m, x_m, p_exceed_mean, p_exceed_q05, p_exceed_q95), each with
            ``sizes_m`` and ``stations_x_m``.
        truth_p: (sizes, stations) the truth's exceedance.
        road_x_m: the station of interest (the nearest station is reported).

    Returns:
        {str(size): {"n_stations": stations where the truth or a fit exceeds
        ``LIVE_P_EXCEED``,
        label: {"mean_abs_error": mean |P_fit - P_truth| over those stations,
        "truth_in_band": share of them whose truth lies in the fit's 5-95 % band}
        (None where no station is live), "road": {"x_m", "truth", label: [mean, q05,
        q95]}}}.
    """
    stations_x_m = np.asarray(stations_x_m, float)
    out = {}
    for s, d in enumerate(sizes_m):
        rows = {k: t[np.isclose(t["block_size_m"], d)].set_index("x_m").loc[stations_x_m]
                for k, t in tables.items()}
        p_t = truth_p[s]
        live = p_t > LIVE_P_EXCEED
        for r in rows.values():
            live |= r["p_exceed_mean"].to_numpy() > LIVE_P_EXCEED
        entry = {"n_stations": int(live.sum())}
        i_road = int(np.argmin(np.abs(stations_x_m - road_x_m)))
        entry["road"] = {"x_m": float(stations_x_m[i_road]), "truth": float(p_t[i_road])}
        for k, r in rows.items():
            p, lo, hi = (r[c].to_numpy() for c in ("p_exceed_mean", "p_exceed_q05",
                                                   "p_exceed_q95"))
            inside = (lo <= p_t) & (p_t <= hi)
            entry[k] = {
                "mean_abs_error": float(np.abs(p - p_t)[live].mean()) if live.any() else None,
                "truth_in_band": float(inside[live].mean()) if live.any() else None}
            entry["road"][k] = [float(p[i_road]), float(lo[i_road]), float(hi[i_road])]
        out[str(d)] = entry
    return out
