"""The command-line kit every ``python -m`` command of the project uses.

One-line errors with exit code 2 (``CliError``, ``OneLineParser``,
``run_guarded``), option parsing, deprecated option names kept for one release
(``deprecated_alias``), progress bars on stderr (``Progress``), atomic writes
of all of a command's outputs (``write_all_atomic``, ``write_outputs``),
JSON-ready values (``json_ready``), and the one schema of both solvers' output
CSVs (``RUN_COLUMNS``, ``run_columns``, ``station_columns``, described for
``--help`` by ``run_columns_help``). No physics here. Commands import these
names from this module, never another command's private helpers.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import tempfile
import time

import numpy as np

from solvers.jsonable import json_ready  # noqa: F401  (the commands' JSON kit)

__all__ = [
    "CliError",
    "DefaultsHelpFormatter",
    "OneLineParser",
    "Progress",
    "RUN_COLUMNS",
    "deprecated_alias",
    "fail",
    "json_ready",
    "parse_floats",
    "parse_stations",
    "run_columns",
    "run_columns_help",
    "run_guarded",
    "station_column_names",
    "station_columns",
    "text_writer",
    "write_all_atomic",
    "write_csv_atomic",
    "write_outputs",
    "write_text_atomic",
]


class CliError(Exception):
    """A user error to report as one line on stderr, exit status 2."""


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports bad arguments as a single line and exits 2."""

    def error(self, message: str):  # noqa: D401 - argparse API
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(2)


