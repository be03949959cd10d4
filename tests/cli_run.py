"""Helpers shared by the tests: run a command's ``main`` in-process, a module
in a fresh process, or load a study script of ``scripts/`` (not a test
module: pytest does not collect it; tests import them as ``from cli_run
import run_cli``, as they do ``test_hazard_fixtures``)."""

from __future__ import annotations

import importlib.util
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


def load_script(name: str):
    """The study script ``scripts/<name>.py`` as a module (the scripts are not a
    package: loaded from their file, relative to the repository root)."""
    spec = importlib.util.spec_from_file_location(name, f"scripts/{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
