"""Independent runs of a study, in this process or on a Dask cluster, each
saved to its own file the moment it finishes.

A study (``python -m calib.power``) is a list of runs that share nothing: each
is a pure function of its parameters (its PRNG keys come from its own seeds),
so where it runs and in which order does not change its record. ``run_tasks``
takes the list, skips every run whose record file is already there (a killed
study resumes), runs the others and writes each record atomically as it
finishes, with a progress bar over finished runs.

Where the runs go:

* in this process, one after the other (``serial=True`` or one worker);
* a ``dask.distributed.LocalCluster`` of ``workers`` processes on this
  machine, one thread each;
* the Dask scheduler at ``scheduler`` (``tcp://host:port``), whose workers
  someone else started (``dask scheduler`` and ``dask worker`` on the machines
  of a cluster, with this project installed in the same environment there).

Why Dask distributed (and not Ray): pure-Python wheels on PyPI with no
service of its own to install; a LocalCluster of processes by default and
``Client(address)`` for a scheduler elsewhere with the same code; futures and
``as_completed`` are all that independent runs need. Ray brings a compiled
runtime and an object store that a few dozen runs returning small records do
not use.

Worker processes and JAX (only on a LocalCluster, whose processes this module
starts; the workers of a remote scheduler are set up by whoever starts them,
as docs/distributed.md says):

* the processes are started with ``spawn`` (Dask's default, set here
  explicitly): a forked child of a process in which JAX has started its
  thread pools can deadlock;
* each worker takes its share of this machine's cores, ``cores // workers``
  (at least one): ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS`` and
  ``MKL_NUM_THREADS`` are set to it before the worker process starts (Dask's
  ``distributed.nanny.pre-spawn-environ``; BLAS libraries read them when they
  load), and the worker's CPU affinity is set to its own cores before it
  imports JAX (``_CoreShare``): XLA's CPU client sizes its thread pool from
  the affinity mask (the JAX maintainers' advice, jax-ml/jax issue 1539), and
  there is no XLA flag for that pool's size. ``XLA_FLAGS`` is left alone: its
  flags are part of JAX's compilation-cache key and
  ``--xla_cpu_multi_thread_eigen=false`` switches the dot kernels, which could
  change a run's sums from those of a serial run.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import os
import sys
import traceback
from asyncio import CancelledError  # a BaseException, as Dask's cancelled futures raise
from collections.abc import Callable, Sequence

from distributed.diagnostics.plugin import WorkerPlugin

__all__ = ["ClusterUnreachable", "RunFailed", "Task", "local_workers", "run_tasks"]

_BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclasses.dataclass(frozen=True)
class Task:
    """One run: ``fn(*args)`` returns its record (a JSON-ready dict), saved at
    ``path``; ``name`` names the run in progress and error lines. ``fn`` must be
    a module-level function (it travels to the workers by reference)."""

    name: str
    path: str
    fn: Callable
    args: tuple


class ClusterUnreachable(Exception):
    """The scheduler's address is not one, or nothing answers there."""


class RunFailed(Exception):
    """Some runs raised; every other run finished and was saved. The message
    is one line naming the first failed run; ``failures`` holds (task, one-line
    error, traceback text) of each."""

    def __init__(self, failures: list[tuple[Task, str, str]]):
        task, error, _ = failures[0]
        more = f" (and {len(failures) - 1} more failed runs)" if len(failures) > 1 else ""
        super().__init__(f"run {task.name} failed: {error}{more}")
        self.failures = failures


def local_workers() -> int:
    """Worker processes that keep this machine busy: one per usable CPU core on
    the CPU backend (``solvers.parallel.default_workers``); one on an
    accelerator, where one process drives the device (and each JAX process
    would claim most of its memory)."""
    import jax

    from solvers.parallel import default_workers

    return default_workers() if jax.default_backend() == "cpu" else 1


def _cores() -> list[int]:
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:
        return list(range(os.cpu_count() or 1))


