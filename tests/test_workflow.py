"""File-level workflow (behind the CLI): rows without attitude are dropped and counted, not lost silently."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from trimag.workflow import fit_file, simulate_to_file


def test_interference12_rows_without_attitude_are_counted(tmp_path: Path) -> None:
    K = np.eye(3) + np.array([[0.05, 0.01, -0.02], [0.0, -0.03, 0.02], [0.01, 0.0, 0.04]])
    params = {f"k{i + 1}{j + 1}": float(K[i, j]) for i in range(3) for j in range(3)}
    params.update({"c1": 300.0, "c2": -150.0, "c3": 80.0})
    (tmp_path / "p.json").write_text(json.dumps(params))
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
