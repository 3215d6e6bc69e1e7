"""Issue 41, item 17: a CSV whose only non-UTF-8 byte is in its header (a spreadsheet's Latin-1 "xé" or "µT") was
fitted by ``fit`` and refused by ``apply`` and ``evaluate`` (each reader skipped the header its own way). One rule
now for all three: the header and any preamble are UTF-8 text like the rows, else one line naming the byte, exit 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import refusal, run_trimag, simulate_ellipsoid


@pytest.mark.parametrize("head", [b"x\xe9,y,z\n", b"Bx [\xb5T],By,Bz\n", b"sensor: caf\xe9\nx,y,z\n"],
                         ids=["header", "unit", "preamble"])
@pytest.mark.parametrize("command", ["fit", "apply", "evaluate"])
def test_a_header_that_is_not_utf8_is_refused_alike(command: str, head: bytes, tmp_path: Path) -> None:
    good = tmp_path / "good.csv"
    np.savetxt(good, simulate_ellipsoid(300, noise=20.0), delimiter=",", header="x,y,z", comments="")
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", good, "--units", "nT", "-o", cal).returncode == 0
    latin = tmp_path / "latin.csv"
    latin.write_bytes(head + good.read_bytes().split(b"\n", 1)[1])
    out = "out.json" if command == "fit" else "out.csv"
    args = {"fit": ("fit", "latin.csv", "--units", "nT", "-o", out), "evaluate": ("evaluate", "cal.json", "latin.csv"),
            "apply": ("apply", "cal.json", "latin.csv", "-o", out)}[command]
    r = run_trimag(*args, cwd=tmp_path)
    assert r.returncode == 2, (r.returncode, r.stderr)
    verdict, _ = refusal(r.stderr)
    assert "not UTF-8 text (byte 0x" in verdict and "latin.csv" in verdict, verdict
    assert not (tmp_path / out).exists()
