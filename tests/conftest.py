"""Shared fixtures; helper functions live in `_helpers.py`."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from _helpers import simulate_ellipsoid

SRC = Path(__file__).resolve().parents[1] / "src" / "trimag"


def stale_installed_copy() -> str | None:
    """Why the imported trimag is not this checkout's ``src/trimag`` (None when it is, or when its files are the
    same bytes, as after ``pip install .`` of this very tree, what CI does).

    After ``pip install .`` a later edit of ``src/`` is not what the tests import: they would pass or fail on
    the old copy. ``pip install -e ".[dev]"`` (an editable install) imports ``src/`` itself."""
    import trimag

    installed = Path(trimag.__file__).resolve().parent
    if not SRC.is_dir() or installed == SRC:
        return None
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC)
        copy = installed / rel
        if not copy.is_file() or copy.read_bytes() != path.read_bytes():
            return (f"the tests import trimag from {installed}, an installed copy that differs from this checkout's "
                    f"src/trimag ({rel}); reinstall, or install for development with pip install -e \".[dev]\"")
    return None


def pytest_sessionstart(session: pytest.Session) -> None:
    reason = stale_installed_copy()
    if reason is not None:
        raise pytest.UsageError(reason)


def pytest_collection_finish(session: pytest.Session) -> None:
    """After the imports of collection (numpy, scipy, pandas, trimag, every test module): those objects live as long
    as the process, so the garbage collector is told to stop traversing them (``gc.freeze``); each later collection
    then walks only what the tests allocate (~10 % of the CPU time of in-process tests such as the fuzzing)."""
    import gc

    gc.collect()
    gc.freeze()


@pytest.fixture
def ellipsoid_log(tmp_path: Path) -> Path:
    """A CSV log (header bx,by,bz plus a time column) of a simulated sensor, 600 rows."""
    raw = simulate_ellipsoid(600, noise=5.0, seed=1)
    path = tmp_path / "log.csv"
    t = np.arange(len(raw)) * 0.02
    np.savetxt(path, np.column_stack([t, raw]), delimiter=",", header="t,bx,by,bz", comments="", fmt="%.6f")
    return path


@pytest.fixture
def small_chunks() -> Iterator[Callable[[int], None]]:
    """Shrink the one chunk setting (trimag._core.chunks): ``small_chunks(rows)`` makes passes over (N, 3) samples
    take ``rows`` rows per chunk from then on, and every other pass proportionally fewer (a pass with 24 doubles of
    temporaries per row: rows / 8), so the multi-chunk path of every pass runs. Restored after the test."""
    from trimag._core import chunks

    tokens = []

    def rows(n: int) -> None:
        tokens.append(chunks._WORKING_MEMORY.set(int(n) * 3 * 8))

    yield rows
    if tokens:
        chunks._WORKING_MEMORY.reset(tokens[0])


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """The counts of the documentation's commands (tests/test_docs.py, issue 42): executed, skipped, failing."""
    counts = {"passed": 0, "skipped": 0, "failed": 0}
    skipped: list[str] = []
    seen = False
    for reports in terminalreporter.stats.values():
        for report in reports:
            if getattr(report, "when", None) != "call":
                continue
            for name, value in getattr(report, "user_properties", ()):
                if name == "doc_commands":
                    seen = True
                    for key in counts:
                        counts[key] += value[key]
                    skipped.extend(value["skipped_list"])
    if not seen:
        return
    terminalreporter.write_line(
        f"doc commands (README.md, docs/*.md): {counts['passed'] + counts['failed']} executed, "
        f"{counts['skipped']} skipped, {counts['failed']} failing"
        + ("" if terminalreporter.config.option.verbose > 0 or not skipped else " (-v lists the skipped ones)"))
    if terminalreporter.config.option.verbose > 0:
        for line in sorted(skipped):
            terminalreporter.write_line(f"  skipped {line}")
