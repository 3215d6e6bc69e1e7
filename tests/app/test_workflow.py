"""File-level workflow (behind the CLI): rows without attitude are dropped and counted, not lost silently."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from trimag.app import fit_file, simulate_to_file


def _write_interference12_params(path: Path) -> None:
    """Soft iron K (near identity) and hard iron (300, -150, 80) nT of an interference12 sensor, as JSON."""
    K = np.eye(3) + np.array([[0.05, 0.01, -0.02], [0.0, -0.03, 0.02], [0.01, 0.0, 0.04]])
    params = {f"k{i + 1}{j + 1}": float(K[i, j]) for i in range(3) for j in range(3)}
    params.update({"c1": 300.0, "c2": -150.0, "c3": 80.0})
    path.write_text(json.dumps(params))


def test_interference12_rows_without_attitude_are_counted(tmp_path: Path) -> None:
    _write_interference12_params(tmp_path / "p.json")
    simulate_to_file(model="interference12", params_path=tmp_path / "p.json", n=60, noise=0.0,
                     out=tmp_path / "sim.csv", field=48000.0, seed=2)
    df = pd.read_csv(tmp_path / "sim.csv")
    df.loc[[3, 17], "qw"] = np.nan
    df.to_csv(tmp_path / "gaps.csv", index=False)
    result = fit_file(tmp_path / "gaps.csv", model="interference12", units="nT",
                      quaternion_columns="qw,qx,qy,qz", background_ned="48000,0,0")
    assert result.summary["n_used"] == 58 and result.summary["n_dropped"] == 2
    assert any("dropped 2 rows whose attitude" in m for m in result.messages)
    np.testing.assert_allclose(result.calibration.offset, [300.0, -150.0, 80.0], atol=1e-6)


def test_export_and_simulate_take_one_request(tmp_path: Path, capsys) -> None:
    """export_to_file and simulate_to_file take a typed request (what the CLI builds from its flags) or its fields;
    ``trimag export --json`` prints exactly what export_to_file returns."""
    import pytest

    from trimag.app import export_to_file
    from trimag.app.requests import ExportRequest, SimulateRequest
    from trimag.cli import main
    from trimag.errors import TrimagInputError

    W = np.eye(3) + np.array([[0.05, 0.01, 0.0], [0.01, -0.03, 0.02], [0.0, 0.02, 0.04]])
    params = {f"w{i + 1}{j + 1}": float(W[i, j]) for i in range(3) for j in range(3)}
    params.update({"hard_iron_x": 0.1, "hard_iron_y": -0.2, "hard_iron_z": 0.05})
    (tmp_path / "p.json").write_text(json.dumps(params))
    req = SimulateRequest("ellipsoid", tmp_path / "p.json", n=300, out=tmp_path / "sim.csv", noise=1e-3, seed=4)
    assert simulate_to_file(req)["n"] == 300
    first = (tmp_path / "sim.csv").read_bytes()
    simulate_to_file(model="ellipsoid", params_path=tmp_path / "p.json", n=300, out=tmp_path / "sim.csv",
                     noise=1e-3, seed=4)
    assert (tmp_path / "sim.csv").read_bytes() == first
    with pytest.raises(TrimagInputError, match="not both"):
        simulate_to_file(req, seed=5)
    fit_file(tmp_path / "sim.csv", units="uT", out=tmp_path / "cal.json")
    r = export_to_file(ExportRequest(tmp_path / "cal.json", "ardupilot", tmp_path / "a.parm", instance=2))
    assert r["target"] == "ardupilot" and r["out"] == str(tmp_path / "a.parm")
    assert any(k.startswith("COMPASS_OFS2") for k in r["parameters"])
    assert main(["export", str(tmp_path / "cal.json"), "--to", "ardupilot", "--instance", "2", "-o",
                 str(tmp_path / "a.parm"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(json.dumps(r))


def test_vector_evaluation_takes_one_request_and_refuses_a_background_run(tmp_path: Path) -> None:
    """evaluate_vector_file takes an EvaluateRequest (or its fields): the same errors either way; a background run
    (a fitting input, no `trimag evaluate` flag) is refused in one line instead of being read without attitudes."""
    import pytest

    from trimag.app import evaluate_vector_file
    from trimag.app.requests import AttitudeSpec, EvaluateRequest, InputSpec, ReferenceSpec
    from trimag.errors import TrimagInputError

    _write_interference12_params(tmp_path / "p.json")
    simulate_to_file(model="interference12", params_path=tmp_path / "p.json", n=80, noise=1.0,
                     out=tmp_path / "sim.csv", field=48000.0, seed=3)
    fit_file(tmp_path / "sim.csv", model="interference12", units="nT", quaternion_columns="qw,qx,qy,qz",
             background_ned="48000,0,0", out=tmp_path / "cal.json")
    req = EvaluateRequest(tmp_path / "cal.json", InputSpec(tmp_path / "sim.csv"),
                          reference=ReferenceSpec(background_ned="48000,0,0"),
                          attitude=AttitudeSpec(quaternion_columns="qw,qx,qy,qz"))
    typed = evaluate_vector_file(req)
    flat = evaluate_vector_file(tmp_path / "cal.json", tmp_path / "sim.csv", background_ned="48000,0,0",
                                quaternion_columns="qw,qx,qy,qz")
    assert typed == flat and typed["n_used"] == 80 and typed["rms_after"] < 0.1 * typed["rms_before"]
    with pytest.raises(TrimagInputError, match="`background_run` is for fitting"):
        evaluate_vector_file(tmp_path / "cal.json", tmp_path / "sim.csv", background_run=str(tmp_path / "sim.csv"),
                             quaternion_columns="qw,qx,qy,qz")
