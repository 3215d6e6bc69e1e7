"""``trimag simulate`` with impossible numbers (issue 41, item 17): a field of 0, a negative or infinite one, a
negative seed, a parameter that is not a number, a singular soft-iron matrix or values too large for a reading are
refused in one line (exit 2), nothing written (before: exit 0 with a file of a zero or negative field, numpy warnings
with source paths and exit 0 for an infinite field or 1e308 offsets, exit 1 "internal error" for the rest)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from _helpers import run_trimag


@pytest.mark.parametrize(("params", "extra", "said"), [
    ({"hard_iron_x": 1.0}, ["--field", "0"], "--field must be a positive field magnitude"),
    ({"hard_iron_x": 1.0}, ["--field", "-1"], "--field must be a positive field magnitude"),
    ({"hard_iron_x": 1.0}, ["--field", "inf"], "--field must be a positive field magnitude"),
    ({"hard_iron_x": 1.0}, ["--seed", "-1"], "--seed must be a whole number of 0 or more"),
    ({"hard_iron_x": "a"}, [], "every parameter must be a finite number; got hard_iron_x = 'a'"),
    ({"w11": 0, "w22": 0, "w33": 0}, [], "give a matrix with a non-zero determinant"),
    ({"hard_iron_x": 1e308, "w11": 1e300}, [], "these parameters give no finite readings"),
])
def test_impossible_numbers_are_refused_in_one_line(tmp_path: Path, params: dict, extra: list[str], said: str) -> None:
    p = tmp_path / "p.json"
    p.write_text(json.dumps(params))
    out = tmp_path / "s.csv"
    r = run_trimag("simulate", "--model", "ellipsoid", "--params", p, "--n", "50", "-o", out, *extra)
    assert r.returncode == 2, r.stderr
    assert said in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Warning" not in r.stderr
    assert not out.exists()
