"""Joint fit of the fluxgate (interference12, with eddy-current terms) and a compensated scalar magnetometer
(issue 21, item 5; :mod:`trimag.vehicle.joint`). Simulated calibration boxes at 10 Hz whose INS attitudes carry errors:
the magnitude rows, which need no attitudes, must cut the held-out magnitude error of the vector-only fit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import trimag
from trimag.errors import TrimagInputError
from trimag.estimators.tolles_lawson import fit_tolles_lawson
from trimag.simulate import simulate_aircraft
from trimag.vehicle.eddy import EDDY_NAMES, eddy_values, free_mask
from trimag.vehicle.joint import fit_joint_scalar
from trimag.vehicle.regressors import fit_regressors

from _helpers import run_trimag

K_TRUE = np.eye(3) + np.array([[0.02, 0.01, -0.005], [0.0, -0.01, 0.008], [0.004, 0.0, 0.015]])
C_TRUE = np.array([300.0, -150.0, 80.0])
E_TRUE = np.array([[-0.05, 0.01, 0.0], [0.0, -0.03, 0.02], [0.01, 0.0, -0.04]])
EARTH = np.array([18_000.0, 1_000.0, 46_000.0])


def _box(seed: int, att_noise_deg: float = 0.05, E: np.ndarray | None = E_TRUE, drift: bool = True):
    """A box whose INS attitudes err by white noise of ``att_noise_deg`` per axis (plus, with ``drift``, a random
    walk scaled to the same RMS: the correlated error of a real INS)."""
    sim = simulate_aircraft(40.0, vector_K=K_TRUE, vector_c=C_TRUE, vector_E=E, vector_noise_nT=0.5,
                            earth_ned_nT=EARTH, seed=seed)
    rng = np.random.default_rng(100 + seed)
    error = rng.normal(scale=att_noise_deg, size=sim.attitude_deg.shape)
    if drift:
        walk = np.cumsum(rng.normal(size=error.shape), axis=0)
        error += (walk - walk.mean(axis=0)) * att_noise_deg / walk.std()
    ins = Rotation.from_euler("ZYX", sim.attitude_deg + error, degrees=True)
    values, _, _ = eddy_values(sim.vector_nT, time_s=sim.time_s)
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=sim.rate_hz, segments=sim.segments, bootstrap=0)
    return sim, ins, values, np.asarray(comp.apply(sim.vector_nT, sim.scalar_nT)) - sim.geology_nT


def _magnitude_error(cal: trimag.Calibration, sim, values) -> float:
    H = cal.apply(sim.vector_nT, regressors=values)
    return float(np.sqrt(np.mean((np.linalg.norm(H, axis=1) - np.linalg.norm(sim.body_nT, axis=1)) ** 2)))


def test_joint_fit_cuts_the_held_out_magnitude_error() -> None:
    sim, ins, values, S = _box(0)
    test, _, values_t, _ = _box(1)
    base = trimag.fit(sim.vector_nT, model="interference12", reference=EARTH, attitude=ins, units="nT")
    vector = fit_regressors(base, sim.vector_nT, values, attitude=ins, free=free_mask(9))
    joint = fit_joint_scalar(vector, sim.vector_nT, S, attitude=ins, background=EARTH, regressors=values)
    before, after = _magnitude_error(vector, test, values_t), _magnitude_error(joint, test, values_t)
    assert after < 0.4 * before and after < 3.0, (before, after)
    info = joint.diagnostics["joint_scalar"]
    assert info["scalar_rms_after"] < info["vector_only"]["scalar_rms_after"]
    assert joint.regressors["names"] == list(EDDY_NAMES) and joint.regressors["means"] == vector.regressors["means"]
    # the eddy matrix is kept (not traded away for the magnitude)
    coef = np.asarray(joint.regressors["coefficients"])
    np.testing.assert_allclose(coef, E_TRUE.T, atol=2e-3)


def test_joint_fit_without_regressor_terms_recovers_K_within_its_sigmas() -> None:
    sim, ins, _, S = _box(2, att_noise_deg=0.02, E=None, drift=False)
    base = trimag.fit(sim.vector_nT, model="interference12", reference=EARTH, attitude=ins, units="nT")
    joint = fit_joint_scalar(base, sim.vector_nT, S, attitude=ins, background=EARTH)
    std = joint.uncertainty["param_std"]
    K = np.linalg.inv(joint.matrix)
    z = [(K[i, j] - K_TRUE[i, j]) / std[f"k{i + 1}{j + 1}"] for i in range(3) for j in range(3)]
    assert np.max(np.abs(z)) < 5.0, z
    assert joint.regressors is None


@pytest.mark.filterwarnings("ignore::trimag.errors.IdentifiabilityWarning")
def test_refusals() -> None:
    sim, ins, values, S = _box(3, E=None)
    base = trimag.fit(sim.vector_nT, model="interference12", reference=EARTH, attitude=ins, units="nT")
    with pytest.raises(TrimagInputError, match="one finite value per sample"):
        fit_joint_scalar(base, sim.vector_nT, S[:-1], attitude=ins, background=EARTH)
    with pytest.raises(TrimagInputError, match="attitude of every sample"):
        fit_joint_scalar(base, sim.vector_nT, S, attitude=None, background=EARTH)
    ell = trimag.fit(sim.vector_nT, units="nT")
    with pytest.raises(TrimagInputError, match="refines an interference12"):
        fit_joint_scalar(ell, sim.vector_nT, S, attitude=ins, background=EARTH)
    eddy = fit_regressors(base, sim.vector_nT, values, attitude=ins)
    with pytest.raises(TrimagInputError, match="give the values of the regressors"):
        fit_joint_scalar(eddy, sim.vector_nT, S, attitude=ins, background=EARTH)
    # a scalar column in another unit (uT against nT) was fitted silently, mis-weighted
    with pytest.raises(TrimagInputError, match="not in the vector data's unit"):
        fit_joint_scalar(base, sim.vector_nT, S / 1000.0, attitude=ins, background=EARTH)


def test_cli_reference_column_with_the_vector_model_fits_jointly(tmp_path: Path) -> None:
    sim, ins, _, S = _box(4)
    ypr = ins.as_euler("ZYX", degrees=True)
    data = tmp_path / "box.csv"
    pd.DataFrame({"t": sim.time_s, "x": sim.vector_nT[:, 0], "y": sim.vector_nT[:, 1], "z": sim.vector_nT[:, 2],
                  "yaw": ypr[:, 0], "pitch": ypr[:, 1], "roll": ypr[:, 2], "S": S}).to_csv(data, index=False)
    args = ("--model", "interference12", "--columns", "x,y,z", "--attitude-columns", "yaw,pitch,roll",
            "--background-ned", "18000,1000,46000", "--units", "nT", "--option", "eddy=9", "--time-column", "t")
    proc = run_trimag("fit", data, *args, "--reference-column", "S", "-o", tmp_path / "joint.json")
    assert proc.returncode == 0, proc.stderr
    assert "joint fit with the scalar magnetometer S" in proc.stdout
    d = json.loads((tmp_path / "joint.json").read_text())
    assert d["diagnostics"]["joint_scalar"]["scalar"] == "column S"
    proc = run_trimag("apply", tmp_path / "joint.json", data, "--columns", "x,y,z", "-o", tmp_path / "out.csv")
    assert proc.returncode == 0, proc.stderr
    out = pd.read_csv(tmp_path / "out.csv")[["x_cal", "y_cal", "z_cal"]].to_numpy()
    assert np.sqrt(np.mean((np.linalg.norm(out, axis=1) - np.linalg.norm(sim.body_nT, axis=1)) ** 2)) < 3.0


def test_uncertainty_has_the_fields_of_every_estimator() -> None:
    from trimag.calibration import UNCERTAINTY_FIELDS

    sim, ins, _, S = _box(3, att_noise_deg=0.02, E=None, drift=False)
    base = trimag.fit(sim.vector_nT, model="interference12", reference=EARTH, attitude=ins, units="nT")
    joint = fit_joint_scalar(base, sim.vector_nT, S, attitude=ins, background=EARTH)
    assert set(UNCERTAINTY_FIELDS) <= set(joint.uncertainty)
