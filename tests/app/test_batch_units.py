"""``trimag batch``'s summary says each row's unit (issue 39, item 8: rows in counts, G and unknown side by side with
no unit column)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from trimag.cli import main

from _helpers import simulate_ellipsoid


def test_the_batch_summary_has_each_files_unit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "fleet"
    d.mkdir()
    for name, header, scale in (("a_plain.csv", "x,y,z", 1.0), ("b_gauss.csv", "x_G,y_G,z_G", 1e-5),
                                ("c_micro.csv", "mag_x_uT,mag_y_uT,mag_z_uT", 1e-3)):
        np.savetxt(d / name, simulate_ellipsoid(400, noise=20.0, seed=4) * scale, delimiter=",", header=header,
                   comments="", fmt="%.8g")
    out = tmp_path / "out"
    assert main(["batch", str(d / "*.csv"), "--out", str(out), "-q"]) == 0
    summary = pd.read_csv(out / "summary.csv", keep_default_na=False)
    assert list(summary["units"]) == ["unknown", "G", "uT"]
    assert list(summary.columns).index("units") == list(summary.columns).index("rms_after") + 1
