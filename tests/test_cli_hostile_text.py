"""Text from input files reaches the terminal escaped (issue 41, item 13): a calibration file or a CSV header with
terminal escape sequences (ESC [ ... , a bell, a carriage return, a C1 control) was printed raw, so a file could
rewrite the terminal's title, hide a warning or fake a line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag import Calibration
from trimag.cli import main

from _helpers import simulate_ellipsoid

HOSTILE = "\x1b]0;pwned\x07\x1b[2J\r\x9b31m"


def _assert_no_control(text: str) -> None:
    bad = [c for c in text if (ord(c) < 32 and c not in "\n\t") or 0x7F <= ord(c) <= 0x9F]
    assert bad == [], repr(text)


def test_a_csv_header_s_escape_bytes_are_printed_escaped(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "lab.csv"
    raw = simulate_ellipsoid(300, noise=20.0, seed=7)
    np.savetxt(data, raw, delimiter=",", header=f"x{HOSTILE},y,z", comments="", fmt="%.3f")
    code = main(["fit", str(data), "--columns", "q,y,z"])  # an unknown column: the header's names are listed
    out, err = capsys.readouterr()
    assert code == 2
    _assert_no_control(out + err)
    assert "\\x9b" in err  # said, escaped


def test_a_calibration_file_s_escape_bytes_are_printed_escaped(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    data = json.loads(Calibration.from_matrix_offset(np.eye(3), [100.0, 20.0, -30.0], units="mG").to_json())
    data["model"] = f"affine{HOSTILE}"
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(data))
    assert main(["export", str(path), "--to", "ardupilot", "-o", str(tmp_path / "a.param")]) == 2
    out, err = capsys.readouterr()
    _assert_no_control(out + err)
    data["model"], data["method"] = "affine", f"given{HOSTILE}"
    path.write_text(json.dumps(data))
    log = tmp_path / "lab.csv"
    np.savetxt(log, simulate_ellipsoid(300, noise=20.0, seed=7) / 100, delimiter=",", header="x,y,z", comments="",
               fmt="%.3f")
    main(["fit", str(log), "--units", "mG", "--prior", str(path), "-o", str(tmp_path / "new.json")])
    out, err = capsys.readouterr()
    _assert_no_control(out + err)
