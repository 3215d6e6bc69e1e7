"""Tests of trimag.parallel: the same results in-process, on the local pools (processes, threads; no Dask) and with
progress shown."""

from __future__ import annotations

import io
import sys
from functools import partial

import numpy as np
import pytest

from trimag import parallel
from trimag.errors import TrimagInputError
from trimag.parallel import ProgressBar, map_trials, trial_seeds


def _fit_trial(seed: int, n: int = 300) -> tuple[float, ...]:
    """A small numpy-heavy trial: fit a simulated sensor; returns the offset (bit-exact comparisons)."""
    import trimag

    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    raw = u * [1.1, 0.9, 1.0] * 50.0 + [3.0, -2.0, 1.0] + rng.normal(scale=0.1, size=(n, 3))
    cal = trimag.fit(raw, method="ml", reference=50.0)
    return tuple(cal.offset.tolist())


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise ValueError("trial 3 failed")
    return x * x


def _sleep_and_report(x: int) -> int:
    import os
    import time

    time.sleep(0.2)
    return os.getpid()


def test_worker_processes_share_the_chunks_as_they_free_up() -> None:
    """Each idle worker process is handed one chunk at a time. (Dask's multiprocessing scheduler by default hands
    out batches of 6 tasks fixed in advance: of 8 equal chunks one worker got 6 and the other 2, which cost the
    batch benchmark ~20 % of its throughput; docs/performance.md.)"""
    import collections

    pids = map_trials(_sleep_and_report, list(range(8)), workers=2, chunksize=1, progress=False)
    counts = collections.Counter(pids)
    assert len(counts) == 2 and max(counts.values()) <= 5, counts


def test_trial_seeds_deterministic_and_distinct() -> None:
    a = trial_seeds(7, 50)
    assert a == trial_seeds(7, 50)
    assert len(set(a)) == 50
    assert a[:10] == trial_seeds(7, 10)  # a prefix does not depend on how many are drawn
    assert a != trial_seeds(8, 50)
    assert all(0 <= s < 2**63 for s in a)
    with pytest.raises(TrimagInputError, match="trials"):
        trial_seeds(0, -1)


def test_in_process_keeps_order() -> None:
    assert map_trials(_fail_on_three, [5, 1, 2], progress=False) == [25, 1, 4]
    assert map_trials(_fail_on_three, [], progress=False) == []


@pytest.mark.parametrize("backend", ["threads", "processes"])
def test_local_scheduler_matches_in_process(backend: str) -> None:
    seeds = trial_seeds(1, 12)
    serial = map_trials(_fit_trial, seeds, progress=False)
    # chunksize 5 over 12 items: uneven chunks must still come back in order
    par = map_trials(_fit_trial, seeds, workers=2, backend=backend, chunksize=5, progress=False)
    assert par == serial  # bit-identical: one BLAS thread per process, order preserved


def test_partial_and_builtin_functions() -> None:
    out = map_trials(partial(_fit_trial, n=200), trial_seeds(3, 3), workers=2, backend="threads", progress=False)
    assert out == [_fit_trial(s, n=200) for s in trial_seeds(3, 3)]
    assert map_trials(abs, [-1, 2, -3], workers=2, backend="threads", progress=False) == [1, 2, 3]


@pytest.mark.parametrize("workers,backend", [(1, None), (2, "threads"), (2, "processes")])
def test_trial_error_is_raised(workers: int, backend: str | None) -> None:
    with pytest.raises(ValueError, match="trial 3 failed"):
        map_trials(_fail_on_three, range(6), workers=workers, backend=backend, chunksize=1, progress=False)


