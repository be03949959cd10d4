"""The command-line kit every ``python -m`` command of the project uses.

One-line errors with exit code 2 (``CliError``, ``OneLineParser``,
``run_guarded``), option parsing, progress bars on stderr
(``Progress``), atomic writes of all of a command's outputs
(``write_all_atomic``, ``write_outputs``), JSON-ready values (``json_ready``),
and the station columns both solvers write (``station_columns``). No physics
here. Commands
import these names from this module, never another command's private helpers.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import tempfile
import time

import numpy as np

__all__ = [
    "CliError",
    "DefaultsHelpFormatter",
    "OneLineParser",
    "Progress",
    "fail",
    "json_ready",
    "parse_floats",
    "parse_stations",
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
                   name: str = "--stations") -> list[float]:
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
    """
    todo = {os.path.join(out, name): text_writer(text) for name, text in files.items()}
    todo.update({os.path.join(out, name): functools.partial(fig.savefig, dpi=120)
                 for name, fig in (figs or {}).items()})
    todo.update({os.path.join(out, name): w for name, w in (writers or {}).items()})
    return write_all_atomic(todo)


def json_ready(v):
    """A copy of ``v`` that ``json.dumps(..., allow_nan=False)`` accepts: NumPy
    scalars become Python ones, non-finite floats None, tuples lists."""
    if isinstance(v, dict):
        return {k: json_ready(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [json_ready(x) for x in v]
    if isinstance(v, (np.bool_, bool)):
        return bool(v)
    if isinstance(v, (np.integer, int)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v) if np.isfinite(v) else None
    return v


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
