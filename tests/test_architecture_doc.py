"""docs/architecture.md stays true: every module of calib/, solvers/ and terrain/
is named in it, and it names no module that does not exist."""

from __future__ import annotations

import pathlib
import re

DOC = pathlib.Path("docs/architecture.md").read_text()


def _modules():
    for pkg in ("calib", "solvers", "terrain"):
        for p in sorted(pathlib.Path(pkg).rglob("*.py")):
            if p.name != "__init__.py":
                yield p.as_posix()


def test_every_module_is_on_the_map():
    def named(m: str) -> bool:
        # its full path, or its file name listed under its package's folder
        folder, name = m.rsplit("/", 1)
        return m in DOC or (f"`{name}`" in DOC and f"`{folder}/" in DOC)

    missing = [m for m in _modules() if not named(m)]
    assert not missing, f"modules missing from docs/architecture.md: {missing}"


def test_the_map_names_no_missing_module():
    named = set(re.findall(r"`((?:calib|solvers|terrain)/[\w/]+\.py)`", DOC))
    gone = sorted(m for m in named if not pathlib.Path(m).is_file())
    assert not gone, f"docs/architecture.md names modules that do not exist: {gone}"
