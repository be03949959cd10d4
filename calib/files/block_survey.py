"""A block survey: the volumes (or masses) of surveyed rockfall blocks, one per row,
read as the empirical volume law of a hazard run (``calib.model.release``,
``python -m calib.hazard --volumes-csv FILE``).

Format: a CSV with a column ``volume_m3`` (m^3) or a column ``mass_kg`` (kg; one
of the two), any other columns ignored (a block id, where it lay, a note).
Masses become volumes with the site's rock density, V = m / rho (the density the
calibration records, ``rock_density_kg_m3``). Every value must be a positive
finite number; a bad cell is refused naming the file, line and column.
"""

from __future__ import annotations

import numpy as np

from calib.model.release import VolumeLaw
from solvers.csv_rows import cell_float, read_csv_rows

__all__ = ["BlockSurveyError", "read_block_survey"]


class BlockSurveyError(ValueError):
    """A block survey that cannot be used; the message names file, line and column."""


def read_block_survey(path: str, density_kg_m3: float) -> VolumeLaw:
    """The survey at ``path`` as an empirical ``VolumeLaw`` (module docstring).

    Args:
        path: the CSV.
        density_kg_m3: rho, for a survey of masses.

    Raises:
        BlockSurveyError: missing file, neither or both columns, a bad cell, no rows.
    """
    header, rows = read_csv_rows(path, "volume_m3 or mass_kg", BlockSurveyError)
    cols = [c for c in ("volume_m3", "mass_kg") if c in header]
    if len(cols) != 1:
        raise BlockSurveyError(f"{path}: line 1: expected one column 'volume_m3' (m^3) or "
                               f"'mass_kg' (kg), got {', '.join(header) or 'none'}")
    col = cols[0]
    values = []
    for line, row in rows:
        v = cell_float(path, line, row, col, BlockSurveyError)
        if v <= 0:
            raise BlockSurveyError(f"{path}: line {line}: column '{col}': expected a positive "
                                   f"number, got {row[col]!r}")
        values.append(v)
    if not values:
        raise BlockSurveyError(f"{path}: no rows below the header")
    vol = np.sort(np.asarray(values, float))
    if col == "mass_kg":
        vol = vol / float(density_kg_m3)
        source = (f"--volumes-csv {path} ({len(vol)} masses, kg, / {density_kg_m3:g} "
                  "kg/m^3)")
    else:
        source = f"--volumes-csv {path} ({len(vol)} volumes, m^3)"
    return VolumeLaw("empirical", tuple(float(v) for v in vol), source)