def test_kept_process_pool_survives_a_failed_run_and_needs_no_dask(monkeypatch: pytest.MonkeyPatch) -> None:
    """A trial's error leaves the kept worker processes usable; local runs never import Dask."""
    for name in ("dask", "distributed"):
        monkeypatch.setitem(sys.modules, name, None)  # `import dask` now fails, as without the batch extra
    with pytest.raises(ValueError, match="trial 3 failed"):
        map_trials(_fail_on_three, range(40), workers=2, chunksize=1, progress=False)
    assert map_trials(_fail_on_three, [4, 5, 6], workers=2, chunksize=1, progress=False) == [16, 25, 36]
    assert map_trials(_fail_on_three, [7, 8], workers=2, backend="threads", progress=False) == [49, 64]


def _die_on_three(x: int) -> int:
    """A trial whose worker process dies on item 3 (as the kernel's out-of-memory killer kills it)."""
    import os
    import signal

    if x == 3:
        os.kill(os.getpid(), signal.SIGKILL)
    return x * x


def test_a_worker_that_dies_costs_only_its_own_item() -> None:
    """Issue 33, item 4: a dead worker broke the pool and the whole run (batch exit 1, no summary). With
    ``worker_died`` the items that were running are retried, each alone when suspected; the one that kills its
    worker when alone gets ``worker_died(item)``; every other item gets its result; the kept pool is usable."""
    died: list[int] = []

    def note(item: int) -> int:
        died.append(item)
        return -1

    # chunks of 3: the dead worker's chunk-mates and the other worker's chunk are struck too, then cleared
    out = map_trials(_die_on_three, range(10), workers=2, chunksize=3, progress=False, worker_died=note)
    assert out == [0, 1, 4, -1, 16, 25, 36, 49, 64, 81] and died == [3]
    assert map_trials(_fail_on_three, [4, 5], workers=2, progress=False) == [16, 25]
    from concurrent.futures.process import BrokenProcessPool

    with pytest.raises(BrokenProcessPool):  # without `worker_died`: as before
        map_trials(_die_on_three, range(6), workers=2, chunksize=1, progress=False)
    assert map_trials(_fail_on_three, [6], workers=2, progress=False) == [36]


@pytest.mark.parametrize(
    "kwargs,match",
    [({"workers": 0}, "workers"), ({"workers": 1.5}, "workers"), ({"workers": True}, "workers"),
     ({"chunksize": 0}, "chunksize"), ({"backend": "gpu"}, "backend")],
)
def test_bad_arguments(kwargs: dict, match: str) -> None:
    with pytest.raises(TrimagInputError, match=match):
        map_trials(abs, [1], progress=False, **kwargs)


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_on_terminal_stderr(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = _Terminal()
    monkeypatch.setattr(sys, "stderr", fake)
    monkeypatch.setattr(parallel, "_SHOW_AFTER_S", 0.0)  # show at once instead of after 1 s
    assert map_trials(abs, [-1, -2, -3], progress="my trials") == [1, 2, 3]
    text = fake.getvalue()
    assert "my trials" in text and "3/3" in text


def test_no_progress_when_disabled_or_not_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(parallel, "_SHOW_AFTER_S", 0.0)
    fake = _Terminal()
    monkeypatch.setattr(sys, "stderr", fake)
    map_trials(abs, [-1, -2], progress=False)
    assert fake.getvalue() == ""
    pipe = io.StringIO()  # not a terminal: no bar, no escape codes in logs
    monkeypatch.setattr(sys, "stderr", pipe)
    map_trials(abs, [-1, -2], progress=True)
    assert pipe.getvalue() == ""


def test_progress_bar_open_count(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = _Terminal()
    monkeypatch.setattr(sys, "stderr", fake)
    monkeypatch.setattr(parallel, "_SHOW_AFTER_S", 0.0)
    with ProgressBar("trimag apply", None, unit="rows") as bar:
        bar.update(1_234_567)
    assert "1,234,567 rows" in fake.getvalue()


def test_progress_waits_a_second(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = _Terminal()
    monkeypatch.setattr(sys, "stderr", fake)
    with ProgressBar("quick", 10) as bar:  # finishes well within the default 1 s: nothing shown
        bar.advance(10)
    assert fake.getvalue() == ""
