"""Spreading work units over every JAX device.

Units are independent (each has its own random keys, see ``_units``), so the
run is data-parallel over units: unit i is committed to device i mod D with
``jax.device_put`` and dispatched asynchronously; at most ``max_in_flight``
units are outstanding, and results are collected in unit order. The tables are
therefore the same for any number of devices, bit for bit: every unit computes
the same integers on whichever device it runs, and they are added up in the
same order. With host CPU "devices" (XLA_FLAGS=--xla_force_host_platform_device_count=2)
the two devices share the machine's cores.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

import jax

__all__ = ["run_units"]


def run_units(units: Iterable[tuple[Any, Callable[[], tuple], Callable]],
              on_result: Callable[[Any, Any], None], devices=None,
              max_in_flight: int | None = None) -> None:
    """Run work units over ``devices`` (default: all of ``jax.devices()``).

    Args:
        units: iterable of ``(tag, make_args, fn)``: ``make_args()`` returns the
            positional arguments (a tuple of pytrees) and ``fn(*args)`` the
            (jitted) computation of the unit.
        on_result: called as ``on_result(tag, result)`` with the result fetched
            to host NumPy arrays, in unit order.
        devices: devices to use.
        max_in_flight: outstanding units (default 2 per device).
    """
    devices = list(jax.devices() if devices is None else devices)
    limit = max_in_flight or 2 * len(devices)
    pending: deque = deque()

    def collect():
        tag, out = pending.popleft()
        on_result(tag, jax.device_get(out))

    for i, (tag, make_args, fn) in enumerate(units):
        dev = devices[i % len(devices)]
        args = jax.device_put(make_args(), dev)
        pending.append((tag, fn(*args)))
        while len(pending) >= limit:
            collect()
    while pending:
        collect()
