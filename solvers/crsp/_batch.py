"""Batched CRSP runs: vmap over blocks, chunked to bound memory, keyed per block.

Block i of a run with key K always uses ``fold_in(K, i)``, so results do not
depend on the chunk size or on how many blocks run together.

``simulate_batch`` is plain ``vmap(simulate)``: its while_loop runs until the
slowest block of the batch is done (about 3x the mean event count on
Postignano). ``simulate_pooled`` keeps a fixed pool of lanes busy instead: every
``refill_every`` events, lanes whose block has finished write its result and
take the next block, so the cost follows the mean event count.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from solvers._rng import key_words
from solvers.crsp._model import (
    Result,
    init,
    raw_result,
    running,
    segment_table,
    simulate,
    sorted_stations,
    step,
)
from solvers.crsp._params import Block, Params, Settings
from solvers.crsp._stations import empty_values, first_beyond, record, write
from solvers.parallel import default_workers, map_ordered
from solvers.profile import Profile

__all__ = ["block_keys", "chunk_plan", "default_pool", "run_blocks", "simulate_batch",
           "simulate_pooled", "simulate_tasks", "task_slots"]


def default_pool() -> int:
    """Lanes of the CRSP pool when none is given: 256 on a CPU, 4096 on an accelerator.

    On a CPU small pools run fastest (the lanes' state stays in cache and fewer
    lanes idle while the last blocks of a call finish). Measured on 2 cores
    (2026-11-24), ``python -m solvers.bench --no-dem`` with 1 m blocks and 61
    stations: 102,000 blocks/s with 256 lanes, 78,000-80,000 with 512-1024 and
    63,000-72,000 with 2048 (medians of 3-4 runs, 10 % noise between runs); the
    default hazard run took 90 s with 256 lanes and 103 s with 1024, with
    identical tables; the calibration forward model ran its 96-task calls as
    fast with 128 as with 256. Re-measured after station passages moved out of
    the step (2026-11-25, one call each, median of 7 runs, 1 m blocks):
    without stations 135,000 / 148,000 / 124,000 / 131,000 blocks/s with
    128 / 256 / 512 / 1024 lanes, with 61 stations 106,000 / 105,000 / 109,000
    / 98,000 (runs within a call ranged over +-20 %): 256 stays the default.
    Accelerators want wide pools to fill their cores.
    Results never depend on the pool (``simulate_pooled``).
    """
    return 256 if jax.default_backend() == "cpu" else 4096


def block_keys(key: jax.Array, start, count: int) -> jax.Array:
    """Keys of blocks ``start .. start + count - 1`` of a run keyed by ``key``:
    fold_in(key, start + j) (``start`` may be traced, ``count`` static)."""
    idx = (start + jnp.arange(count)).astype(jnp.uint32)
    return jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)


@functools.partial(jax.jit, static_argnames=("settings",))
def simulate_batch(params: Params, block: Block, keys: jax.Array, profile: Profile,
                   stations_x_m: jax.Array, settings: Settings = Settings()) -> Result:
    """``simulate`` vmapped over ``keys`` (shape (N, ...)); jitted entry point."""
    fn = functools.partial(simulate, profile=profile, stations_x_m=stations_x_m,
                           settings=settings)
    return jax.vmap(fn, in_axes=(None, None, 0))(params, block, keys)


def task_slots(n_per_task: int) -> int:
    """Output rows per task that one compiled pool holds for ``n_per_task`` blocks.

    The block count of a call is traced, not compiled in: calls whose counts
    share a slot count (256, then 384, 512, 768, 1024, ...: each at most 1.5x
    the count above 256) share one program. Compiling a pool takes 8-15 s on
    2 CPU cores, so a calibration's stages (design, gradient, checks, each with
    its own block count) and runs of different sizes reuse one program instead
    of compiling one each. The lanes' arithmetic does not depend on the slots,
    so neither do the results (our choice of rounding; the output memory grows
    by at most the same 1.5x).
    """
    if n_per_task <= 0:
        raise ValueError(f"n_per_task must be positive, got {n_per_task}")
    slots = _MIN_SLOTS
    while slots < n_per_task:
        slots = slots * 3 // 2 if slots & (slots - 1) == 0 else slots * 4 // 3
    return slots


_MIN_SLOTS = 256


def simulate_pooled(params: Params, block: Block, key: jax.Array, profile: Profile,
                    stations_x_m: jax.Array, n_blocks: int, pool: int | None = None,
                    settings: Settings = Settings(), refill_every: int = 8,
                    offset: jax.Array | int = 0) -> Result:
    """Blocks ``offset .. offset + n_blocks - 1`` of the run keyed ``key``, on a
    pool of lanes (``pool``; None: ``default_pool()``).

    Each block i follows exactly the event sequence of ``simulate`` with key
    ``fold_in(key, i)``; only the scheduling differs. Calls whose ``n_blocks``
    share ``task_slots`` share one compiled program.

    Returns:
        ``Result`` with leading dimension ``n_blocks``.
    """
    one = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], (params, block))
    res = simulate_tasks(one[0], one[1], key, profile, stations_x_m, n_blocks, pool=pool,
                         settings=settings, refill_every=refill_every, offset=offset,
                         n_slots=task_slots(n_blocks))
    return _first_blocks(res, n_blocks, one_task=True)


def simulate_tasks(params: Params, block: Block, key: jax.Array, profile: Profile,
                   stations_x_m: jax.Array, n_per_task: int, pool: int | None = None,
                   settings: Settings = Settings(), refill_every: int = 8,
                   offset: jax.Array | int = 0, task_offsets: jax.Array | None = None,
                   n_slots: int | None = None) -> Result:
    """Many (parameter set, block) tasks in one pool, with common random numbers.

    ``params`` and ``block`` carry a leading task axis T (every leaf). Block j of
    every task uses the key ``fold_in(key, j)`` (j = 0 .. n_per_task - 1), so the
    tasks share their random numbers: differences between tasks come from the
    parameters, not from the draws (common random numbers, as calibration by
    finite differences needs). Task t with ``params[t]`` gives exactly what
    ``simulate_pooled(params[t], block[t], key, ..., n_blocks=n_per_task)`` gives.
    ``offset`` (traced) shifts the block indices to ``offset .. offset +
    n_per_task - 1``, so a long run can be computed in chunks with one program.

    ``task_offsets`` ((T,) integers, traced; None: all 0) shifts each task's
    block indices further: block j of task t uses ``fold_in(key, offset +
    task_offsets[t] + j)``. With ``n_per_task = 1`` and ``task_offsets = arange(T)``
    every task is ONE block with its own key, the key block ``offset + t`` of a
    run keyed ``key`` has: a batch of blocks that differ block by block (size,
    release), each as random as in a run of one block set, whatever the chunk
    (``calib.hazard._units.seeded_chunk``).

    ``n_per_task`` is a Python int; the compiled program depends on it only
    through ``task_slots(n_per_task)``. Jit-able (inside a jit it is inlined).
    With ``n_slots`` (a Python int) given, ``n_per_task`` may be traced (at most
    ``n_slots``; one program serves every count) and the result keeps ``n_slots``
    rows per task, the rows from ``n_per_task`` on zero.

    Returns:
        ``Result`` with leading dimensions (T, n_per_task), or (T, n_slots) when
        ``n_slots`` is given.
    """
    slots = task_slots(n_per_task) if n_slots is None else n_slots
    res = _tasks_in_slots(params, block, key, profile, stations_x_m,
                          jnp.asarray(n_per_task, jnp.int32), offset, task_offsets,
                          n_slots=slots, pool=pool, settings=settings,
                          refill_every=refill_every)
    return res if n_slots is not None else _first_blocks(res, n_per_task)


@functools.partial(jax.jit, static_argnames=("n_slots", "pool", "settings", "refill_every"))
def _tasks_in_slots(params, block, key, profile, stations_x_m, n_per_task, offset,
                    task_offsets, *, n_slots, pool, settings, refill_every):
    """``_pooled`` compiled for ``n_slots`` rows per task, ``n_per_task`` traced."""
    return _pooled(params, block, key, profile, stations_x_m, n_per_task, n_slots, pool,
                   settings, refill_every, offset, task_offsets)


@functools.partial(jax.jit, static_argnames=("n", "one_task"))
def _first_blocks(res, n, one_task=False):
    """The first ``n`` rows of every task of a pool's (T, n_slots, ...) result
    (``one_task``: of its only task, without the task axis), in one program."""
    return jax.tree_util.tree_map(lambda a: a[0, :n] if one_task else a[:, :n], res)


def _pooled(params, block, key, profile, stations_x_m, n_per_task, n_slots, pool, settings,
            refill_every, offset, task_offsets=None):
    """Pool of lanes over T tasks x ``n_per_task`` blocks (traced, not jitted).

    Work item i is block ``j = i % n_per_task`` of task ``t = i // n_per_task``
    (key index ``offset + task_offsets[t] + j``); every ``refill_every`` events the
    lanes whose block finished write its result and take the next item, so the
    cost follows the mean event count. Item i's result goes to row ``t *
    n_slots + j`` of the output (``n_slots >= n_per_task`` static, ``n_per_task``
    may be traced); rows no item fills stay zero.

    Returns:
        ``Result`` with leading dimensions (T, n_slots).
    """
    n_tasks = jax.tree_util.tree_leaves(params)[0].shape[0]
    n_items = n_tasks * n_per_task
    n_rows = n_tasks * n_slots
    # at most one lane per output row: calls whose block counts share their slots
    # then share the program whatever pool they ask for above that (a lane beyond
    # the last block idles; each lane's arithmetic is its own)
    pool = min(default_pool() if pool is None else pool, n_rows)
    stations_x_m, stations_z_m, order = sorted_stations(profile, stations_x_m)
    params, block, tables = _padded_tasks(params, block, profile, n_tasks)
    lane_init, lane_step = _lanes(params, block, tables, key, profile, settings, n_per_task,
                                  offset, task_offsets)
    finalize = functools.partial(_finalize, stations_x_m)

    lane = jnp.arange(pool)
    states, words = jax.vmap(lane_init)(jnp.minimum(lane, n_items - 1))
    x0 = states.x_m
    active = lane < n_items
    reached = first_beyond(stations_x_m, x0)  # stations passed so far, per lane
    proto = jax.eval_shape(finalize, jax.tree_util.tree_map(lambda a: a[0], states), x0[0],
                           reached[0])
    out = jax.tree_util.tree_map(lambda a: jnp.zeros((n_rows,) + a.shape, a.dtype), proto)
    # station passages go from the events' buffer straight into the output (one
    # (n_rows, n_stations) array per quantity), never through the lanes' state
    values = empty_values((n_rows, stations_x_m.shape[0]))
    proto_passage = jax.eval_shape(lambda s, w, t: lane_step(s, w, t)[1],
                                   jax.tree_util.tree_map(lambda a: a[0], states), words[0],
                                   jnp.int32(0))
    body = _pool_body(lane_init, lane_step, finalize, proto_passage, stations_x_m,
                      stations_z_m, order, n_per_task, n_slots, n_items, n_rows, pool,
                      refill_every, settings)

    def cond(carry):
        return jnp.any(carry[4])

    carry = (states, words, x0, jnp.minimum(lane, n_items - 1), active,
             jnp.asarray(pool), out, values, reached)
    _, _, _, _, _, _, (res, first, last), values, _ = jax.lax.while_loop(cond, body, carry)
    out = res._replace(stations=record(first, last, values, order))
    return jax.tree_util.tree_map(
        lambda a: a.reshape((n_tasks, n_slots) + a.shape[1:]), out)


def _padded_tasks(params, block, profile, n_tasks):
    """The task axis padded to the lane quantum, and each task's segment table.

    The padding (copies of the last task) is never simulated: XLA:CPU compiles a
    call with one task differently from one with several (and a vector loop
    differently from its scalar tail), which rounds the runouts differently
    (1.7e-13 m); a task's blocks must not depend on how many tasks share the call.

    Returns:
        (params, block, tables), each leaf with a leading axis of
        ``n_tasks`` rounded up to a multiple of ``_LANE_QUANTUM``.
    """
    pad = (-n_tasks) % _LANE_QUANTUM

    def padded(tree):
        return jax.tree_util.tree_map(
            lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), tree)

    params, block = padded(params), padded(block)
    tables = jax.vmap(segment_table, in_axes=(None, 0, 0))(profile, params, block)
    return params, block, tables


def _lanes(params, block, tables, key, profile, settings, n_per_task, offset, task_offsets):
    """A lane's start and event step for work item i (see ``_pooled``).

    Returns:
        (lane_init, lane_step): ``lane_init(i)`` gives item i's initial state and
        the key words of its events (release key and event key split from
        ``fold_in(key, offset [+ task_offsets[t]] + j)``); ``lane_step(s, words,
        t)`` is one event of task t (a finished lane is left unchanged by
        ``step`` and passes nothing).
    """

    def task_of(t):
        return jax.tree_util.tree_map(lambda a: a[t], (params, block, tables))

    def lane_init(i):
        t, j = i // n_per_task, i % n_per_task
        p, b, _ = task_of(t)
        gi = j + offset if task_offsets is None else j + offset + task_offsets[t]
        gi = gi.astype(jnp.uint32)
        release_key, event_key = jax.random.split(jax.random.fold_in(key, gi))
        s = init(p, b, release_key, profile, settings)
        return s, key_words(event_key)

    def lane_step(s, words, t):
        p, b, table = task_of(t)
        return step(s, p, b, words, profile, table, settings)

    return lane_init, lane_step


def _finalize(stations_x_m, s, x0, reached):
    """A finished lane's result: the run's outcome (``raw_result``) and the
    station indices that ``record`` turns into its station records: the first
    station beyond its release and the stations it reached (``first_beyond``)."""
    return raw_result(s, x0), first_beyond(stations_x_m, x0), reached


def _pool_body(lane_init, lane_step, finalize, proto_passage, stations_x_m, stations_z_m,
               order, n_per_task, n_slots, n_items, n_rows, pool, refill_every, settings):
    """The pool loop's body: ``refill_every`` events on every lane, then the
    stations they passed written, finished lanes' results stored and those
    lanes refilled with the next work items (``_refill``)."""

    def body(carry):
        states, words, x0, idx, active, nxt, out, values, reached = carry
        task = idx // n_per_task
        row = task * n_slots + idx % n_per_task  # the item's output row
        item = jnp.where(active, row, n_rows)  # inactive lanes: dropped

        def steps(k, c):
            s, buf = c
            s, passage = jax.vmap(lane_step)(s, words, task)
            return s, jax.tree_util.tree_map(lambda b, a: b.at[:, k].set(a), buf, passage)

        buf = jax.tree_util.tree_map(
            lambda a: jnp.zeros((pool, refill_every) + a.shape, a.dtype), proto_passage)
        states, buf = jax.lax.fori_loop(0, refill_every, steps, (states, buf))
        # the stations these events passed first, written between the steps'
        # loops (``_stations.write``), before a finished lane is refilled
        reached, values = write(values, item, reached, buf, stations_x_m, stations_z_m, order,
                                settings.g_m_s2, settings.station_slots * pool)
        done = active & ~jax.vmap(running)(states)
        res = jax.vmap(finalize)(states, x0, reached)
        target = jnp.where(done, row, n_rows)  # out of bounds: dropped
        out = jax.tree_util.tree_map(lambda o, r: o.at[target].set(r, mode="drop"), out, res)
        states, words, x0, reached, idx, active, nxt = _refill(
            lane_init, stations_x_m, n_items, done, states, words, x0, reached, idx, active,
            nxt)
        return states, words, x0, idx, active, nxt, out, values, reached

    return body


def _refill(lane_init, stations_x_m, n_items, done, states, words, x0, reached, idx, active,
            nxt):
    """Lanes whose block is ``done`` take the next work items (``nxt`` on) while
    any are left; the others keep their state. Returns the lanes' new
    (states, words, x0, reached, idx, active, nxt)."""
    new_idx = nxt + jnp.cumsum(done) - 1
    refill = done & (new_idx < n_items)
    ns, nw = jax.vmap(lane_init)(jnp.where(refill, new_idx, 0))

    def pick(a, c):
        m = refill.reshape(refill.shape + (1,) * (a.ndim - 1))
        return jnp.where(m, a, c)

    states = jax.tree_util.tree_map(pick, ns, states)
    words = pick(nw, words)
    x0 = jnp.where(refill, ns.x_m, x0)
    reached = jnp.where(refill, first_beyond(stations_x_m, ns.x_m), reached)
    idx = jnp.where(refill, new_idx, idx)
    active = (active & ~done) | refill
    nxt = nxt + jnp.sum(done)
    return states, words, x0, reached, idx, active, nxt


_LANE_QUANTUM = 16


def chunk_plan(n_blocks: int, chunk_size: int, workers: int) -> tuple[int, list[int]]:
    """Equal chunks covering ``n_blocks``: (size, first block of each chunk).

    At least one chunk per worker and at most ``chunk_size`` blocks per chunk,
    the number of chunks a multiple of ``workers`` when there are enough blocks;
    equal sizes, a multiple of 16, so that one compiled program serves every
    chunk (the last chunk is padded to the size and its padding dropped)."""
    if n_blocks <= 0:
        raise ValueError(f"n_blocks must be positive, got {n_blocks}")
    if chunk_size <= 0 or workers <= 0:
        raise ValueError(f"chunk_size and workers must be positive, got {chunk_size}, "
                         f"{workers}")
    n_chunks = -(-n_blocks // chunk_size)
    n_chunks = min(n_blocks, -(-n_chunks // workers) * workers)
    size = -(-n_blocks // n_chunks)
    # a multiple of the lane quantum: XLA:CPU runs a vector loop over the lanes
    # and a scalar tail, which round differently (1e-13 m), so lane counts that
    # leave a tail would make results depend on the chunking
    size = -(-size // _LANE_QUANTUM) * _LANE_QUANTUM
    return size, list(range(0, n_blocks, size))


def run_blocks(
    params: Params,
    block: Block,
    key: jax.Array,
    n_blocks: int,
    profile: Profile,
    stations_x_m=None,
    settings: Settings = Settings(),
    chunk_size: int = 65536,
    progress=None,
    pool: int | None = None,
    workers: int | None = None,
) -> Result:
    """Simulate ``n_blocks`` blocks in chunks and return NumPy arrays.

    Chunks run side by side on ``workers`` threads (``solvers.parallel``);
    block i always uses ``fold_in(key, i)``, so the result does not depend on
    ``chunk_size``, ``pool`` or ``workers``.

    Args:
        params, block, profile, settings: as for ``simulate``.
        key: PRNG key of the run.
        n_blocks: number of blocks (> 0).
        stations_x_m: analysis abscissae, m, or None.
        chunk_size: most blocks per compiled call (memory grows linearly with it
            and with ``workers``).
        progress: optional callable ``progress(n_done)`` called after each chunk,
            in block order.
        pool: lanes of ``simulate_pooled`` (None: ``default_pool()``; at most
            ``task_slots(chunk)`` of them are used).
        workers: threads (default ``solvers.parallel.default_workers()``).

    Returns:
        ``Result`` whose leaves are NumPy arrays with leading dimension n_blocks.
    """
    st = jnp.zeros((0,), jnp.float64) if stations_x_m is None else jnp.asarray(
        stations_x_m, jnp.float64)
    workers = default_workers() if workers is None else workers
    chunk, starts = chunk_plan(n_blocks, chunk_size, workers)

    def one(start: int):
        res = simulate_pooled(params, block, key, profile, st, n_blocks=chunk, pool=pool,
                              settings=settings, offset=start)
        count = min(chunk, n_blocks - start)
        return jax.tree_util.tree_map(lambda a: np.asarray(a)[:count], res)

    parts = []
    for part in map_ordered(one, starts, workers):
        parts.append(part)
        if progress is not None:
            progress(part.runout_m.shape[0])
    return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=0), *parts)
