"""A reproducible split of observation rows into calibration and held-out rows.

``python -m calib.fit --holdout-fraction F --seed S`` keeps ``round(F n)`` rows
(at least 1, and at least 2 left to fit) aside for ``calib.validate``: the rows
are permuted by a NumPy generator seeded with S, so the same file, fraction
and seed give the same split on any machine (NumPy's PCG64 stream is stable
across versions). The split is not stratified by block size: our choice, so
that a split never depends on how sizes were rounded.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from calib.files.observations import Observations

__all__ = ["holdout_rows", "subset"]


def holdout_rows(n_rows: int, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(fit rows, held-out rows), each sorted, 0-based.

    Raises:
        ValueError: fraction outside (0, 1), or too few rows to keep 2 for the fit
            and 1 aside.
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"--holdout-fraction: expected a fraction in (0, 1), got {fraction:g}")
    n_held = int(round(fraction * n_rows))
    n_held = max(1, n_held)
    if n_rows - n_held < 2:
        raise ValueError(f"--holdout-fraction {fraction:g}: {n_rows} rows leave fewer than 2 "
                         "to fit")
    perm = np.random.default_rng(seed).permutation(n_rows)
    return np.sort(perm[n_held:]), np.sort(perm[:n_held])


def subset(obs: Observations, rows: np.ndarray) -> Observations:
    """The observations of ``rows`` (every per-row field indexed)."""
    n = obs.n_obs
    upd = {}
    for f in dataclasses.fields(obs):
        v = getattr(obs, f.name)
        if isinstance(v, np.ndarray) and v.shape[:1] == (n,):
            upd[f.name] = v[rows]
        elif isinstance(v, tuple) and len(v) == n:
            upd[f.name] = tuple(v[i] for i in rows)
    return dataclasses.replace(obs, **upd)
