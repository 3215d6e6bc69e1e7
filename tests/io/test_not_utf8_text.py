"""A CSV log that is not UTF-8 (a spreadsheet's Latin-1 export: a temperature column of "20 degC" with the degree
sign as byte 0xb0) read by ``fit``,
``apply`` and ``evaluate`` (issue 41, item 17): one line naming the file and the byte, and what to do (before:
fit said "cannot parse as delimited text: 'utf-8' codec can't decode byte 0xb0 in position 0: invalid start byte";
apply and evaluate named no file and printed the byte as Python's b'\\xb0' "at position" of a parser's buffer)."""

from __future__ import annotations

from pathlib import Path

import pytest

from _helpers import run_trimag, write_sphere_csv


@pytest.mark.parametrize("command", ["fit", "apply", "evaluate"])
def test_a_latin1_log_is_named_with_its_byte_and_what_to_do(tmp_path: Path, command: str) -> None:
    good = write_sphere_csv(tmp_path / "good.csv", seed=4)
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", good, "-o", cal, "-q").returncode == 0
    latin = tmp_path / "latin.csv"
    latin.write_bytes(good.read_bytes().replace(b"\n", b",20\xb0C\n").replace(b"x,y,z,20\xb0C", b"x,y,z,temp", 1))
    args = {"fit": ["fit", latin, "-q"], "apply": ["apply", cal, latin, "-o", tmp_path / "out.csv"],
            "evaluate": ["evaluate", cal, latin]}[command]
    r = run_trimag(*args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert f"{latin}: not UTF-8 text (byte 0xb0" in lines[0] and "save it as UTF-8" in lines[0], r.stderr
    assert "codec" not in r.stderr and "b'" not in r.stderr
    assert not (tmp_path / "out.csv").exists()
