"""Helpers shared by the tests: run a command's ``main`` in-process, or a module
in a fresh process (not a test module: pytest does not collect it; tests
import them as ``from cli_run import run_cli``, as they do
``test_hazard_fixtures``)."""

from __future__ import annotations

import subprocess
import sys


def run_cli(main, argv, capsys) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``main(argv)``; argparse's exits count."""
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def run_module(module: str, *args: str, cwd=None, timeout: float = 900
               ) -> subprocess.CompletedProcess:
    """``python -m module *args`` in a fresh process (the command as a user runs
    it: the interpreter's exit status, stdout and stderr as text)."""
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True,
                          text=True, cwd=cwd, timeout=timeout)
