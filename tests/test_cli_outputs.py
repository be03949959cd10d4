"""Outputs written by every command (``solvers.cli.write_all_atomic``) are files a
colleague can open: they get the user's umask, like any file the user writes."""

from __future__ import annotations

import os
import stat

import pytest

from solvers.cli import text_writer, write_all_atomic


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_outputs_follow_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        paths = write_all_atomic({str(tmp_path / "a.csv"): text_writer("x\n"),
                                  str(tmp_path / "sub" / "b.json"): text_writer("{}\n")})
    finally:
        os.umask(old)
    for p in paths:
        assert stat.S_IMODE(os.stat(p).st_mode) == mode, (p, oct(os.stat(p).st_mode))



def test_both_solvers_write_one_schema():
    """``python -m solvers.crsp --out`` and ``python -m solvers.dem --out`` lead with
    the columns of ``solvers.cli.run_columns`` (names, order, units: the CSVs
    themselves are checked in tests/test_crsp_cli.py and tests/test_dem.py),
    one row per fragment, and both --help texts list that schema with the
    energy in its own unit (kJ per block against kJ per metre of width)."""
    import numpy as np

    from solvers.cli import RUN_COLUMNS, run_columns
    from solvers.crsp.__main__ import build_parser as crsp_parser
    from solvers.dem.__main__ import build_parser as dem_parser
    from solvers.status import BUDGET, STOPPED

    assert list(RUN_COLUMNS)[:4] == ["block", "fragment", "block_size_m", "status"]
    z = np.zeros(6)
    cols = run_columns(0.8, [STOPPED] * 5 + [BUDGET], z + 1.0, z + 2.0, z + 3.0, n_fragments=2)
    assert list(cols) == list(RUN_COLUMNS)
    assert list(cols["block"]) == [0, 0, 1, 1, 2, 2]
    assert list(cols["fragment"]) == [0, 1, 0, 1, 0, 1]
    assert list(cols["block_size_m"]) == [0.8] * 6
    assert cols["status"] == ["stopped"] * 5 + ["budget"]
    crsp_help = " ".join(crsp_parser().format_help().split())
    dem_help = " ".join(dem_parser().format_help().split())
    for text in (crsp_help, dem_help):
        assert all(f" {name}: " in text for name in RUN_COLUMNS)
    assert "energy_kJ_<x>m: kinetic energy (translation and rotation), kJ per block" in crsp_help
    assert "energy_kJ_per_m_<x>m: kinetic energy (translation and rotation), kJ per metre" \
        in dem_help
