"""The tests' zygote (tests/_zygote.py) forks a child per ``trimag`` command: it must not hold a thread that takes
the allocator's locks at any time (pyarrow's jemalloc background thread), or a child forked while that thread holds
one waits forever (seen: a forked ``trimag fit`` that never answered, then every later command of that worker
failing)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _zygote


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="threads are listed from /proc (Linux)")
def test_the_zygote_forks_without_an_allocator_thread() -> None:
    proc = _zygote._start()
    _zygote.run_forked(["--version"], cwd=None, env=dict(os.environ), timeout=120)  # warmed up
    names = [(t / "comm").read_text().strip() for t in Path(f"/proc/{proc.pid}/task").iterdir()]
    assert "jemalloc_bg_thd" not in names, names
