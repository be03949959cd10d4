"""The command-line kit (``solvers.cli``) and what every command owes its user.

* Commands share plumbing through the public kit, never through another
  module's private names (an AST scan of ``calib/``, ``solvers/`` and ``terrain/``).
* The packages import one way: ``calib`` -> ``terrain`` -> ``solvers``.
* Both solvers name the quantities they share alike.
* ``--help`` of every command shows every default.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("calib", "solvers", "terrain")

# Private names still imported across modules (none left; an entry must name the
# change that removes it).
KNOWN: set[tuple[str, str, str]] = set()


def _modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            is_pkg = parts[-1] == "__init__"
            name = ".".join(parts[:-1] if is_pkg else parts)
            yield path, name, is_pkg


def _imports(path, name, is_pkg):
    """(line, imported module, imported name or None) of every import in the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    here = name.split(".") if is_pkg else name.split(".")[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name, None
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[:len(here) - (node.level - 1)]
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module or ""
            for a in node.names:
                yield node.lineno, src, a.name


def _private(part: str) -> bool:
    return part.startswith("_") and not part.startswith("__")


def cross_module_private_imports() -> list[str]:
    """``file:line: from X import _name`` (X another module) and imports of a private
    module (``solvers.cli``) from outside the package that holds it."""
    bad = []
    for path, name, is_pkg in _modules():
        rel = path.relative_to(ROOT)
        for line, src, what in _imports(path, name, is_pkg):
            if src.split(".")[0] not in PACKAGES:
                continue
            if what is not None and _private(what) and src != name:
                if (name, src, what) not in KNOWN:
                    bad.append(f"{rel}:{line}: from {src} import {what}")
            parts = src.split(".")
            for i, part in enumerate(parts):
                owner = ".".join(parts[:i])  # the package the private module belongs to
                if _private(part) and not (name == owner or name.startswith(owner + ".")):
                    bad.append(f"{rel}:{line}: imports private module {src}")
                    break
    return list(dict.fromkeys(bad))


def _is_command(name: str) -> bool:
    """A command module (or a benchmark run as one): calib/<x>.py, any
    ``__main__``, ``bench``/``_bench`` and the terrain cut."""
    parts = name.split(".")
    return ((parts[0] == "calib" and len(parts) == 2) or parts[-1] in
            ("__main__", "bench", "_bench") or name in ("solvers.cli", "terrain.cut"))


def library_imports_of_the_cli_kit() -> list[str]:
    """``file:line`` of library modules that import ``solvers.cli``."""
    bad = []
    for path, name, is_pkg in _modules():
        if is_pkg or _is_command(name):
            continue
        for line, src, what in _imports(path, name, is_pkg):
            if src == "solvers.cli" or (src == "solvers" and what == "cli"):
                bad.append(f"{path.relative_to(ROOT)}:{line}: imports solvers.cli")
    return list(dict.fromkeys(bad))


def test_library_code_does_not_import_the_cli_kit():
    """The kit is for commands; library code raises its own errors and reads its
    CSVs through ``solvers.csv_rows`` (before: calib/files/inputs.py raised
    CliError, raster, profile and field_runs read CSVs through the kit, the
    hazard tables and the fit's check took the few-blocks rule from it)."""
    bad = library_imports_of_the_cli_kit()
    assert not bad, "\n".join(bad)


def test_no_private_name_is_imported_across_modules():
    bad = cross_module_private_imports()
    assert not bad, "import these from the public kit (solvers.cli) or make them public:\n" \
        + "\n".join(bad)


def test_the_known_exceptions_are_still_there():
    """An entry of KNOWN that no longer occurs must leave the list (it would hide a
    regression)."""
    seen = {(name, src, what) for path, name, is_pkg in _modules()
            for _, src, what in _imports(path, name, is_pkg)}
    assert not KNOWN - seen, f"remove from KNOWN: {sorted(KNOWN - seen)}"


# Imports that go against the layering: none but the deprecated command name
# ``python -m solvers.profile cut``, which runs ``terrain.cut`` (removed with it).
LAYERING_EXCEPTIONS = {("solvers.profile", "terrain.cut")}


def layering_violations() -> list[tuple[str, str]]:
    """(module, imported module) of every import from ``solvers`` into ``terrain``
    or ``calib``, and from ``terrain`` into ``calib``."""
    above = {"solvers": ("terrain", "calib"), "terrain": ("calib",), "calib": ()}
    bad = []
    for path, name, is_pkg in _modules():
        for _, src, what in _imports(path, name, is_pkg):
            top = src.split(".")[0]
            full = src if what is None or top != src else f"{src}.{what}"
            if top in above[name.split(".")[0]]:
                bad.append((name, full))
    return list(dict.fromkeys(bad))


def test_packages_import_one_way():
    """``solvers`` (the physics and the profile) imports neither ``terrain`` nor
    ``calib``; ``terrain`` (rasters, lines in plan, the cut) does not import
    ``calib``."""
    bad = set(layering_violations())
    assert bad == LAYERING_EXCEPTIONS, sorted(bad ^ LAYERING_EXCEPTIONS)


# ---------------------------------------------------------------- solver outputs

def test_both_solvers_name_shared_station_quantities_alike():
    """python -m solvers.crsp and python -m solvers.dem build their station columns
    with station_columns: the same names for passage, speed and bounce height; the
    2D DEM's energy (kJ per metre of block width) is named so, the CRSP's (kJ per
    block) is not."""
    import numpy as np

    from solvers.cli import station_column_names, station_columns
    from solvers.stations import StationRecord

    crsp, dem = station_column_names(110.0), station_column_names(110.0, energy_per_m=True)
    for field in ("passed", "velocity_m_s", "bounce_height_m"):
        assert crsp[field] == dem[field]
    assert crsp == {"passed": "passed_110m", "energy_kJ": "energy_kJ_110m",
                    "velocity_m_s": "velocity_m_s_110m",
                    "bounce_height_m": "bounce_height_m_110m"}
    assert dem["energy_kJ"] == "energy_kJ_per_m_110m"
    assert station_column_names(2.5)["passed"] == "passed_2.5m"
    # (blocks, fragments, stations) records flatten to one row per fragment
    v = np.arange(12.0).reshape(3, 2, 2)
    cols = station_columns([10.0, 20.0], StationRecord(v > 4, v, v, v), energy_per_m=True)
    assert list(cols)[:4] == list(station_column_names(10.0, energy_per_m=True).values())
    np.testing.assert_array_equal(cols["energy_kJ_per_m_20m"], v[..., 1].ravel())


# ---------------------------------------------------------------- --help shows defaults

COMMANDS = ["solvers.crsp.__main__", "solvers.dem.__main__", "terrain.cut", "solvers.bench",
            "calib.fit", "calib.discover", "calib.power", "calib.synth", "calib.validate",
            "calib.field", "calib.hazard.__main__"]


def _parsers(module):
    """The command's parser and its sub-commands' parsers."""
    import argparse
    import importlib

    parser = importlib.import_module(module).build_parser()
    out = [parser]
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            out += list(a.choices.values())
    return out


@pytest.mark.parametrize("module", COMMANDS)
def test_every_option_with_a_default_says_it(module):
    """An option whose default is a value (not None, not an off switch) names that
    default in its help, by hand or through ArgumentDefaultsHelpFormatter."""
    import argparse

    missing = []
    for parser in _parsers(module):
        auto = issubclass(parser.formatter_class, argparse.ArgumentDefaultsHelpFormatter)
        for a in parser._actions:
            if not a.option_strings or any(a.default is v for v in (None, False,
                                                                     argparse.SUPPRESS)):
                continue
            if not (auto or "default" in (a.help or "").lower()):
                missing.append(f"{parser.prog} {a.option_strings[0]} (default {a.default!r})")
    assert not missing, "say the default in --help:\n" + "\n".join(missing)


@pytest.mark.parametrize("module, needles", [
    ("solvers.crsp.__main__", ["default 1000", "default 1.0", "default 2350"]),
    ("solvers.dem.__main__", ["default: 256", "default: unbalanced", "default: 200.0",
                              "Default 0.01", "default: 2350"]),
    ("calib.fit", ["default: both", "default 0", "default 1.0 m"]),
    ("calib.hazard.__main__", ["0.2,0.5,1.0,2.0", "default 5000"]),
])
def test_help_shows_defaults(module, needles, capsys):
    import importlib

    with pytest.raises(SystemExit) as exc:
        importlib.import_module(module).main(["--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for needle in needles:
        assert needle in text, (module, needle)


# ---------------------------------------------------------------- percentiles from few blocks

def test_few_blocks_is_the_one_rule_below_20():
    import numpy as np

    from solvers.percentiles import MIN_BLOCKS_FOR_PERCENTILE, few_blocks, few_blocks_warning

    assert MIN_BLOCKS_FOR_PERCENTILE == 20
    assert few_blocks(19) is True and few_blocks(20) is False
    np.testing.assert_array_equal(few_blocks(np.array([0, 1, 19, 20, 10**6])),
                                  [True, True, True, False, False])
    assert few_blocks_warning([("a", 20), ("b", 500)]) is None
    w = few_blocks_warning([("x = 110 m", 7), ("x = 120 m", 25), ("x = 130 m", 1)],
                           what="E p95")
    assert w == ("warning: E p95 rest on fewer than 20 blocks in 2 row(s), treat them as "
                 "rough: x = 110 m (7 blocks); x = 130 m (1 block)")
    many = few_blocks_warning([(f"row {i}", 3) for i in range(12)], max_named=8)
    assert "in 12 row(s)" in many and "row 7 (3 blocks); and 4 more" in many
    assert "row 8 (" not in many


# ---------------------------------------------------------------- deprecated names

def test_a_deprecated_option_name_still_works_and_warns_once(capsys):
    """``deprecated_alias``: the old name parses as the new one does, converted
    (a radius r read as the diameter 2 r), stores where the new one stores, and
    says so in one line on stderr naming the new option; the new option's
    default stands when neither is given, and --help marks the old one."""
    from solvers.cli import OneLineParser, deprecated_alias

    p = OneLineParser(prog="cmd")
    p.add_argument("--block-size-m", type=float, default=1.0, help="diameter, m")
    deprecated_alias(p, "--radius-m", "--block-size-m", convert=lambda r: 2.0 * r)
    assert p.parse_args([]).block_size_m == 1.0
    assert capsys.readouterr().err == ""
    assert p.parse_args(["--radius-m", "0.3"]).block_size_m == 0.6
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("cmd: warning: --radius-m is deprecated")
    assert "--block-size-m 0.6" in err
    assert p.parse_args(["--block-size-m", "0.3"]).block_size_m == 0.3
    assert capsys.readouterr().err == ""
    with pytest.raises(SystemExit):
        p.parse_args(["--radius-m", "x"])  # parsed as the new option is: a float
    assert "--radius-m" in capsys.readouterr().err
    help_text = " ".join(p.format_help().split())
    assert "--radius-m RADIUS_M deprecated name of --block-size-m" in help_text