def _no_default(value) -> bool:
    """None, an off switch or argparse.SUPPRESS: nothing for --help to show (by
    identity: a default of 0 == False is a value to show)."""
    return value is None or value is False or value is argparse.SUPPRESS


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` that ends each option's text with ``(default: X)``, except where
    the text already names its default or there is none to show (None, an off
    switch): say what None means in the text, e.g. "(default: first vertex)"."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (not action.option_strings or _no_default(action.default)
                or "default" in text.lower()):
            return text
        return text + " (default: %(default)s)"


class _DeprecatedAlias(argparse.Action):
    """Store an old option's value where its new option stores (``deprecated_alias``)."""

    def __init__(self, option_strings, dest, new: str = "", convert=None, **kw):
        super().__init__(option_strings, dest, **kw)
        self.new, self.convert = new, convert

    def __call__(self, parser, namespace, values, option_string=None):
        value = values if self.convert is None else self.convert(values)
        shown = f"{value:g}" if isinstance(value, float) else str(value)
        sys.stderr.write(f"{parser.prog}: warning: {option_string} is deprecated and goes in "
                         f"the next release; read as {self.new} {shown}\n")
        setattr(namespace, self.dest, value)


def deprecated_alias(parser: argparse.ArgumentParser, old: str, new: str, convert=None,
                     note: str = "") -> None:
    """Accept option ``old`` for one release as a deprecated name of option ``new``.

    The old option parses its value as ``new`` does (same type and choices),
    passes it through ``convert`` if given (e.g. a radius r to the diameter
    d = 2 r), stores it where ``new`` stores, and prints one warning line on
    stderr naming ``new`` and the value it reads. Its ``--help`` line says it
    is deprecated. Given both, the one typed last wins (argparse's rule for a
    repeated option).

    Args:
        parser: the command's parser, ``new`` already added.
        old, new: option strings, e.g. ``"--radius-m"``, ``"--block-size-m"``.
        convert: value of ``old`` -> value of ``new``; None: the same value.
        note: said after "deprecated name of NEW" in ``--help``, e.g. "; d = 2 r".
    """
    target = parser._option_string_actions[new]
    parser.add_argument(old, action=_DeprecatedAlias, new=new, convert=convert,
                        dest=target.dest, type=target.type, choices=target.choices,
                        metavar=old.lstrip("-").replace("-", "_").upper(),
                        default=argparse.SUPPRESS,
                        help=f"deprecated name of {new}{note}; goes in the next release")


def fail(prog: str, message: str) -> None:
    """Print ``prog: error: message`` on one line and exit 2."""
    sys.stderr.write(f"{prog}: error: {' '.join(str(message).split())}\n")
    raise SystemExit(2)


def run_guarded(prog: str, fn, *args) -> int:
    """``fn(*args)``, turning a ``CliError`` or Ctrl-C into one line and exit 2."""
    try:
        return fn(*args)
    except CliError as e:
        fail(prog, str(e))
    except KeyboardInterrupt:
        fail(prog, "interrupted; nothing written")
    return 0


class Progress:
    """A progress callback ``(stage, done, total)`` that shows one tqdm bar per
    stage on stderr, labelled ``"<label>: <stage>"``; does nothing when not
    ``enabled`` (a command's ``--no-progress``)."""

    def __init__(self, enabled: bool, label: str):
        self.enabled, self.label, self.bar, self.stage = enabled, label, None, None
        self.t0 = time.perf_counter()

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self.enabled:
            return
        from tqdm import tqdm

        if stage != self.stage:
            if self.bar is not None:
                self.bar.close()
            self.stage = stage
            self.bar = tqdm(total=total, desc=f"{self.label}: {stage}", file=sys.stderr,
                            leave=False)
        self.bar.n = done
        self.bar.refresh()

    def close(self):
        if self.bar is not None:
            self.bar.close()


def parse_floats(text: str, name: str) -> list[float]:
    """Parse ``"0.1,0.5"`` into floats, naming the option on failure."""
    out = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            v = float(part)
        except ValueError:
            raise CliError(f"{name}: expected comma-separated numbers, got {part!r}") from None
        if not np.isfinite(v):
            raise CliError(f"{name}: expected finite numbers, got {part!r}")
        out.append(v)
    if not out:
        raise CliError(f"{name}: expected at least one number")
    return out


def parse_stations(text: str | None, x_range_m: tuple[float, float],
                   name: str = "--stations-m") -> list[float]:
    """Stations as ``"110,230"`` or a range ``"start:stop:step"`` (stop included);
    errors name the option ``name``.

    Raises:
        CliError: on malformed text or stations outside the profile.
    """
    if not text:
        return []
    if ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise CliError(f"{name}: expected start:stop:step, got {text!r}")
        start, stop, step = parse_floats(",".join(parts), name)
        if step <= 0 or stop < start:
            raise CliError(f"{name}: need step > 0 and stop >= start, got {text!r}")
        n = int(np.floor((stop - start) / step + 1e-9)) + 1
        stations = [start + i * step for i in range(n)]
    else:
        stations = parse_floats(text, name)
    lo, hi = x_range_m
    bad = [s for s in stations if not (lo <= s <= hi)]
    if bad:
        raise CliError(f"{name}: station(s) {', '.join(f'{b:g}' for b in bad)} m lie outside "
                       f"the profile x range [{lo:g}, {hi:g}] m")
    return stations


def write_all_atomic(writers: dict) -> list[str]:
    """Write several outputs so that a crash leaves none of them half-written.

    ``writers`` maps each final path to a callable ``write(tmp_path)``. Every
    output is first written to a temporary file beside its final path (same
    extension, so e.g. matplotlib picks the format), and only when all have
    been written are they renamed into place; on any error the temporaries
    are removed and nothing is renamed. Returns the final paths.

    Each output gets the permissions of a file the user creates (0666 less the
    umask), not the 0600 that ``tempfile.mkstemp`` gives its temporaries.
    """
    umask = os.umask(0)
    os.umask(umask)
    staged = []
    try:
        for final, write in writers.items():
            directory = os.path.dirname(os.path.abspath(final))
            os.makedirs(directory, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(final)[1],
                                       dir=directory)
            os.close(fd)
            staged.append((tmp, final))
            write(tmp)
            os.chmod(tmp, 0o666 & ~umask)
        for tmp, final in staged:
            os.replace(tmp, final)
    finally:
        for tmp, _ in staged:
            if os.path.exists(tmp):
                os.unlink(tmp)
    return [final for _, final in staged]


def write_outputs(out: str, files: dict, figs: dict | None = None,
                  writers: dict | None = None) -> list[str]:
    """Write a command's outputs into folder ``out`` atomically (``write_all_atomic``).

    Args:
        out: output folder (created if needed).
        files: file name -> text.
        figs: file name -> matplotlib figure (saved at 120 dpi, format from the name).
        writers: file name -> ``write(path)`` callable.

    Returns:
        The final paths.

    The figures are closed afterwards, written or not: a command run in-process
    (tests, notebooks) must not keep every figure it drew open.
    """
    todo = {os.path.join(out, name): text_writer(text) for name, text in files.items()}
    todo.update({os.path.join(out, name): functools.partial(fig.savefig, dpi=120)
                 for name, fig in (figs or {}).items()})
    todo.update({os.path.join(out, name): w for name, w in (writers or {}).items()})
    try:
        return write_all_atomic(todo)
    finally:
        if figs:
            import matplotlib.pyplot as plt

            for fig in figs.values():
                plt.close(fig)


def text_writer(text: str):
    """A ``write(path)`` callable for ``write_all_atomic`` that writes ``text``."""
    def write(path):
        with open(path, "w", newline="") as fh:
            fh.write(text)
    return write


def write_text_atomic(path: str, text: str) -> None:
    """Write ``text`` to ``path`` atomically (``write_all_atomic``)."""
    write_all_atomic({path: text_writer(text)})


def write_csv_atomic(df, path: str) -> None:
    """Write a pandas DataFrame to ``path`` atomically (``write_text_atomic``)."""
    write_text_atomic(path, df.to_csv(index=False))


def station_column_names(x_m: float, energy_per_m: bool = False) -> dict[str, str]:
    """The CSV column of each station quantity at station ``x_m`` (m), the same
    in ``python -m solvers.crsp`` and ``python -m solvers.dem``.

    ``passed_<x>m``, ``energy_kJ_<x>m`` (``energy_kJ_per_m_<x>m`` where the energy
    is per metre of block width, the 2D DEM), ``velocity_m_s_<x>m``,
    ``bounce_height_m_<x>m``; ``<x>`` is ``f"{x_m:g}"``.

    Returns:
        ``StationRecord`` field name -> column name.
    """
    tag = f"{x_m:g}m"
    return {"passed": f"passed_{tag}",
            "energy_kJ": f"energy_kJ_per_m_{tag}" if energy_per_m else f"energy_kJ_{tag}",
            "velocity_m_s": f"velocity_m_s_{tag}",
            "bounce_height_m": f"bounce_height_m_{tag}"}


def station_columns(stations_x_m, record, energy_per_m: bool = False) -> dict:
    """Station columns of a solver's output CSV (``station_column_names``).

    Args:
        stations_x_m: (S,) station abscissae, m.
        record: a ``solvers.stations.StationRecord`` whose fields have shape
            (..., S); the leading axes are flattened in C order to one row per
            block (per fragment for the DEM).
        energy_per_m: the energies are kJ per metre of block width (2D DEM).

    Returns:
        column name -> (n_rows,) array, station by station.
    """
    cols = {}
    for j, x in enumerate(stations_x_m):
        for field, name in station_column_names(x, energy_per_m).items():
            v = np.asarray(getattr(record, field))
            cols[name] = v.reshape(-1, v.shape[-1])[:, j]
    return cols


# The one schema of the solvers' output CSVs (python -m solvers.crsp --out,
# python -m solvers.dem --out): these columns first, in this order, then the
# solver's own counts, then the station columns (station_column_names).
RUN_COLUMNS = {
    "block": "block index i, 0 to N-1; its random key is fold_in(key(seed), i)",
    "fragment": "fragment index in the block, 0 to F-1 (CRSP: 0, a block is one piece; DEM: "
                "the n x n fragments of --fragments)",
    "block_size_m": "block size d, the diameter, m (CRSP sphere radius r = d/2; DEM square "
                    "side L = d)",
    "status": "how the row's run ended: stopped, left_profile, budget (still moving when "
              "its budget ran out) or invalid (solvers.status); a DEM fragment that passed "
              "the profile's end is left_profile, its resting siblings stopped",
    "runout_m": "horizontal distance from the release abscissa to stop_x_m, m (a runout only "
                "where status is stopped or left_profile)",
    "stop_x_m": "abscissa where the row's run ended, m",
    "stop_z_m": "height there, m",
}


def run_columns(block_size_m: float, status, runout_m, stop_x_m, stop_z_m,
                n_fragments: int = 1) -> dict:
    """The ``RUN_COLUMNS`` of a solver's output CSV, one row per fragment.

    Args:
        block_size_m: the blocks' size d (the diameter), m.
        status: (N F,) ``solvers.status`` codes of each row, blocks in order and,
            within a block, its fragments in order.
        runout_m, stop_x_m, stop_z_m: (N F,) m, same order.
        n_fragments: F, fragments per block (1 for CRSP).

    Returns:
        column name -> (N F,) values, in ``RUN_COLUMNS`` order.
    """
    from solvers.status import STATUS_NAMES

    codes = np.asarray(status).ravel()
    n_blocks = codes.size // n_fragments
    return {
        "block": np.repeat(np.arange(n_blocks), n_fragments),
        "fragment": np.tile(np.arange(n_fragments), n_blocks),
        "block_size_m": np.full(codes.size, float(block_size_m)),
        "status": [STATUS_NAMES.get(int(c), str(c)) for c in codes],
        "runout_m": np.asarray(runout_m).ravel(),
        "stop_x_m": np.asarray(stop_x_m).ravel(),
        "stop_z_m": np.asarray(stop_z_m).ravel(),
    }


def run_columns_help(own: dict[str, str], energy_per_m: bool = False) -> str:
    """The output CSV's columns as ``--help`` text: ``RUN_COLUMNS``, then the
    solver's ``own`` columns (name -> meaning), then the station columns."""
    import textwrap

    energy = ("energy_kJ_per_m_<x>m: kinetic energy (translation and rotation), kJ per "
              "metre of block width (the DEM is 2D)" if energy_per_m else
              "energy_kJ_<x>m: kinetic energy (translation and rotation), kJ per block")
    rows = [*RUN_COLUMNS.items(), *own.items(),
            ("per station x (--stations-m)",
             f"passed_<x>m: crossed x moving downslope; at that first passage, {energy}, "
             "velocity_m_s_<x>m: speed, m/s, bounce_height_m_<x>m: "
             "clearance of the block's lowest point above the ground, m (empty where not "
             "passed; solvers.stations)")]
    lines = textwrap.wrap("Output CSV (--out), one row per fragment of each block, the same "
                          "schema for python -m solvers.crsp and python -m solvers.dem "
                          "(solvers.cli.RUN_COLUMNS):", 80)
    for name, what in rows:
        lines += textwrap.wrap(f"{name}: {what}", 78, initial_indent="  ",
                               subsequent_indent="      ")
    return "\n".join(lines)
