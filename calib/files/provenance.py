"""What every output says about how it was made: the command line, the seed, the
SHA-256 of each input file and the versions of the packages that computed it,
so that a colleague can tell which run a file came from and repeat it."""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import importlib.metadata as md
import platform
import shlex
import sys

__all__ = ["PACKAGES", "command_args", "command_line", "command_running", "file_sha256",
           "provenance", "versions"]

PACKAGES = ("rockfall-calib", "jax", "jaxlib", "numpy", "scipy", "optax", "numpyro", "pandas",
            "matplotlib", "scoringrules")


_COMMAND_ARGS: contextvars.ContextVar[list[str] | None] = contextvars.ContextVar(
    "command_args", default=None)


@contextlib.contextmanager
def command_args(argv: list[str] | None):
    """Within it, ``provenance`` records ``argv`` as the command's arguments: a
    command's ``main(argv)`` wraps its run in it, so that a run called with its
    arguments in-process (a notebook, a study script, a test) records those,
    not the arguments of the program it runs inside. ``argv`` None: the
    process's own, ``sys.argv[1:]`` (the command run from a shell)."""
    token = _COMMAND_ARGS.set([str(a) for a in (sys.argv[1:] if argv is None else argv)])
    try:
        yield
    finally:
        _COMMAND_ARGS.reset(token)


def command_running() -> bool:
    """Whether a command's ``main`` encloses this call (``command_args``): False in
    a library call, whose caller's arguments are not the command's."""
    return _COMMAND_ARGS.get() is not None


def versions() -> dict:
    """Python and package versions (None for a package that is not installed)."""
    out = {"python": platform.python_version()}
    for pkg in PACKAGES:
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = None
    return out


def file_sha256(path: str) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def command_line(prog: str, argv: list[str] | None = None) -> str:
    """``prog`` followed by the arguments that repeat the run, quoted for a POSIX
    shell (``shlex.join``): ``argv``, else those of the enclosing
    ``command_args``, else none: outside a command's ``main`` (a library call
    from a notebook, say) the process's arguments are not the run's, and
    ``prog`` is what the caller names it."""
    args = argv if argv is not None else _COMMAND_ARGS.get()
    return " ".join([prog, shlex.join(args)]) if args else prog


def provenance(prog: str, seed: int | None, inputs: dict[str, str | None],
               argv: list[str] | None = None) -> dict:
    """The provenance record of one run.

    Args:
        prog: the command, e.g. "python -m calib.validate".
        seed: the run's seed (None where it has none).
        inputs: role -> path of each input file (None: not used).
        argv: the command's arguments that repeat the run (None: those of the
            enclosing ``command_args``, a command's ``main``; a command run
            inside another one, e.g. ``calib.fit``'s held-out check, passes
            its own).

    Returns:
        {"command", "seed", "inputs": {role: {"path", "sha256"}}, "versions"};
        the command is ``command_line(prog, argv)``.
    """
    return {"command": command_line(prog, argv), "seed": seed,
            "inputs": {role: None if p is None else {"path": p, "sha256": file_sha256(p)}
                       for role, p in inputs.items()},
            "versions": versions()}
