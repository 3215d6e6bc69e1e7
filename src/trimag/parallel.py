"""A small executor for independent trials: in-process, a local pool of worker processes (or threads), or a
``dask.distributed`` cluster.

Every Monte Carlo reproduction, benchmark and :mod:`trimag.app.batch` run goes through :func:`map_trials`, so one
``--workers N`` (or ``--scheduler ADDRESS``) option speeds all of them up.

Rules for the function you pass (so that the same code runs in one process, in worker processes, or on a
cluster):

* it must be picklable: a module-level function (or a :func:`functools.partial` of one), not a lambda or a
  closure;
* each item carries everything a trial needs, in particular its own random seed (use :func:`trial_seeds`), so
  the results do not depend on ``workers`` or on the order in which trials finish;
* it returns something picklable and small (numbers, a dict, a small array), not the simulated data.

Local runs (``workers >= 1``) need nothing beyond the core install (:mod:`concurrent.futures`); only a cluster
(``scheduler=``) needs Dask, the ``batch`` extra (``pip install "trimag[batch]"``).

Example
-------
>>> from trimag.parallel import map_trials, trial_seeds
>>> import numpy as np
>>> def trial(seed):  # at module level in real code
...     return float(np.random.default_rng(seed).normal())
>>> out = map_trials(trial, trial_seeds(0, 4), progress=False)
>>> len(out)
4
"""

from __future__ import annotations

import atexit
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_EXCEPTION, Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ._core.extras import require
from ._core.threads import one_blas_thread
from .errors import TrimagInputError

__all__ = ["DEFAULT_LOCAL_BACKEND", "ProgressBar", "map_trials", "shutdown_pools", "trial_seeds"]

T = TypeVar("T")
R = TypeVar("R")

#: Local pool used for ``workers > 1``. ``"processes"`` sidesteps the GIL, which numpy only releases inside large
#: array operations; for trials of a few thousand samples (the usual Monte Carlo and calibration-log sizes) it
#: measured faster than ``"threads"`` on the 2-core benchmark machine (docs/performance-history.md, "The executor").
DEFAULT_LOCAL_BACKEND = "processes"

_SHOW_AFTER_S = 1.0


def trial_seeds(seed: int | None, n: int) -> list[int]:
    """``n`` independent integer seeds derived from ``seed`` (``numpy.random.SeedSequence.spawn``).

    Give trial ``k`` the seed ``trial_seeds(seed, n)[k]``: the results are then the same whatever the number
    of workers and whatever order the trials finish in.
    """
    if n < 0:
        raise TrimagInputError(f"the number of trials must be >= 0; got {n}")
    children = np.random.SeedSequence(seed).spawn(n)
    return [int(c.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1)) for c in children]


def _apply_chunk(fn: Callable[[Any], Any], chunk: Sequence[Any]) -> list[Any]:
    """Run ``fn`` on every item of one chunk (the unit of work shipped to a worker)."""
    return [fn(item) for item in chunk]


class ProgressBar:
    """A rich progress bar on stderr that appears only once the work has taken more than a second, and only
    when stderr is a terminal (logs and pipes get no escape codes).

    Parameters
    ----------
    label : str
        Text before the bar.
    total : int, optional
        Number of units of work; ``None`` for an open count (e.g. rows of a file being streamed).
    enabled : bool
        ``False`` makes every method a no-op.
    unit : str
        Name of the unit shown with an open count (``"rows"``).

    Use as a context manager; call :meth:`advance` (increments) or :meth:`update` (absolute count).
    """

    def __init__(self, label: str, total: int | None = None, enabled: bool = True, unit: str = "") -> None:
        self.label = label
        self.total = total
        self.unit = unit
        self.enabled = enabled and total != 0
        self.done = 0
        self.t0 = time.monotonic()
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> ProgressBar:
        return self

    def advance(self, k: int) -> None:
        """Add ``k`` finished units."""
        self.update(self.done + k)

    def update(self, done: int) -> None:
        """Set the number of finished units."""
        self.done = done
        if not self.enabled:
            return
        if self._progress is None and time.monotonic() - self.t0 > _SHOW_AFTER_S:
            self._start()
        if self._progress is not None:
            self._progress.update(self._task, completed=self.done)

    def _start(self) -> None:
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        console = Console(file=sys.stderr)
        if not console.is_terminal:
            self.enabled = False
            return
        if self.total is None:
            columns: tuple[Any, ...] = (
                TextColumn("[bold]{task.description}"), BarColumn(bar_width=20),
                TextColumn("{task.completed:,} " + self.unit), TimeElapsedColumn(),
            )
        else:
            columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                       TimeRemainingColumn())
        self._progress = Progress(*columns, console=console, transient=False)
        self._progress.start()
        self._task = self._progress.add_task(self.label, total=self.total, completed=self.done)

    def close(self) -> None:
        """Stop the display (leaving its last state on the terminal)."""
        if self._progress is not None:
            self._progress.update(self._task, completed=self.done)
            self._progress.stop()
            self._progress = None

    def __exit__(self, *exc: object) -> None:
        self.close()


_BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
_POOLS: dict[int, ProcessPoolExecutor] = {}


def _noop(i: int) -> int:
    return i


def _process_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` spawned processes, kept for reuse by later calls (closed at exit).

    The workers start with one BLAS thread each: ``workers`` processes each running a multi-threaded BLAS on
    the same cores oversubscribe them (measured: several times slower), and one thread per process also makes
    results bit-identical to an in-process run. Workers are spawned (not forked), so they read these variables
    when numpy loads.
    """
    pool = _POOLS.get(workers)
    if pool is not None and not getattr(pool, "_broken", False):
        return pool
    if pool is not None:  # a worker died (killed by the system, a crash in a C library): start a new pool
        pool.shutdown(wait=False, cancel_futures=True)
    import multiprocessing

    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    saved = {k: os.environ.get(k) for k in _BLAS_ENV}
    os.environ.update({k: "1" for k in _BLAS_ENV})
    try:  # start every worker now, while the environment says one BLAS thread
        list(pool.map(_noop, range(workers)))
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    _POOLS[workers] = pool
    return pool


def shutdown_pools() -> None:
    """Stop the worker processes kept by earlier ``map_trials(..., workers > 1)`` calls."""
    while _POOLS:
        _, pool = _POOLS.popitem()
        pool.shutdown(wait=True, cancel_futures=True)


atexit.register(shutdown_pools)


def _chunks(items: list[T], chunksize: int) -> list[list[T]]:
    return [items[i : i + chunksize] for i in range(0, len(items), chunksize)]


def _auto_chunksize(n: int, slots: int) -> int:
    # ~8 chunks per worker: few enough that per-task overhead (pickling, scheduling: ~1 ms) is negligible,
    # enough for load balancing and a moving progress bar
    return max(1, math.ceil(n / (8 * max(slots, 1))))


#: Most local worker processes :func:`map_trials` starts (each imports numpy and trimag: ~100 MB, ~1 s)
MAX_LOCAL_WORKERS = 256


def check_workers(workers: Any, scheduler: Any = None) -> None:
    """Refuse a number of local worker processes that is not a whole number of 1 or more, or beyond
    :data:`MAX_LOCAL_WORKERS` (without a ``scheduler``, whose cluster has its own)."""
    if isinstance(workers, bool) or not isinstance(workers, int | np.integer) or workers < 1:
        raise TrimagInputError(f"`workers` must be a whole number of 1 or more; got {workers!r}")
    if workers > MAX_LOCAL_WORKERS and scheduler is None:
        raise TrimagInputError(f"`workers` {workers} is more processes than a machine runs usefully (this one has "
                               f"{os.cpu_count() or 1} cores); give at most {MAX_LOCAL_WORKERS}, about the number of "
                               "cores")


def map_trials(
    fn: Callable[[T], R],
    items: Iterable[T],
    *,
    workers: int = 1,
    scheduler: Any = None,
    progress: bool | str = True,
    chunksize: int | None = None,
    backend: str | None = None,
    worker_died: Callable[[T], R] | None = None,
) -> list[R]:
    """Apply ``fn`` to every item and return the results in the order of ``items``.

    Parameters
    ----------
    fn : callable
        ``fn(item) -> result``. Module-level (picklable) when ``workers > 1`` or ``scheduler`` is given.
    items : iterable
        One entry per trial (e.g. a seed, or a ``(seed, noise)`` tuple, or a file path).
    workers : int
        ``1`` (default): run in this process. ``> 1``: a local pool of this many worker processes (or threads,
        ``backend``). Ignored when ``scheduler`` is given (the cluster has its own workers).
    scheduler : str or distributed.Client, optional
        Address of a running ``dask.distributed`` scheduler (e.g. ``"tcp://10.0.0.5:8786"``), or a ``Client``;
        the trials then run on that cluster. A client opened here is closed afterwards; a client passed in is
        left open. Needs Dask (the ``batch`` extra).
    progress : bool or str
        Show a rich progress bar on stderr when the run takes more than a second (and stderr is a terminal).
        A string is used as the bar's label (default label: ``"trials"``).
    chunksize : int, optional
        Items per task. Default: about 8 tasks per worker, which keeps per-task overhead negligible.
    backend : {"processes", "threads"}, optional
        Local pool for ``workers > 1``; default :data:`DEFAULT_LOCAL_BACKEND`. ``"threads"`` avoids starting
        processes and suits trials dominated by large numpy operations (which release the GIL).
    worker_died : callable, optional
        Local worker processes only: survive a worker process that dies (killed by the kernel's out-of-memory
        killer, a crash in a C library). The items it was running are run again, then each alone; an item whose
        worker dies while it runs alone gets ``worker_died(item)`` (called in this process) as its result, every
        other item its own result. Without it, such a death raises ``BrokenProcessPool``.

    Returns
    -------
    list
        ``[fn(item) for item in items]``, whatever the execution route.

    Raises
    ------
    TrimagInputError
        ``workers < 1``, ``chunksize < 1`` or an unknown ``backend``.
    MissingExtraError
        ``scheduler`` is given and Dask is not installed (``pip install "trimag[batch]"``).
    Exception
        The first exception raised by ``fn`` is re-raised (catch errors inside ``fn`` to keep going, as
        :mod:`trimag.app.batch` does for bad files).
    """
    check_workers(workers, scheduler)
    if chunksize is not None and chunksize < 1:
        raise TrimagInputError(f"chunksize must be >= 1; got {chunksize!r}")
    backend = backend or DEFAULT_LOCAL_BACKEND
    if backend not in ("processes", "threads"):
        raise TrimagInputError(f"backend must be 'processes' or 'threads'; got {backend!r}")
    items = list(items)
    label = progress if isinstance(progress, str) else "trials"
    with ProgressBar(label, len(items), bool(progress)) as bar:
        if not items:
            return []
        if scheduler is not None:
            return _run_distributed(fn, items, scheduler, chunksize, bar)
        workers = min(int(workers), len(items))  # no process without an item to run: 3 files need 3 at most
        if workers == 1:
            out = []
            with one_blas_thread():  # as in the worker processes (trimag._core.threads)
                for item in items:
                    out.append(fn(item))
                    bar.advance(1)
            return out
        if worker_died is not None and backend == "processes":
            return _run_surviving(fn, items, int(workers), chunksize, bar, worker_died)
        return _run_local(fn, items, int(workers), backend, chunksize, bar)


def _tracked_chunk(fn: Callable[[Any], Any], chunk: Sequence[Any], marker: str) -> list[Any]:
    """:func:`_apply_chunk` that leaves the file ``marker`` while it runs: a chunk whose marker is left after its
    worker died was running then (not merely queued)."""
    with open(marker, "wb"):
        pass
    out = _apply_chunk(fn, chunk)
    os.unlink(marker)
    return out


def _run_surviving(
    fn: Callable[[T], R], items: list[T], workers: int, chunksize: int | None, bar: ProgressBar,
    worker_died: Callable[[T], R],
) -> list[R]:
    """:func:`_run_local` on the kept process pool, surviving dead workers (see ``worker_died`` of
    :func:`map_trials`). Rounds: items never caught in a death run in chunks; items running when a worker died run
    again one per task; items caught twice run alone (nothing else running), where a death is their own."""
    results: dict[int, R] = {}
    strikes = [0] * len(items)
    markers = Path(tempfile.mkdtemp(prefix="trimag-tasks-"))
    todo = list(range(len(items)))
    try:
        for round_ in range(3 * len(items) + 1):  # every round finishes or strikes an item, or finishes a death
            if not todo:
                break
            fresh = [i for i in todo if strikes[i] == 0]
            tasks = _chunks(fresh, chunksize or _auto_chunksize(len(fresh), workers)) if fresh else []
            tasks += [[i] for i in todo if strikes[i] == 1]
            alone = [i for i in todo if strikes[i] >= 2]
            todo = _surviving_round(fn, items, tasks, workers, markers / str(round_), results, strikes, bar)
            for i in alone:
                try:
                    future = _process_pool(workers).submit(_tracked_chunk, fn, [items[i]],
                                                           str(markers / f"{round_}-alone-{i}"))
                except BrokenProcessPool:  # a new worker died as it started: try again next round
                    todo.append(i)
                    continue
                try:
                    results[i] = future.result()[0]
                except BrokenProcessPool:
                    results[i] = worker_died(items[i])
                bar.advance(1)
        for i in todo:  # deaths that struck no running task, round after round: give up on these items
            results[i] = worker_died(items[i])
    finally:
        shutil.rmtree(markers, ignore_errors=True)
    return [results[i] for i in range(len(items))]


def _surviving_round(
    fn: Callable[[T], R], items: list[T], tasks: list[list[int]], workers: int, markers: Path,
    results: dict[int, R], strikes: list[int], bar: ProgressBar,
) -> list[int]:
    """Run ``tasks`` (lists of item indices) on the pool into ``results``; returns the indices to run again (a
    death broke the pool before they finished), with a strike for those whose task was running."""
    if not tasks:
        return []
    markers.mkdir()
    try:
        pool = _process_pool(workers)
    except BrokenProcessPool:  # a new worker died as it started: no task ran, all run again
        return sorted(i for task in tasks for i in task)
    futures = {pool.submit(_tracked_chunk, fn, [items[i] for i in task], str(markers / str(k))): (task, k)
               for k, task in enumerate(tasks)}
    again: list[int] = []
    pending: set[Future[list[R]]] = set(futures)
    try:
        while pending:
            done, pending = wait(pending, return_when=FIRST_EXCEPTION)
            for fut in done:
                task, k = futures[fut]
                if isinstance(fut.exception(), BrokenProcessPool):
                    if (markers / str(k)).exists():
                        for i in task:
                            strikes[i] += 1
                    again += task
                    continue
                results.update(zip(task, fut.result(), strict=True))  # a trial's own error is raised here
                bar.advance(len(task))
    finally:
        for fut in pending:
            fut.cancel()
    return sorted(again)


def _run_local(
    fn: Callable[[T], R], items: list[T], workers: int, backend: str, chunksize: int | None, bar: ProgressBar
) -> list[R]:
    """Run the chunks on the kept process pool (or a thread pool), one chunk per dispatch, in order of ``items``.

    One chunk at a time per worker: a worker that finishes early takes the next chunk, instead of idling while
    another still has several (measured: a fixed batch of chunks per worker leaves cores idle at the end).
    """
    chunks = _chunks(items, chunksize or _auto_chunksize(len(items), workers))
    pool: Executor = _process_pool(workers) if backend == "processes" else ThreadPoolExecutor(workers)
    futures: list[Future[list[R]]] = []
    try:
        futures = [pool.submit(_apply_chunk, fn, chunk) for chunk in chunks]
        size = {id(f): len(c) for f, c in zip(futures, chunks, strict=True)}
        pending: set[Future[list[R]]] = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_EXCEPTION)
            for fut in done:
                fut.result()  # re-raises the trial's exception here (the rest are cancelled below)
                bar.advance(size[id(fut)])
        return [r for fut in futures for r in fut.result()]
    finally:
        for fut in futures:
            fut.cancel()  # after an error: chunks not yet started are dropped; the kept pool stays usable
        if backend != "processes":
            pool.shutdown(wait=True)


def _run_distributed(
    fn: Callable[[T], R], items: list[T], scheduler: Any, chunksize: int | None, bar: ProgressBar
) -> list[R]:
    distributed = require("distributed", "running on a Dask cluster (`scheduler`)")
    Client, as_completed = distributed.Client, distributed.as_completed

    own = not isinstance(scheduler, Client)
    try:
        client = Client(scheduler, set_as_default=False) if own else scheduler
    except OSError as exc:
        raise TrimagInputError(
            f"cannot connect to the Dask scheduler at {scheduler!r} ({exc}); start one with "
            "`dask scheduler` and workers with `dask worker ADDRESS`, or drop `scheduler` to run locally"
        ) from None
    try:
        slots = sum(client.nthreads().values()) or 1
        chunks = _chunks(items, chunksize or _auto_chunksize(len(items), slots))
        futures = client.map(_apply_chunk, [fn] * len(chunks), chunks, pure=False)
        size = {f.key: len(c) for f, c in zip(futures, chunks, strict=True)}
        for fut in as_completed(futures, loop=client.loop):
            if fut.status == "error":
                fut.result()  # re-raises the trial's exception here
            bar.advance(size[fut.key])
        results = client.gather(futures)
    finally:
        if own:
            client.close()
    return [r for chunk_result in results for r in chunk_result]
