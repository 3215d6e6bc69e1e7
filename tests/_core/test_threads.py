"""``trimag._core.threads.one_blas_thread``: fits and in-process trials run with one BLAS thread, restored after."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg  # noqa: F401  (loads scipy's own OpenBLAS, so both libraries are checked)
from threadpoolctl import threadpool_info, threadpool_limits

import trimag
from trimag._core.threads import one_blas_thread
from trimag.parallel import map_trials


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def _trial(_: int) -> list[int]:
    return _blas_threads()


def test_one_thread_inside_restored_after_even_on_error() -> None:
    with threadpool_limits(limits=2, user_api="blas"):  # a known starting point on any machine
        before = _blas_threads()
        if not before or any(n != 2 for n in before):
            pytest.skip("this machine's BLAS cannot be set to two threads, so a limit to one cannot be seen")
        with one_blas_thread():
            assert all(n == 1 for n in _blas_threads())
            with one_blas_thread():  # nested: still one, and the outer block restores
                assert all(n == 1 for n in _blas_threads())
            assert all(n == 1 for n in _blas_threads())
        assert _blas_threads() == before
        with pytest.raises(ValueError), one_blas_thread():
            raise ValueError("boom")
        assert _blas_threads() == before


def test_fit_and_in_process_trials_run_with_one_blas_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    from trimag.estimators.ellipsoid_fit import EllipsoidFit

    seen: list[list[int]] = []
    original = EllipsoidFit._fit

    def spy(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(_blas_threads())
        return original(self, *args, **kwargs)

    monkeypatch.setattr(EllipsoidFit, "_fit", spy)
    u = np.random.default_rng(0).normal(size=(500, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    with threadpool_limits(limits=2, user_api="blas"):
        if any(n != 2 for n in _blas_threads()):
            pytest.skip("this machine's BLAS cannot be set to two threads, so a limit to one cannot be seen")
        trimag.fit(u * [1.1, 0.9, 1.0] + 0.1, method="ellipsoid-fit")
        assert all(n == 2 for n in _blas_threads())  # restored
        trials = map_trials(_trial, range(3), progress=False)
    assert seen and all(n == 1 for n in seen[0])
    assert all(all(n == 1 for n in t) for t in trials)


def test_other_threads_leave_the_blas_setting_alone() -> None:
    """Only the main thread changes the (process-wide) BLAS setting: OpenBLAS does not reliably apply a change made
    from another thread, and a restore made there could leave the process on one thread. A fit in a worker thread
    (Dask's threaded scheduler) therefore runs with the setting as it is, and leaves it as it was."""
    import threading

    before = _blas_threads()
    seen: list[list[int]] = []

    def worker() -> None:
        u = np.random.default_rng(1).normal(size=(500, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        with one_blas_thread():
            seen.append(_blas_threads())
        trimag.fit(u * [1.1, 0.9, 1.0] + 0.1, method="ml")

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len(seen) == 2 and all(s == before for s in seen)
    assert _blas_threads() == before
    with one_blas_thread():  # the main thread still limits afterwards
        assert all(n == 1 for n in _blas_threads())
    assert _blas_threads() == before
