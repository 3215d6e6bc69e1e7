"""Tolles–Lawson's seams between commands (issue 39, item 9): `export` of a compensation file and `fit` of one point
to the commands that take it (apply, evaluate), never at each other; `fit --model tolles-lawson --report` is refused
in one line before any work (it drew nothing and said nothing)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from trimag.cli import main
from trimag.simulate import simulate_aircraft


@pytest.fixture(scope="module")
def box(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("tl")
    sim = simulate_aircraft(60.0, seed=0, terms="p,i5,e8")
    path = d / "box.csv"
    np.savetxt(path, np.column_stack([sim.time_s, sim.vector_nT, sim.scalar_nT]), delimiter=",",
               header="time,fx,fy,fz,mag", comments="", fmt="%.6f")
    return path


def _fit(box: Path, *more: str) -> int:
    return main(["fit", str(box), "--model", "tolles-lawson", "--columns", "fx,fy,fz", "--scalar-column", "mag",
                 "--time-column", "time", "--option", "terms=p,i5,e8", "-q", *more])


def _one_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_export_and_fit_of_a_compensation_point_to_apply_and_evaluate(box: Path, tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    comp = tmp_path / "tl.json"
    assert _fit(box, "-o", str(comp)) == 0
    capsys.readouterr()
    assert main(["export", str(comp), "--to", "ardupilot", "-o", str(tmp_path / "x.param")]) == 2
    export_says = _one_line(capsys)
    assert "trimag fit" not in export_says and "Tolles-Lawson" in export_says
    assert "trimag apply" in export_says and "trimag evaluate" in export_says
    assert not (tmp_path / "x.param").exists()
    assert main(["fit", str(comp)]) == 2
    fit_says = _one_line(capsys)
    assert "trimag export" not in fit_says and "trimag apply" in fit_says and "trimag evaluate" in fit_says


def test_a_report_of_a_tolles_lawson_fit_is_refused_before_any_work(box: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    report, comp = tmp_path / "tl.png", tmp_path / "tl.json"
    assert _fit(box, "--report", str(report), "-o", str(comp)) == 2
    line = _one_line(capsys)
    assert "--report" in line and "tolles-lawson" in line
    assert not report.exists() and not comp.exists()
    for flag in (["--igrf", "52.5,13.3,40,2024-01-01"], ["--target", "ardupilot"], ["--rows", "0:100"]):
        assert _fit(box, *flag) == 2
        assert flag[0] in _one_line(capsys)
