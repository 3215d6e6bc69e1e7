"""A background that changes across the room (issue 31, item 4): paper C's model with the background's gradient
fitted from positions (:mod:`trimag.vehicle.gradient`), on simulated lab recordings with known truth
(:func:`trimag.simulate.simulate_room`: 50 Hz, 20 nT noise per axis, the sensor carried within 0.4 m, a gradient
changing the field by a few thousand nT over the reach)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import trimag
from trimag import Calibration
from trimag.errors import IdentifiabilityError, IdentifiabilityWarning, TrimagInputError
from trimag.simulate import simulate_room
from trimag.vehicle.gradient import GRADIENT_TERMS, background_at, fit_background_gradient, gradient_tensor

from _helpers import run_trimag


def _base(sim, fitted: bool) -> Calibration:
    """The fit without the gradient: the background (at the mean position) fitted, or given."""
    H_mean = sim.background + sim.positions.mean(axis=0) @ sim.gradient.T
    if fitted:
        return trimag.fit(sim.raw, model="interference12", attitude=sim.attitude, units="nT",
                          reference=float(np.linalg.norm(H_mean)), estimate_background=True)
    return trimag.fit(sim.raw, model="interference12", attitude=sim.attitude, units="nT", reference=H_mean)


def _truth_terms(sim) -> np.ndarray:
    G = sim.gradient
    return np.array([G[0, 0], G[0, 1], G[0, 2], G[1, 1], G[1, 2]])


def test_tensor_is_symmetric_and_traceless():
    G = gradient_tensor([1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_allclose(G, G.T)
    assert np.trace(G) == 0.0


@pytest.mark.parametrize("fitted", [False, True])
def test_terms_recovered_within_their_sigmas(fitted):
    """Over 8 recordings: every term within 3.5 sigma, the z-scores' standard deviation within 0.6..1.4, and the
    vector residual at the noise floor (20 sqrt(3) = 34.6 nT) where the fit without the gradient leaves ~1300."""
    z = []
    for seed in range(8):
        sim = simulate_room(3000, seed)
        base = _base(sim, fitted)
        cal = fit_background_gradient(base, sim.raw, sim.attitude, sim.positions)
        g = cal.diagnostics["background_gradient"]
        got = np.array([g["terms"][k] for k in GRADIENT_TERMS])
        std = np.array([g["terms_std"][k] for k in GRADIENT_TERMS])
        z.append((got - _truth_terms(sim)) / std)
        assert g["vector_rms_with"] < 1.05 * 20 * np.sqrt(3) and g["vector_rms_without"] > 10 * g["vector_rms_with"]
        np.testing.assert_allclose(np.linalg.inv(cal.matrix), sim.K, atol=2e-4)
    z = np.concatenate(z)
    assert np.abs(z).max() < 3.5 and 0.6 < z.std() < 1.4, z


def test_background_at_positions():
    sim = simulate_room(2000, 3)
    cal = fit_background_gradient(_base(sim, False), sim.raw, sim.attitude, sim.positions)
    truth = sim.background + sim.positions @ sim.gradient.T
    assert np.abs(background_at(cal, sim.positions) - truth).max() < 5.0  # nT, against thousands of nT of change


def test_refusals():
    sim = simulate_room(500, 1)
    base = _base(sim, False)
    still = np.tile(sim.positions[:1], (len(sim.raw), 1))
    with pytest.raises(IdentifiabilityError, match="cannot identify the background's gradient"):
        fit_background_gradient(base, sim.raw, sim.attitude, still)
    with pytest.raises(TrimagInputError, match="positions must be"):
        fit_background_gradient(base, sim.raw, sim.attitude, sim.positions[:, :2])
    with pytest.warns(IdentifiabilityWarning):  # (a short tumble: the magnitude-only fit warns; not the point here)
        ml = trimag.fit(sim.raw, units="nT")
    with pytest.raises(TrimagInputError, match="interference12"):
        fit_background_gradient(ml, sim.raw, sim.attitude, sim.positions)


def _write(d: Path, name: str, sim) -> dict[str, Path]:
    q = sim.attitude.as_quat(scalar_first=True)
    pd.DataFrame({"t_att": sim.time_s, "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
                  "px": sim.positions[:, 0], "py": sim.positions[:, 1], "pz": sim.positions[:, 2]}).to_csv(
        d / f"{name}_att.csv", index=False)
    pd.DataFrame({"time": sim.time_s, "x": sim.raw[:, 0], "y": sim.raw[:, 1], "z": sim.raw[:, 2]}).to_csv(
        d / f"{name}_mag.csv", index=False)
    return {"mag": d / f"{name}_mag.csv", "att": d / f"{name}_att.csv"}


def test_cli_lab_commands_with_positions(tmp_path):
    """The lab user's two commands with the positions in the motion-capture file: the fit takes them from there,
    evaluate uses the stored position columns by default, and the held-out angular error drops to the noise."""
    fit_files = _write(tmp_path, "fit", simulate_room(3000, 11))
    held = simulate_room(3000, 12)
    held_files = _write(tmp_path, "held", held)

    def sync(files):
        return ["--attitude-file", files["att"], "--quaternion-columns", "qw,qx,qy,qz", "--time-column", "time",
                "--attitude-time-column", "t_att"]

    out = tmp_path / "cal.json"
    proc = run_trimag("fit", fit_files["mag"], "--units", "nT", "--model", "interference12", *sync(fit_files),
                      "--option", "estimate_background=true", "--position-columns", "px,py,pz", "-o", out)
    assert proc.returncode == 0, proc.stderr
    assert "background gradient (nT/m)" in proc.stdout
    plain = tmp_path / "plain.json"
    assert run_trimag("fit", fit_files["mag"], "--units", "nT", "--model", "interference12", *sync(fit_files),
                      "--option", "estimate_background=true", "-o", plain).returncode == 0
    errors = {}
    for name, cal in (("gradient", out), ("plain", plain)):
        proc = run_trimag("evaluate", cal, held_files["mag"], *sync(held_files), "--json")
        assert proc.returncode == 0, proc.stderr
        errors[name] = json.loads(proc.stdout)["angular_error_rms_deg"]
    assert errors["gradient"] < 0.05 < errors["plain"], errors  # the noise: 20 nT / 49 889 nT = 0.023 deg per axis
