"""A condition number said in the user's words (issue 42, item 6): `live --replay` of a log still quoted "condition
number 4.7e+17" (ardusub_small.tlog's compass 2), as did `fit` of a table that turned about one axis only, and the
warning of a weakly identified fit. The message names what the data do not determine (the x offset, the vertical
scale) and what to record; the number itself is a detail of the refusal (printed indented under it)."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

import trimag
from trimag.cli import main
from trimag.errors import IdentifiabilityError, IdentifiabilityWarning

_NUMBER = re.compile(r"condition number|\de\+1\d")  # (4.7e+17; a replay rate of 1e+06 is no condition number)


PX4 = Path(__file__).resolve().parents[1] / "data" / "logs" / "px4tools_01_07_59.px4log"  # barely turned


def _compass(number: str) -> np.ndarray:
    """The bundled PX4 log's compass ``number`` (G): compass 2 gave "condition number 5.08e+15" (refused), compass 1
    warned "condition number 4.15e+05"."""
    from trimag.io import read_samples

    return read_samples(PX4, sensor=number).field


def test_a_refusal_names_what_is_not_determined_not_a_condition_number() -> None:
    with pytest.raises(IdentifiabilityError) as info:
        trimag.fit(_compass("2"), units="G")
    said = str(info.value)
    assert not _NUMBER.search(said), said
    assert "the x offset" in said and "the vertical (z) offset" in said and "the vertical (z) scale" in said, said
    assert "record" in said
    assert any("condition number" in d for d in info.value.details)  # kept for whoever wants it


def test_a_weak_fit_warns_in_words() -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trimag.fit(_compass("1"), units="G")
    said = [str(w.message) for w in caught if issubclass(w.category, IdentifiabilityWarning)]
    assert said and not any(_NUMBER.search(s) for s in said), said
    assert any("the vertical (z) scale" in s for s in said), said


def test_live_replay_says_it_in_words(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "compass2.csv"
    np.savetxt(data, _compass("2"), delimiter=",", header="x,y,z", comments="")
    code = main(["live", "--replay", str(data), "--units", "G", "--rate", "1e6", "--exit-at-end", "--no-browser",
                 "--port", "0", "-o", str(tmp_path / "cal.json"), "--json"])
    captured = capsys.readouterr()
    assert code == 3
    state = json.loads(captured.out)
    assert state["fit_message"] and not _NUMBER.search(state["fit_message"]), state["fit_message"]
    assert not _NUMBER.search(captured.err), captured.err
    assert "offset" in state["fit_message"]
