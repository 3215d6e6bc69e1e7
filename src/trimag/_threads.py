"""One BLAS thread while trimag computes (not public API).

trimag's numerical work is elementwise numpy and small BLAS calls (3 x 3 products over blocks of samples,
9 x 9 Gram matrices of cache-sized blocks), which a multi-threaded BLAS cannot speed up. What a second BLAS
thread does do is spin-wait: whenever another job holds a core, OpenBLAS's idle threads burn it. Measured on the
2-core benchmark machine (docs/performance.md, "One BLAS thread"): with one core busy, 100 ``ml`` fits of
5000-sample files took 1.8-2.9 s with numpy's default two BLAS threads and 1.1-1.3 s with one; on an idle
machine 1.5-1.9 s against 1.3-1.5 s; a 1e7-sample ``ml`` fit takes the same time either way (1.12 s).

:func:`one_blas_thread` limits every loaded BLAS (numpy's and scipy's OpenBLAS) to one thread for the duration
of a ``with`` block, through ``threadpoolctl``, and restores the previous setting afterwards. Its controller is
built on first use (about 0.7 ms); entering and leaving the block costs about 11 us.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any

__all__ = ["one_blas_thread"]

_CONTROLLER: Any = None
_LOCK = threading.Lock()
_STATE = threading.local()


def _controller() -> Any:
    global _CONTROLLER
    with _LOCK:
        if _CONTROLLER is None:
            try:
                from threadpoolctl import ThreadpoolController

                _CONTROLLER = ThreadpoolController()
            except Exception:  # no threadpoolctl or an unreadable library: run with the threads as they are
                _CONTROLLER = False
        return _CONTROLLER


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the block with one BLAS thread (re-entrant: nested blocks do nothing more)."""
    depth = getattr(_STATE, "depth", 0)
    controller: Any = _controller() if depth == 0 else False
    limiter = controller.limit(limits=1, user_api="blas") if controller else contextlib.nullcontext()
    _STATE.depth = depth + 1
    try:
        with limiter:
            yield
    finally:
        _STATE.depth = depth