class _Reporter:
    """Progress over finished runs (a tqdm bar on stderr, or one line per run),
    saving records as they come and keeping the failures."""

    def __init__(self, total: int, done: int, progress: bool, label: str,
                 save: Callable[[str, dict], None], describe: Callable[[dict], str]):
        self.bar, self.save, self.describe, self.failed = None, save, describe, []
        if progress:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, desc=label, file=sys.stderr)

    def finished(self, task: Task, rec: dict) -> None:
        self.save(task.path, rec)
        self._show(f"{task.name}: {self.describe(rec)}")

    def failed_with(self, task: Task, exc: BaseException, tb) -> None:
        text = "".join(traceback.format_exception(type(exc), exc, tb))
        self.failed.append((task, " ".join(f"{type(exc).__name__}: {exc}".split()), text))
        self._show(f"{task.name}: FAILED")

    def _show(self, line: str) -> None:
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix_str(line)
        else:
            print(line, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        if self.failed:
            raise RunFailed(self.failed)


def run_tasks(tasks: Sequence[Task], save: Callable[[str, dict], None], *,
              scheduler: str | None = None, workers: int = 1, serial: bool = False,
              progress: bool = True, label: str = "runs",
              describe: Callable[[dict], str] = lambda rec: "done") -> list[dict]:
    """Run every task whose record file is missing; the records of all tasks,
    in the order of ``tasks``.

    Args:
        tasks: the runs; their ``path`` values must differ.
        save: ``save(path, record)`` writes a finished run's record (a JSON
            file, atomically: a killed study leaves no half-written record);
            called in this process as each run finishes.
        scheduler: address of a running Dask scheduler (``tcp://host:port``);
            None: this machine.
        workers: processes of the LocalCluster when ``scheduler`` is None
            (capped at the number of runs left; one means this process).
        serial: run in this process whatever ``workers`` says.
        progress: a progress bar on stderr; otherwise one line per finished run.
        label: the progress bar's label.
        describe: ``record -> text`` shown for a finished run.

    Returns:
        The records (read back from the files of runs finished before).

    Raises:
        RunFailed: after every other run finished and was saved.
        ClusterUnreachable: ``scheduler`` is not an address or does not answer
            (before any run starts).
    """
    records: dict[int, dict] = {}
    for i, t in enumerate(tasks):
        if os.path.exists(t.path):
            with open(t.path) as fh:
                records[i] = json.load(fh)
    todo = [(i, t) for i, t in enumerate(tasks) if i not in records]
    report = _Reporter(len(tasks), len(records), progress, label, save, describe)
    try:
        if todo and scheduler is None and (serial or min(workers, len(todo)) <= 1):
            for i, t in todo:
                try:
                    records[i] = t.fn(*t.args)
                except Exception as e:  # noqa: BLE001 - reported by run name at the end
                    report.failed_with(t, e, e.__traceback__)
                else:
                    report.finished(t, records[i])
        elif todo:
            with _client(scheduler, min(workers, len(todo))) as client:
                _gather(client, todo, records, report)
    finally:
        report.close()
    return [records[i] for i in range(len(tasks))]


def _gather(client, todo, records, report) -> None:
    """Submit every run, then save each as it finishes (in finishing order)."""
    from distributed import as_completed

    futures = {client.submit(t.fn, *t.args, pure=False): (i, t) for i, t in todo}
    for fut in as_completed(futures):
        i, t = futures[fut]
        try:  # the run's own exception, or the cluster's (a worker that died: KilledWorker;
            records[i] = fut.result()  # a run cancelled with its scheduler: CancelledError)
        except (Exception, CancelledError) as e:  # noqa: BLE001 - reported at the end
            report.failed_with(t, e, e.__traceback__)
        else:
            report.finished(t, records[i])
        fut.release()


@contextlib.contextmanager
def _client(scheduler: str | None, workers: int):
    """A Dask client of the scheduler at ``scheduler``, or of a LocalCluster of
    ``workers`` spawned processes with one thread and their share of the cores
    each; closed (and the cluster shut down) on leaving."""
    import logging

    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        # a Client that fails to connect has already made itself the process's Dask
        # scheduler (dask.config "scheduler"), and nothing undoes that: put it back
        saved = copy.deepcopy(dask.config.config)
        try:
            client = Client(scheduler)
        except (ValueError, TypeError, OSError) as e:  # OSError: also the timeout
            dask.config.config.clear()
            dask.config.config.update(saved)
            raise ClusterUnreachable(f"no Dask scheduler answers at {scheduler!r} "
                                     f"({type(e).__name__}: {e})") from None
        with client:
            yield client
        return
    cores = _cores()
    share = str(max(1, len(cores) // workers))
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    environ.update(dict.fromkeys(_BLAS_THREADS, share))
    saved = {k: os.environ.get(k) for k in environ}  # the nanny sets them here too
    try:
        with dask.config.set({"distributed.worker.multiprocessing-method": "spawn",
                              "distributed.nanny.pre-spawn-environ": environ}), \
                LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                             dashboard_address=None, silence_logs=logging.CRITICAL) as cluster, \
                Client(cluster) as client:
            client.register_plugin(_CoreShare(cores, workers), name="core-share")
            yield client
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _core_share_of(cores: list[int], workers: int, index: int) -> list[int]:
    """Worker ``index``'s cores: an equal slice of ``cores``, or one core when
    there are more workers than cores."""
    lo, hi = index * len(cores) // workers, (index + 1) * len(cores) // workers
    return cores[lo:hi] or [cores[index % len(cores)]]


class _CoreShare(WorkerPlugin):
    """Sets a LocalCluster worker's CPU affinity to its share of the cores
    (LocalCluster names its workers 0, 1, ...), for every thread of the worker
    process, so that the thread pools JAX starts later are sized to it."""

    def __init__(self, cores: list[int], workers: int):
        self.cores, self.workers = list(cores), workers

    def setup(self, worker) -> None:
        if not hasattr(os, "sched_setaffinity"):
            return
        share = _core_share_of(self.cores, self.workers, int(worker.name))
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setaffinity(int(tid), share)
