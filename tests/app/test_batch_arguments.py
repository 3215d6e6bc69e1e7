"""``trimag batch`` with odd arguments (issue 41, item 17): a file as ``--out``, a folder instead of a pattern, far
more workers than files or than a machine runs, a failing file named once (before: "cannot read or write
noisy.csv: File exists"; "'logs' matches no file; quote the pattern"; ``--workers 100000`` ran for minutes
starting processes for 3 files; "fleet/b.csv: fleet/b.csv: the file is empty")."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import run_trimag


@pytest.fixture()
def fleet(tmp_path: Path) -> Path:
    rng = np.random.default_rng(8)
    folder = tmp_path / "fleet"
    folder.mkdir()
    for k in range(2):
        u = rng.normal(size=(300, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        np.savetxt(folder / f"log{k}.csv", u * 500 + rng.normal(0, 2, (300, 3)), delimiter=",", header="x,y,z",
                   comments="")
    (folder / "empty.csv").write_text("")
    return folder


def test_a_file_as_out_is_refused_in_words(fleet: Path, tmp_path: Path) -> None:
    out = tmp_path / "summary.csv"
    out.write_text("keep me\n")
    r = run_trimag("batch", str(fleet / "log*.csv"), "--out", out)
    assert r.returncode == 2 and f"--out {out} is a file; batch writes a folder" in r.stderr, r.stderr
    assert out.read_text() == "keep me\n"


def test_a_folder_instead_of_a_pattern_is_named_with_the_pattern_to_give(fleet: Path, tmp_path: Path) -> None:
    empty = tmp_path / "nothing"
    empty.mkdir()
    r = run_trimag("batch", empty, "--out", tmp_path / "out")
    assert r.returncode == 2 and f"{empty} is a folder: give the logs in it as a quoted pattern" in r.stderr


def test_workers_beyond_the_files_or_the_machine(fleet: Path, tmp_path: Path) -> None:
    r = run_trimag("batch", str(fleet / "log*.csv"), "--out", tmp_path / "out", "--workers", "100", "-q",
                   timeout=60)
    assert r.returncode == 0, r.stderr  # two files: two processes at most, not 100
    r = run_trimag("batch", str(fleet / "log*.csv"), "--out", tmp_path / "out2", "--workers", "100000")
    assert r.returncode == 2 and "--workers 100000 is more processes than a machine runs usefully" in r.stderr
    assert not (tmp_path / "out2").exists()


def test_a_failing_file_is_named_once(fleet: Path, tmp_path: Path) -> None:
    r = run_trimag("batch", str(fleet / "*.csv"), "--out", tmp_path / "out", "-q")
    assert r.returncode == 2
    line = next(x for x in r.stderr.splitlines() if "empty.csv" in x)
    assert line.count("empty.csv") == 1, line
