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
