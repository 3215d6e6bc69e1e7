"""A long log's levels are compared on evenly spread samples, and only the chosen level is fitted and judged on every
sample (issue 40 item 3: a 5 h log at 10 Hz has 180 000 compass samples and 12 candidate levels with 5 folds each).

The threshold is lowered here (``LEVEL_CHOICE_MAX_ROWS``) so that the project's simulated flight (2 500 samples)
takes that path in-process: the choice is said, the chosen level's figures and parameters are those of every sample
(the same as a fit of that level alone on every sample), and the other levels' rows are the subsample's.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
from pathlib import Path

import numpy as np
import pytest

TESTS_DIR = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS_DIR / "app"))
pytest.importorskip("pymavlink")

from test_firmware_fit import _write_log  # noqa: E402

from trimag import cli  # noqa: E402
from trimag.vehicle import firmware  # noqa: E402


def _fit(log: Path, *args: str) -> tuple[int, str, dict]:
    """``(exit code, what the command said, its --json document)``."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(["fit", str(log), "--target", "ardupilot", "--json", *args])
    text = out.getvalue()
    return code, err.getvalue() + text[:text.index("{")], json.loads(text[text.index("{"):])


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_log(tmp_path_factory.mktemp("long") / "flight.bin")


def test_a_long_log_compares_levels_on_spread_samples_and_fits_the_chosen_one_on_all(
        flight: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    code, said, whole = _fit(flight)
    assert code == 0 and "levels compared" not in said
    monkeypatch.setattr(firmware, "LEVEL_CHOICE_MAX_ROWS", 600)
    code, said, spread = _fit(flight)
    assert code == 0
    n = whole["n_used"]
    assert f"levels compared on every 5th sample ({len(range(0, n, 5))} of {n}" in said, said
    assert f"the chosen level fitted and judged on all {n}" in said, said
    rows = spread["diagnostics"]["firmware"]["levels"]
    chosen = next(r for r in rows if r["chosen"])
    chosen_whole = next(r for r in whole["diagnostics"]["firmware"]["levels"] if r["chosen"])
    assert (chosen["level"], chosen["motor"]) == (chosen_whole["level"], chosen_whole["motor"])
    assert chosen["rows"] == n
    np.testing.assert_allclose(chosen["heldout_rms"], chosen_whole["heldout_rms"], rtol=1e-6)
    a, b = spread["params"], whole["params"]
    assert a.keys() == b.keys()
    np.testing.assert_allclose([a[k] for k in a], [b[k] for k in a], rtol=1e-6, atol=1e-6)
    others = [r for r in rows if not r["chosen"]]
    assert others and all("rows" not in r for r in others)  # the subsample's figures
