"""What every output says about how it was made: the command line, the seed, the
SHA-256 of each input file and the versions of the packages that computed it,
so that a colleague can tell which run a file came from and repeat it."""

from __future__ import annotations

import hashlib
import importlib.metadata as md
import platform
import shlex
import sys

__all__ = ["PACKAGES", "file_sha256", "provenance", "versions"]

PACKAGES = ("rockfall-calib", "jax", "jaxlib", "numpy", "scipy", "optax", "numpyro", "pandas",
            "matplotlib", "scoringrules")


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


def provenance(prog: str, seed: int | None, inputs: dict[str, str | None],
               argv: list[str] | None = None) -> dict:
    """The provenance record of one run.

    Args:
        prog: the command, e.g. "python -m calib.validate".
        seed: the run's seed (None where it has none).
        inputs: role -> path of each input file (None: not used).
        argv: the command's arguments that repeat the run (None: this
            process's, ``sys.argv[1:]``; a command run inside another one,
            e.g. ``calib.fit``'s held-out check, passes its own).

    Returns:
        {"command", "seed", "inputs": {role: {"path", "sha256"}}, "versions"};
        the command is ``prog`` followed by the arguments quoted for a POSIX
        shell (``shlex.join``).
    """
    args = sys.argv[1:] if argv is None else argv
    return {"command": " ".join([prog, shlex.join(args)]) if args else prog, "seed": seed,
            "inputs": {role: None if p is None else {"path": p, "sha256": file_sha256(p)}
                       for role, p in inputs.items()},
            "versions": versions()}
