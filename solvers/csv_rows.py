"""CSV input read row by row, with errors that name the file, line and column.

Library code of both packages reads its CSV inputs (profiles, lines, field
runs) through these two functions; each caller passes its own exception class
(``ProfileError``, ``RasterError``, ``FieldError``), which its command turns
into one line and exit status 2.
"""

from __future__ import annotations

import csv
import math
import os

__all__ = ["cell_float", "read_csv_rows"]


def read_csv_rows(path: str, what: str,
                  error: type[Exception]) -> tuple[list[str], list[tuple[int, dict]]]:
    """A CSV's stripped header and its non-blank rows as ``(file line, {column: text})``.

    Args:
        path: the file.
        what: what the header should be, for the message of an empty file.
        error: exception class raised for a missing, empty or non-UTF-8 file.
    """
    if not os.path.isfile(path):
        raise error(f"{path}: file not found")
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            if not reader.fieldnames:
                raise error(f"{path}: line 1: empty file; expected a header ({what})")
            header = [h.strip() for h in reader.fieldnames]
            rows = []
            for raw in reader:
                row = {k.strip(): (v or "").strip() for k, v in raw.items() if k is not None}
                if any(row.values()):
                    rows.append((reader.line_num, row))
    except UnicodeDecodeError:
        raise error(f"{path}: not a UTF-8 text CSV file") from None
    return header, rows


def cell_float(path: str, line: int, row: dict, col: str, error: type[Exception]) -> float:
    """A CSV cell as a finite float; otherwise ``error`` naming file, line and column."""
    text = row.get(col, "")
    try:
        value = float(text)
    except ValueError:
        raise error(f"{path}: line {line}: column '{col}': expected a number, "
                    f"got {text!r}") from None
    if not math.isfinite(value):
        raise error(f"{path}: line {line}: column '{col}': expected a finite number, "
                    f"got {text!r}")
    return value
