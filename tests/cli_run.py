"""Helper shared by the tests: run a command's ``main`` in-process (not a test
module: pytest does not collect it; tests import it as ``from cli_run import
run_cli``, as they do ``test_hazard_fixtures``)."""

from __future__ import annotations


def run_cli(main, argv, capsys) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``main(argv)``; argparse's exits count."""
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err
