"""The halves check of a firmware-space fit (trimag.vehicle._firmware_halves), on simulated flights with known truth
(tests/vehicle/test_firmware.py's: 2 mGauss of noise, 0.5/1 deg attitude errors, vector residual)."""

from __future__ import annotations

import numpy as np
import pytest
from test_firmware import simulate

from trimag.errors import IdentifiabilityError
from trimag.models.firmware import ArduPilotCompass
from trimag.vehicle._firmware_halves import firmware_rms
from trimag.vehicle.firmware import KeepTheLogs, fit_firmware

TRUTH = ArduPilotCompass(orientation=0, offsets=[120.0, -80.0, 40.0], scale=1.0, diagonal=[1.02, 0.97, 1.01],
                         offdiagonal=[0.02, -0.01, 0.03])


def _handled(n: int = 1200, seed: int = 21) -> tuple[np.ndarray, np.ndarray]:
    """Raw readings with 60 mG more hard iron in the first half (the vehicle handled beside iron); the true
    calibration is the one in force."""
    raw, h, _ = simulate(TRUTH, n, seed)
    raw[: n // 2] += [60.0, -40.0, 50.0]
    return raw, h


def test_a_hard_iron_only_in_the_first_half_is_refused_under_auto_and_a_warning_for_a_level_asked_for():
    raw, h = _handled()
    with pytest.raises(KeepTheLogs, match="keep the log's calibration") as info:
        fit_firmware("ardupilot", raw, field_body=h, held=TRUTH, applied_orientation=0)
    assert isinstance(info.value, IdentifiabilityError) and "changed between the halves" in str(info.value)
    fit = fit_firmware("ardupilot", raw, field_body=h, held=TRUTH, applied_orientation=0, level="offsets",
                       motor="none")
    assert fit.halves is not None and fit.halves["refuse"] and fit.halves["worse_than_log"] == ["second"]
    assert any(m.startswith("warning: refitted on each half") for m in fit.messages)
    second = fit.halves["second"]  # the first half's offsets on the second half: the 60 mG iron it saw
    assert second["rms_other_half_fit"] > 10 * second["rms_log"]


def test_the_halves_are_judged_through_the_firmwares_formula_as_the_fit_is():
    """The log's calibration and the fit through ArduPilot's correct_field give the fit's own RMS before and after."""
    raw, h, _ = simulate(TRUTH, 1200, seed=22)
    held = ArduPilotCompass(orientation=0)
    fit = fit_firmware("ardupilot", raw, field_body=h, held=held, applied_orientation=0, motor="none")
    assert firmware_rms(held, raw, h, {}, None) == pytest.approx(fit.rms_before, rel=1e-9)
    assert firmware_rms(fit.compass, raw, h, {}, None) == pytest.approx(fit.rms_after, rel=1e-6)
    assert fit.halves is not None and not fit.halves["flagged"]
    for half in ("first", "second"):
        assert fit.halves[half]["rms_other_half_fit"] < 1.2 * fit.halves[half]["rms_whole_fit"]
