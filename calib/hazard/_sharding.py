"""Spreading work units over every JAX device and every CPU core.

Units are independent (each has its own random keys, see ``_units``), so the
run is data-parallel over units: unit i is committed to device i mod D with
``jax.device_put`` and computed on one of ``solvers.parallel``'s worker
threads (one per CPU core on the CPU backend, where one computation of the
event loop keeps one core busy; one per device elsewhere). Results are handed
to ``on_result`` in unit order, so the tables are the same for any number of
devices and workers, bit for bit: every unit computes the same integers
wherever it runs, and they are added up in the same order.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import jax

from solvers.parallel import default_workers, map_ordered

__all__ = ["run_units"]


def run_units(units: Iterable[tuple[Any, Callable[[], tuple], Callable]],
              on_result: Callable[[Any, Any], None], devices=None,
              workers: int | None = None) -> None:
    """Run work units over ``devices`` (default: all of ``jax.devices()``).

    Args:
        units: iterable of ``(tag, make_args, fn)``: ``make_args()`` returns the
            positional arguments (a tuple of pytrees) and ``fn(*args)`` the
            (jitted) computation of the unit.
        on_result: called as ``on_result(tag, result)`` with the result fetched
            to host NumPy arrays, in unit order.
        devices: devices to use.
        workers: threads computing units side by side (default: at least one
            per device, ``solvers.parallel.default_workers()`` on the CPU).
    """
    devices = list(jax.devices() if devices is None else devices)
    n = workers or max(len(devices), default_workers())

    def compute(item):
        i, (tag, make_args, fn) = item
        args = jax.device_put(make_args(), devices[i % len(devices)])
        return tag, jax.device_get(fn(*args))

    for tag, result in map_ordered(compute, enumerate(units), n):
        on_result(tag, result)
