"""Independent compiled computations run side by side, results in order.

One XLA:CPU computation of the vmapped event loop runs on one core: the lanes
are short vectors and the loop body is a chain of small fused kernels, so the
CPU backend does not split it across threads. Two Python threads that each run
one chunk do run in parallel (JAX releases the GIL while a computation
executes): on a 2-core machine that doubles the blocks per second of a
station-free CRSP run. Async dispatch from ONE thread does not: on one CPU
device the computations then run one after the other.

``map_ordered`` is the one place that does this: it calls ``fn(item)`` for
every item on ``workers`` threads, keeps at most ``workers + 1`` items in
flight (each holds its output on the host), and hands the results to the
caller in item order. Results are therefore the same, bit for bit, for any
number of workers: every item is computed by the same program and nothing is
reduced across items here.

On an accelerator one worker per device is enough (the device queues the
work); ``default_workers`` returns the number of CPU cores this process may use
on the CPU backend and the number of devices elsewhere.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import jax

__all__ = ["default_workers", "map_ordered"]

T = TypeVar("T")


def default_workers() -> int:
    """Threads that keep this machine busy: usable CPU cores on the CPU
    backend, else the number of devices (at least 1)."""
    if jax.default_backend() == "cpu":
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except AttributeError:  # not on Linux
            return max(1, os.cpu_count() or 1)
    return max(1, jax.device_count())


def map_ordered(fn: Callable[[Any], T], items: Iterable[Any],
                workers: int | None = None) -> Iterator[T]:
    """``fn(item)`` for every item, computed on ``workers`` threads, yielded in
    item order.

    Args:
        fn: the work of one item; it should return host (NumPy) arrays, so that
            the computation has finished when it returns (``jax.device_get``).
        items: the items, consumed lazily (at most ``workers + 1`` ahead of the
            result being yielded).
        workers: threads (default ``default_workers()``); 1 runs everything in
            the calling thread.

    Yields:
        ``fn(item)`` in the order of ``items``. An exception raised by ``fn``
        is raised here, at its item's turn; items not started yet are dropped.
    """
    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if n == 1:
        for item in items:
            yield fn(item)
        return
    pending: deque = deque()
    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="solvers") as pool:
        try:
            for item in items:
                pending.append(pool.submit(fn, item))
                if len(pending) > n:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()
