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
import os

import numpy as np
import pandas as pd

from calib.files.observations import Observations

__all__ = ["Holdout", "hold_out", "holdout_rows", "rows_csv", "subset"]


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
        if f.name == "columns":  # per column, not per row
            continue
        v = getattr(obs, f.name)
        if isinstance(v, np.ndarray) and v.shape[:1] == (n,):
            upd[f.name] = v[rows]
        elif isinstance(v, tuple) and len(v) == n:
            upd[f.name] = tuple(v[i] for i in rows)
    return dataclasses.replace(obs, **upd)


def rows_csv(obs: Observations, rows: np.ndarray, out: str) -> str:
    """The CSV text of ``rows`` as they were read (``Observations.cells``), for a
    file in the folder ``out``: a ``profile`` cell is rewritten relative to
    ``out`` (the rows' profiles stay found from there)."""
    if obs.cells is None:
        raise ValueError("rows built in memory have no cells to write")
    table = pd.DataFrame(list(obs.cells), columns=list(obs.columns), dtype=str)
    if "profile" in table.columns:
        table["profile"] = [os.path.relpath(p, out) if p else "" for p in obs.profile]
    return table.iloc[rows].to_csv(index=False)


@dataclasses.dataclass(frozen=True)
class Holdout:
    """A command's inputs split for a hold-out check (``hold_out``).

    Attributes:
        inputs: the inputs with only the rows to fit (``calib.files.inputs.Inputs``).
        rows_path: the path the fitted rows' file will have in the output folder.
        files: output file name -> CSV text: ``calibration_rows.csv`` and
            ``heldout_rows.csv``, the rows as they were read.
        message: one line saying how many rows were held out and where they go.
    """

    inputs: object
    rows_path: str
    files: dict
    message: str


def hold_out(inputs, fraction: float, seed: int, out: str) -> Holdout:
    """Hold ``fraction`` of ``inputs``' rows out of a fit (``holdout_rows``); both
    row files are for the folder ``out``.

    Raises:
        ValueError: the fraction cannot split the rows (``holdout_rows``).
    """
    obs = inputs.obs
    fit_rows, held_rows = holdout_rows(obs.n_obs, fraction, seed)
    files = {"calibration_rows.csv": rows_csv(obs, fit_rows, out),
             "heldout_rows.csv": rows_csv(obs, held_rows, out)}
    message = (f"holding out {len(held_rows)} of {obs.n_obs} rows (seed {seed}): "
               f"{os.path.join(out, 'heldout_rows.csv')}")
    return Holdout(dataclasses.replace(inputs, obs=subset(obs, fit_rows)),
                   os.path.join(out, "calibration_rows.csv"), files, message)
