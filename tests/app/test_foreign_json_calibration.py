"""Issue 41, item 17: `trimag export settings.json` (a JSON file that is not a calibration: an app's settings) said
"make one with `trimag fit settings.json -o cal.json`", fitting the settings. Now it says the file is not a
calibration and what export takes, as apply, evaluate and `fit --prior` say it is not one, never to fit it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import refusal, run_trimag, simulate_ellipsoid


@pytest.mark.parametrize("command", ["export", "apply", "evaluate", "prior"])
def test_a_json_that_is_not_a_calibration_is_named_so(command: str, tmp_path: Path) -> None:
    (tmp_path / "settings.json").write_text('{"port": 8765, "theme": "dark"}')
    np.savetxt(tmp_path / "log.csv", simulate_ellipsoid(200, noise=20.0), delimiter=",", header="x,y,z",
               comments="")
    args = {"export": ("export", "settings.json", "--to", "ardupilot", "-o", "out.param"),
            "apply": ("apply", "settings.json", "log.csv", "-o", "out.csv"),
            "evaluate": ("evaluate", "settings.json", "log.csv"),
            "prior": ("fit", "log.csv", "--prior", "settings.json", "-o", "out.json")}[command]
    r = run_trimag(*args, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    verdict, _ = refusal(r.stderr)
    assert ("settings.json" in verdict and "not a trimag calibration" in verdict) or \
        ("settings.json is not a calibration file" in verdict and "trimag fit LOG -o cal.json" in verdict), verdict
    assert "fit settings.json" not in verdict, verdict
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.csv", "settings.json"]
