"""The rest of the adversarial findings: each one line on stderr and the right exit code (issue 33, item 7)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag.cli import main

from _helpers import simulate_ellipsoid

CALIBRATIONS = Path(__file__).parent / "data" / "calibrations"


def _log(path: Path, n: int = 600, scale: float = 1.0) -> Path:
    np.savetxt(path, simulate_ellipsoid(n, noise=20.0, seed=5) * scale, delimiter=",", header="x,y,z", comments="",
               fmt="%.3f")
    return path


def _one_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err and "internal error" not in err, err
    return lines[0]


def test_a_wild_row_is_dropped_counted_and_named_and_the_fit_is_good(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """One row 1000x the others gave "condition number inf" and advice to turn the sensor (exit 3)."""
    raw = simulate_ellipsoid(600, noise=20.0, seed=5)
    raw[123] *= 1000.0
    path = tmp_path / "wild.csv"
    np.savetxt(path, raw, delimiter=",", header="x,y,z", comments="", fmt="%.3f")
    assert main(["fit", str(path), "--json"]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert summary["n_dropped"] == 1 and summary["n_wild"] == 1 and summary["n_used"] == 599
    assert summary["rms_after"] < 40.0
    assert "data row 123" in captured.err and "median" in captured.err


def test_a_reference_far_from_the_data_is_refused_even_inside_the_earth_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Data of median |B| 48 000 nT with --reference 331000: 6.9x below the reference, accepted because 48 000 nT is
    a plausible Earth field. Raw magnitudes are never that far below the field: the reference makes it certain."""
    path = _log(tmp_path / "log.csv")
    for units in ([], ["--units", "nT"]):
        assert main(["fit", str(path), "--reference", "331000", *units, "-q"]) == 2
        line = _one_line(capsys)
        assert "331000" in line and "reference" in line
    assert main(["fit", str(path), "--reference", "48000", "-q"]) == 0


@pytest.mark.parametrize("kind", ["json-array", "json-object", "toml"])
def test_deeply_nested_files_are_input_errors(kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A calibration, parameter, option or policy file nested 100 000 deep exited 1 (RecursionError)."""
    log = _log(tmp_path / "log.csv")
    n = 100_000
    deep = tmp_path / "deep"
    if kind == "toml":
        deep.write_text("[limits]\nmax_rms_after = " + "[" * n + "]" * n + "\n", encoding="utf-8")
        runs = [["fit", str(log), "--policy", str(deep), "-q"]]
    else:
        deep.write_text("[" * n + "]" * n if kind == "json-array" else '{"a":' * n + "1" + "}" * n,
                        encoding="utf-8")
        runs = [["apply", str(deep), str(log), "-o", str(tmp_path / "o.csv")],
                ["export", str(deep), "--to", "json", "-o", str(tmp_path / "e.json")],
                ["evaluate", str(deep), str(log)],
                ["fit", str(log), "--prior", str(deep), "-q"],
                ["simulate", "--model", "ellipsoid", "--params", str(deep), "--n", "10", "-o", str(tmp_path / "s.csv")],
                ["fit", str(log), "--option", "start=" + deep.read_text(encoding="utf-8"), "-q"]]
    for argv in runs:
        assert main(argv) == 2, argv[:2]
        assert "nested" in _one_line(capsys), argv[:2]


def test_a_singular_calibration_file_is_called_singular(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``export`` of a calibration whose matrix has a zero row said "det <= 0 (a reflection)"."""
    data = json.loads((CALIBRATIONS / "ellipsoid.json").read_text())
    data["matrix"] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]
    cal = tmp_path / "singular.json"
    cal.write_text(json.dumps(data))
    for argv in (["export", str(cal), "--to", "json", "-o", str(tmp_path / "e.json")],
                 ["apply", str(cal), str(_log(tmp_path / "log.csv")), "-o", str(tmp_path / "o.csv")]):
        assert main(argv) == 2
        line = _one_line(capsys)
        assert "singular" in line and "reflection" not in line
