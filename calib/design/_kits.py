"""Barrier kit catalogues: the CSV a design is checked against (``data/barrier_kits.csv``
holds generic classes; ``data/README.md`` says where its numbers come from).

Format: lines starting with ``#`` are comments; a header with the columns
``KIT_COLUMNS`` (others are ignored); one kit per line. ``kit`` a unique name;
``mel_kJ`` > 0; ``sel_kJ`` empty (no SEL test) or in (0, MEL]; ``nominal_height_m``
> 0; ``residual_height_category`` A, B or C; ``max_elongation_m`` > 0. Every
error names the file, the line and the column.
"""

from __future__ import annotations

import csv
import math
from typing import NamedTuple

__all__ = ["CATEGORIES", "KIT_COLUMNS", "Kit", "KitError", "load_kits"]

KIT_COLUMNS = ("kit", "mel_kJ", "sel_kJ", "nominal_height_m", "residual_height_category",
               "max_elongation_m")
CATEGORIES = ("A", "B", "C")


class KitError(ValueError):
    """A kit catalogue that cannot be used; the message names file, line, column."""


class Kit(NamedTuple):
    """One barrier kit (``KIT_COLUMNS``); ``sel_kJ`` None where it has no SEL test;
    ``line`` the file line it came from."""

    name: str
    mel_kJ: float
    sel_kJ: float | None
    nominal_height_m: float
    residual_height_category: str
    max_elongation_m: float
    line: int


def _positive(path: str, line: int, col: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise KitError(f"{path}: line {line}, column {col}: expected a positive number, got "
                       f"{text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise KitError(f"{path}: line {line}, column {col}: expected a positive number, got "
                       f"{text!r}")
    return v


def load_kits(path: str) -> tuple[Kit, ...]:
    """Read a kit catalogue (module docstring), kits in file order.

    Raises:
        KitError: missing or unreadable file, missing column, bad value, repeated
            name, or no kit at all.
    """
    try:
        with open(path, newline="") as fh:
            lines = fh.read().splitlines()
    except FileNotFoundError:
        raise KitError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise KitError(f"{path}: cannot read ({getattr(exc, 'strerror', None) or exc})"
                       ) from None
    numbered = [(i + 1, text) for i, text in enumerate(lines)
                if text.strip() and not text.lstrip().startswith("#")]
    if not numbered:
        raise KitError(f"{path}: no header and no kits (expected columns "
                       f"{', '.join(KIT_COLUMNS)})")
    header_line, header = numbered[0]
    names = [h.strip() for h in next(csv.reader([header]))]
    missing = [c for c in KIT_COLUMNS if c not in names]
    if missing:
        raise KitError(f"{path}: line {header_line}: missing column(s) {', '.join(missing)}")
    kits, seen = [], {}
    for line, text in numbered[1:]:
        cells = [c.strip() for c in next(csv.reader([text]))]
        if len(cells) != len(names):
            raise KitError(f"{path}: line {line}: expected {len(names)} fields, got "
                           f"{len(cells)}")
        row = dict(zip(names, cells, strict=True))
        name = row["kit"]
        if not name:
            raise KitError(f"{path}: line {line}, column kit: expected a name")
        if name in seen:
            raise KitError(f"{path}: line {line}, column kit: {name!r} repeats line "
                           f"{seen[name]}")
        seen[name] = line
        mel = _positive(path, line, "mel_kJ", row["mel_kJ"])
        sel = None if row["sel_kJ"] == "" else _positive(path, line, "sel_kJ", row["sel_kJ"])
        if sel is not None and sel > mel:
            raise KitError(f"{path}: line {line}, column sel_kJ: {sel:g} exceeds mel_kJ "
                           f"{mel:g}")
        cat = row["residual_height_category"].upper()
        if cat not in CATEGORIES:
            raise KitError(f"{path}: line {line}, column residual_height_category: expected "
                           f"A, B or C, got {row['residual_height_category']!r}")
        kits.append(Kit(name, mel, sel,
                        _positive(path, line, "nominal_height_m", row["nominal_height_m"]), cat,
                        _positive(path, line, "max_elongation_m", row["max_elongation_m"]),
                        line))
    if not kits:
        raise KitError(f"{path}: no kit rows after the header (line {header_line})")
    return tuple(kits)
