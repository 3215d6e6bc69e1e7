"""One BLAS thread while trimag computes (not public API).

trimag's numerical work is elementwise numpy and small BLAS calls (3 x 3 products over blocks of samples,
9 x 9 Gram matrices of cache-sized blocks), which a multi-threaded BLAS cannot speed up. What a second BLAS
thread does do is spin-wait: whenever another job holds a core, OpenBLAS's idle threads burn it. Measured on the
2-core benchmark machine (docs/performance-history.md, run V, "One BLAS thread during fits"): with one core
busy, 100 ``ml`` fits of 5000-sample files took 1.8-2.9 s with numpy's default two BLAS threads and 1.1-1.3 s
with one; on an idle machine 1.5-1.9 s against 1.3-1.5 s; a 1e7-sample ``ml`` fit takes the same time either way
(1.12 s).

:func:`one_blas_thread` limits every loaded BLAS (numpy's and scipy's OpenBLAS) to one thread for the duration
of a ``with`` block in the main thread, through ``threadpoolctl``, and restores the previous setting afterwards
(in other threads it does nothing: see its docstring). Its controller is built on first use (about 0.7 ms);
entering and leaving a block costs about 15 us.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any

__all__ = ["one_blas_thread"]

_CONTROLLER: Any = None
_DEPTH = 0  # blocks open in the main thread: the outermost sets the limit and restores it
_LIMITER: Any = None


def _controller() -> Any:
    global _CONTROLLER
    if _CONTROLLER is None:
        try:
            from threadpoolctl import ThreadpoolController

            _CONTROLLER = ThreadpoolController()
        except Exception:  # no threadpoolctl or an unreadable library: run with the threads as they are
            _CONTROLLER = False
    return _CONTROLLER


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the block with one BLAS thread when called from the main thread (re-entrant); elsewhere do nothing.

    The BLAS setting belongs to the process, and OpenBLAS (0.3.31, measured) does not reliably apply a change made
    from another thread: a limit set there may not be seen by that thread, and a restore made there may not be seen
    by the main thread, which would leave the process on one BLAS thread after the fit. So only the main thread
    (in-process fits and trials, the common case) changes it; Dask's threaded scheduler runs fits as before, and
    its worker processes start with one BLAS thread anyway (:mod:`trimag.parallel`).
    """
    global _DEPTH, _LIMITER
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if _DEPTH == 0:
        controller = _controller()
        _LIMITER = controller.limit(limits=1, user_api="blas") if controller else None
    _DEPTH += 1
    try:
        yield
    finally:
        _DEPTH -= 1
        if _DEPTH == 0 and _LIMITER is not None:
            _LIMITER.restore_original_limits()
            _LIMITER = None
