"""Calibration files for the hazard tests (schema rockfall-calibration/1); helpers only,
no tests (named test_hazard_* to sit with them)."""

from __future__ import annotations

import json
import os

import numpy as np

PROFILE = os.path.abspath("data/postignano_profile.csv")


def _summary(v):
    return {"map": v, "mean": v, "q05": v, "q95": v}


def write_calibration(folder, *, crsp=(0.41, 0.87, 2.0), dem=(0.40, 0.5), profile=PROFILE,
                      crsp_posterior=None, dem_posterior=None, name="calibration.json",
                      crsp_names=None, extra=None):
    """Write ``calibration.json`` (and posterior CSVs) into ``folder``.

    Args:
        crsp: (Kn, Kt, roughness_m[, rolling_friction_deg]) map values, or None for
            no CRSP section.
        crsp_names: names of ``crsp``'s values (default: the above), e.g. with one
            ``rolling_friction_deg[<zone>]`` per zone.
        dem: (a, b) of alpha = a L^-b, or None for no DEM section.
        crsp_posterior: (R, 3) rows for crsp_posterior.csv, or None (null).
        dem_posterior: (R, 2) rows for dem_posterior.csv, or None.
        extra: more top-level keys of the file (e.g. ``rock_density_kg_m3``).

    Returns:
        Path of the json file.
    """
    folder = str(folder)
    doc = {"schema": "rockfall-calibration/1", "data_csv": "data/postignano.csv",
           "profile_csv": profile, "seed": 0, "versions": {},
           "block_size_mapping": {"crsp_radius_m": "block_size_m / 2",
                                  "dem_side_m": "block_size_m"},
           "fit_quality": []}
    if crsp is not None:
        names = crsp_names or ("Kn", "Kt", "roughness_m", "rolling_friction_deg")[:len(crsp)]
        doc["crsp"] = {k: _summary(v) for k, v in zip(names, crsp, strict=True)}
        doc["crsp"]["posterior_csv"] = None
        if crsp_posterior is not None:
            doc["crsp"]["posterior_csv"] = "crsp_posterior.csv"
            _write_rows(os.path.join(folder, "crsp_posterior.csv"), ",".join(names),
                        crsp_posterior)
    if dem is not None:
        doc["dem"] = {"alpha_law": {"form": "power", "a": _summary(dem[0]),
                                    "b": _summary(dem[1])},
                      "alpha_at_L": {}, "posterior_csv": None}
        if dem_posterior is not None:
            doc["dem"]["posterior_csv"] = "dem_posterior.csv"
            _write_rows(os.path.join(folder, "dem_posterior.csv"), "a,b", dem_posterior)
    doc.update(extra or {})
    path = os.path.join(folder, name)
    with open(path, "w") as fh:
        json.dump(doc, fh)
    return path


def _write_rows(path, header, rows):
    with open(path, "w") as fh:
        fh.write(header + "\n")
        for r in np.asarray(rows, dtype=float):
            fh.write(",".join(f"{v:.6g}" for v in r) + "\n")


def posterior_rows(n, seed=1):
    """A plausible CRSP posterior sample (n, 3)."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0.35, 0.47, n), rng.uniform(0.83, 0.90, n),
                            rng.uniform(1.5, 2.5, n)])
