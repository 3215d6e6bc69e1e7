"""Findings of issue 22 ("Trust at the data boundary"), each reproduced before its fix."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import trimag

from _helpers import SHARED_DATA, ellipsoid_truth, requires_shared, run_trimag, simulate_ellipsoid


def _cone(n: int, half_deg: float, seed: int = 0, F: float = 50_000.0, noise: float = 5.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(np.cos(np.radians(half_deg)), 1, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z**2)
    u = np.column_stack([s * np.cos(phi), s * np.sin(phi), z])
    W, b = ellipsoid_truth()
    return np.linalg.solve(W, (F * u).T).T + b + rng.normal(scale=noise, size=u.shape)


def test_uncertainty_is_the_same_relative_size_in_nT_and_uT():
    """Finding: every parameter was +-inf in nT, finite for the same data in uT (an unscaled eigenvalue threshold)."""
    raw = _cone(3000, 40.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal_nT = trimag.fit(raw, model="ellipsoid", reference=50_000.0, units="nT")
        cal_uT = trimag.fit(raw / 1000.0, model="ellipsoid", reference=50.0, units="uT")
    s_nT, s_uT = cal_nT.uncertainty["param_std"], cal_uT.uncertainty["param_std"]
    assert s_nT["w11"] is not None and np.isfinite(s_nT["w11"])
    assert s_nT["w11"] == pytest.approx(s_uT["w11"], rel=1e-6)
    assert s_nT["hard_iron_x"] == pytest.approx(1000.0 * s_uT["hard_iron_x"], rel=1e-6)


def test_duplicating_every_row_does_not_shrink_the_sigmas():
    """Finding: duplicating every row shrank every sigma by sqrt(2)."""
    B = simulate_ellipsoid(3000, noise=20.0, seed=1)
    base = trimag.fit(B, model="ellipsoid", units="nT").uncertainty["param_std"]
    for doubled in (np.repeat(B, 2, axis=0), np.vstack([B, B])):
        std = trimag.fit(doubled, model="ellipsoid", units="nT").uncertainty["param_std"]
        assert std["w11"] == pytest.approx(base["w11"], rel=0.05)
        assert std["hard_iron_x"] == pytest.approx(base["hard_iron_x"], rel=0.05)


def test_as_many_samples_as_parameters_reports_unknown_uncertainty():
    """Finding: 9 samples reported c3 = -40719.9 +- 2.89e-09 nT (no degree of freedom left for the noise)."""
    from trimag.calibration import Calibration
    from trimag.quality.honesty import honest_uncertainty

    X = simulate_ellipsoid(9, noise=0.0, seed=2)
    cal = Calibration.from_matrix_offset(np.eye(3), [0, 0, 0], units="nT", model="scalar9",
                                         uncertainty={"param_std": {f"p{k}": 1e-9 for k in range(9)}})
    out = honest_uncertainty(cal, X)
    assert all(v is None for v in out.uncertainty["param_std"].values())
    assert any("no degree of freedom" in w for w in out.diagnostics["warnings"])


def test_correlated_residuals_inflate_and_white_noise_does_not():
    from trimag.quality.honesty import correlation_time

    rng = np.random.default_rng(0)
    white = rng.normal(size=5000)
    assert correlation_time(white) < 1.1
    ar = np.zeros(5000)
    for k in range(1, 5000):  # AR(1), rho = 0.9: tau = (1 + rho) / (1 - rho) = 19
        ar[k] = 0.9 * ar[k - 1] + white[k]
    assert 12 < correlation_time(ar) < 26


def test_a_log_whose_offset_changes_halfway_is_flagged_with_the_size_of_the_change():
    """Finding: the first and second halves of some logs disagree (RMS z up to 31) and nothing says so."""
    B = simulate_ellipsoid(4000, noise=20.0, seed=1)
    stable = trimag.fit(B, model="ellipsoid", units="nT")
    assert stable.diagnostics["drift"]["drift"] is False
    B[2000:] += np.array([150.0, 0.0, 0.0])
    moved = trimag.fit(B, model="ellipsoid", units="nT")
    assert moved.diagnostics["drift"]["drift"] is True
    assert moved.diagnostics["drift"]["offset_change"][0] == pytest.approx(150.0, rel=0.1)
    assert any("changed during the log" in w for w in moved.diagnostics["warnings"])


def _wide_log(path: Path, n: int = 400) -> None:
    """A robot log as the finding's: counters and time stamps before the field, accelerometer columns beside it."""
    rng = np.random.default_rng(0)
    mag = simulate_ellipsoid(n, noise=0.2, seed=3, F=50.0)
    cols = {
        "loop_index": np.arange(n), "last_step_ns": rng.integers(900_000, 1_100_000, n),
        "imu_time_ns": 1_000_000 * np.arange(n) + 5, "unix_time": 1.7e9 + 0.02 * np.arange(n),
        "imu_ax": rng.normal(size=n), "imu_ay": rng.normal(size=n), "imu_az": 9.8 + rng.normal(size=n),
        "mag_X_uT": mag[:, 0], "mag_Y_uT": mag[:, 1], "mag_Z_uT": mag[:, 2], "battery_V": 12 + 0 * mag[:, 0],
    }
    header = ",".join(cols)
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=",", header=header, comments="", fmt="%.9g")


def test_wide_log_columns_are_not_guessed_from_counters_or_accelerometers(tmp_path: Path):
    """Finding: without --columns, fit took loop_index, last_step_ns, imu_time_ns (or unix_time, imu_ax, imu_ay)."""
    from trimag.io import read_samples

    p = tmp_path / "robot.csv"
    _wide_log(p)
    s = read_samples(p)
    assert s.columns == ("mag_X_uT", "mag_Y_uT", "mag_Z_uT")


@pytest.mark.parametrize("header,expected", [("ax,ay,az", "needs three"), ("count,v_min,v_max", "needs three")])
def test_accelerometer_and_statistics_files_are_refused(tmp_path: Path, header: str, expected: str):
    """Finding (field-check): an accelerometer log and a statistics table were fitted as if magnetometers."""
    p = tmp_path / "log.csv"
    rng = np.random.default_rng(1)
    np.savetxt(p, rng.normal(size=(200, 3)) + np.array([0, 0, 9.8]), delimiter=",", header=header, comments="")
    r = run_trimag("fit", p)
    assert r.returncode == 2 and expected in r.stderr and "--columns" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_evaluate_and_apply_on_a_wide_log_use_the_field_columns(tmp_path: Path):
    """Finding: evaluate and apply exited 0 with |B| mean 1.5e18 (they took counters and time stamps)."""
    p = tmp_path / "robot.csv"
    _wide_log(p)
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", p, "--units", "uT", "-o", cal).returncode == 0
    r = run_trimag("evaluate", cal, p, "--json")
    assert r.returncode == 0, r.stderr
    ev = json.loads(r.stdout)
    assert ev["columns"] == ["mag_X_uT", "mag_Y_uT", "mag_Z_uT"] and ev["mean_norm_after"] < 100


def _log(path: Path, B: np.ndarray, header: str = "x,y,z") -> Path:
    np.savetxt(path, B, delimiter=",", header=header, comments="", fmt="%.6f")
    return path


def test_nT_data_declared_as_uT_is_warned_and_refused_against_a_reference(tmp_path: Path):
    """Finding: nT data declared as uT was accepted silently (F = 49776.9 uT), and gave +-inf against --igrf."""
    p = _log(tmp_path / "log.csv", simulate_ellipsoid(600, noise=5.0, seed=1, F=49_800.0))
    r = run_trimag("fit", p, "--units", "uT")
    assert r.returncode == 0 and "not a plausible Earth field in uT" in r.stderr and "nT" in r.stderr
    r = run_trimag("fit", p, "--units", "uT", "--igrf", "52.5,13.4,40,2024-06-01")
    assert r.returncode == 2 and "not in uT" in r.stderr and "look like nT" in r.stderr
    assert run_trimag("fit", p, "--units", "nT", "--igrf", "52.5,13.4,40,2024-06-01").returncode == 0


def test_unit_in_the_header_is_checked_against_units(tmp_path: Path):
    """Finding: a unit in a header (Mx (uT)) was not checked against --units."""
    p = _log(tmp_path / "log.csv", simulate_ellipsoid(600, noise=0.005, seed=1, F=49.8), "Mx (uT),My (uT),Mz (uT)")
    r = run_trimag("fit", p, "--units", "nT")
    assert r.returncode == 2 and "headers say uT" in r.stderr
    r = run_trimag("fit", p, "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["units"] == "uT"


@pytest.fixture
def fitted(tmp_path: Path) -> tuple[Path, Path]:
    log = _log(tmp_path / "log.csv", simulate_ellipsoid(1500, noise=5.0, seed=1))
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", log, "--units", "nT", "-o", cal).returncode == 0
    return log, cal


def test_user_mistakes_exit_2_with_one_line(tmp_path: Path, fitted: tuple[Path, Path]):
    """Finding: unwritable output, a folder as calibration, a non-numeric matrix entry, a latin-1 header and a row
    with an extra field exited 1 ("internal error, please report")."""
    log, cal = fitted
    bad = json.loads(cal.read_text())
    bad["matrix"][0][0] = "abc"
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    latin = tmp_path / "latin.csv"
    latin.write_bytes("x\xe9,y,z\n".encode("latin-1") + log.read_bytes().split(b"\n", 1)[1])
    extra = tmp_path / "extra.csv"
    extra.write_text("x,y,z\n1,2,3\n4,5,6,7\n" + log.read_text().split("\n", 1)[1])
    cases = [
        ("fit", log, "--units", "nT", "-o", log / "cal.json"),
        ("apply", tmp_path, log, "-o", tmp_path / "o.csv"),
        ("apply", tmp_path / "bad.json", log, "-o", tmp_path / "o.csv"),
        ("apply", cal, latin, "-o", tmp_path / "o.csv"),
        ("apply", cal, extra, "-o", tmp_path / "o.csv"),
        ("apply", cal, log, "-o", tmp_path / "out.json"),
    ]
    for args in cases:
        r = run_trimag(*args)
        assert r.returncode == 2, (args, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr and "internal" not in r.stderr
    assert "line 3 has 4 fields" in run_trimag("apply", cal, extra, "-o", tmp_path / "o.csv").stderr
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "out.json").exists()


def test_outputs_appear_together_or_not_at_all(tmp_path: Path, fitted: tuple[Path, Path]):
    """Finding: the calibration JSON was left behind when --report failed."""
    log, _ = fitted
    out = tmp_path / "new.json"
    r = run_trimag("fit", log, "--units", "nT", "-o", out, "--report", log / "r.png")
    assert r.returncode == 2 and not out.exists()


def test_unknown_model_in_a_calibration_file_is_refused(tmp_path: Path, fitted: tuple[Path, Path]):
    """Finding: an unknown model name in a calibration file was used silently."""
    log, cal = fitted
    data = json.loads(cal.read_text())
    data["model"] = "nonsense"
    (tmp_path / "unk.json").write_text(json.dumps(data))
    r = run_trimag("evaluate", tmp_path / "unk.json", log)
    assert r.returncode == 2 and "unknown model 'nonsense'" in r.stderr


def test_calibration_records_its_source_and_columns(fitted: tuple[Path, Path]):
    log, cal = fitted
    stats = json.loads(cal.read_text())["stats"]
    assert stats["source"] == str(log) and stats["columns"] == ["x", "y", "z"]


def test_sigterm_during_apply_leaves_no_temporary_file(tmp_path: Path, fitted: tuple[Path, Path], monkeypatch):
    """Finding: SIGTERM during apply left a hidden 71 MB temporary file."""
    import os
    import signal

    import trimag.io.stream as stream
    from trimag.cli import main

    log, cal = fitted
    real = stream._correct
    calls = {"n": 0}

    def correct_then_terminate(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(*args, **kwargs)

    monkeypatch.setattr(stream, "_correct", correct_then_terminate)
    previous = signal.getsignal(signal.SIGTERM)
    try:
        code = main(["apply", str(cal), str(log), "-o", str(tmp_path / "o.csv"), "--chunk-rows", "100", "-q"])
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert code == 143
    assert not list(tmp_path.glob(".o.csv*")) and not (tmp_path / "o.csv").exists()


@pytest.fixture
def vector_log(tmp_path: Path) -> Path:
    from scipy.spatial.transform import Rotation

    params = tmp_path / "p.json"
    params.write_text(json.dumps({"k11": 1.02, "k12": 0.03, "k13": -0.01, "k21": 0.02, "k22": 0.97, "k23": 0.04,
                                  "k31": -0.03, "k32": 0.01, "k33": 1.05, "c1": 300, "c2": -200, "c3": 150}))
    sim = tmp_path / "s.csv"
    r = run_trimag("simulate", "--model", "interference12", "--params", params, "--n", "600", "--noise", "20",
                   "--field", "50000", "--units", "nT", "-o", sim, "-q")
    assert r.returncode == 0, r.stderr
    import pandas as pd

    d = pd.read_csv(sim)
    ypr = Rotation.from_quat(d[["qx", "qy", "qz", "qw"]].to_numpy()).as_euler("ZYX", degrees=True)
    d["yaw"], d["pitch"], d["roll"] = ypr.T
    d.to_csv(sim, index=False)
    return sim


def test_attitudes_in_the_wrong_order_are_refused_naming_the_right_one(vector_log: Path):
    """Finding: attitudes in the wrong order were accepted with exit 0 while the correction was 88x worse than raw;
    transposed attitudes gave det(K) < 0, also silently."""
    common = ("--columns", "x,y,z", "--model", "interference12", "--background-ned", "50000,0,0", "--units", "nT")
    assert run_trimag("fit", vector_log, *common, "--attitude-columns", "yaw,pitch,roll").returncode == 0
    r = run_trimag("fit", vector_log, *common, "--attitude-columns", "roll,pitch,yaw")
    assert r.returncode == 2 and "cannot be right" in r.stderr and "yaw,pitch,roll" in r.stderr
    r = run_trimag("fit", vector_log, *common[2:], "--columns", "x,y,z", "--quaternion-columns", "qw,qx,qy,qz",
                   "--quaternion-order", "xyzw")
    assert r.returncode == 2 and "order wxyz" in r.stderr


def test_apply_numbers_equal_the_calibration_files_formula(tmp_path: Path, fitted: tuple[Path, Path]):
    """Gap found by a mutation spot-check: apply's numbers were never checked (writing the inverse map passed)."""
    import pandas as pd

    log, cal = fitted
    out = tmp_path / "out.csv"
    assert run_trimag("apply", cal, log, "-o", out).returncode == 0
    data = json.loads(cal.read_text())
    raw = pd.read_csv(log)[["x", "y", "z"]].to_numpy()
    expected = (raw - np.array(data["offset"])) @ np.array(data["matrix"]).T
    got = pd.read_csv(out)[["x_cal", "y_cal", "z_cal"]].to_numpy()
    assert len(raw) > 1000
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-9)


def test_attitude_columns_by_index(vector_log: Path):
    """Finding: --columns took indices, --attitude-columns did not."""
    import pandas as pd

    names = list(pd.read_csv(vector_log, nrows=1).columns)
    idx = ",".join(str(names.index(c)) for c in ("yaw", "pitch", "roll"))
    r = run_trimag("fit", vector_log, "--columns", "0,1,2", "--model", "interference12", "--attitude-columns", idx,
                   "--background-ned", "50000,0,0", "--units", "nT")
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("kind", ["gzip", "bz2", "xz", "zip", "decimal-comma"])
def test_compressed_and_decimal_comma_inputs_are_read(tmp_path: Path, kind: str):
    """Finding: gzip'ed CSV ("no rows of numbers found") and ';' with decimal commas were refused."""
    import bz2
    import gzip
    import lzma
    import zipfile

    B = simulate_ellipsoid(600, noise=0.005, seed=1, F=49.8)
    text = "x,y,z\n" + "\n".join(",".join(f"{v:.6f}" for v in row) for row in B) + "\n"
    if kind == "decimal-comma":
        path = tmp_path / "log.csv"
        path.write_text(text.replace(",", ";").replace(".", ","))
    elif kind == "zip":
        path = tmp_path / "log.zip"
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("log.csv", text)
    else:
        opener = {"gzip": gzip.open, "bz2": bz2.open, "xz": lzma.open}[kind]
        path = tmp_path / f"log.csv.{ {'gzip': 'gz'}.get(kind, kind)}"
        with opener(path, "wt") as fh:
            fh.write(text)
    from trimag.io import read_samples

    s = read_samples(path)
    assert s.n_rows == 600
    np.testing.assert_allclose(s.field, np.round(B, 6), atol=1e-9)
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", path, "--units", "uT", "-o", cal).returncode == 0
    r = run_trimag("evaluate", cal, path, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["n_used"] == 600


def test_evaluate_judges_a_vector_calibration_by_vector_and_angular_error(tmp_path: Path, vector_log: Path):
    """Finding: evaluate had no attitude options: an interference12 calibration could only be judged on |B|."""
    cal = tmp_path / "cal.json"
    common = ("--columns", "x,y,z", "--attitude-columns", "yaw,pitch,roll", "--background-ned", "50000,0,0")
    fit = run_trimag("fit", vector_log, *common, "--model", "interference12", "--units", "nT", "-o", cal)
    assert fit.returncode == 0, fit.stderr
    r = run_trimag("evaluate", cal, vector_log, *common, "--json")
    assert r.returncode == 0, r.stderr
    ev = json.loads(r.stdout)
    assert ev["after"]["rms_vector"] < 0.1 * ev["before"]["rms_vector"]
    assert ev["after"]["angular_error_rms_deg"] < 0.1 and len(ev["after"]["rms_axis"]) == 3
    text = run_trimag("evaluate", cal, vector_log, *common)
    assert text.returncode == 0 and "angular error RMS" in text.stdout


def test_planar_data_diagnosis_describes_the_geometry_and_both_causes():
    """Finding: a robot log turned about all axes in a distorted environment was told only 'turned about a single
    axis'; the message now gives the observed spread and both possible causes."""
    from trimag.errors import IdentifiabilityError

    rng = np.random.default_rng(0)
    phi = rng.uniform(0, 2 * np.pi, 800)
    B = np.column_stack([40 * np.cos(phi), 40 * np.sin(phi), 5 + rng.normal(scale=0.05, size=800)])
    B[:, :2] += rng.normal(scale=0.05, size=(800, 2))
    with pytest.raises(IdentifiabilityError) as info:
        trimag.fit(B, model="ellipsoid", units="uT")
    text = str(info.value)
    # within the sample-to-sample noise the samples are in one plane: the message says so (issue 32, item 3: the
    # other cause, a changed field, is named only when the samples do leave the plane)
    assert "principal spreads" in text and "one plane within the noise" in text and "two more axes" in text
    assert "turned through 3" in text and "+z axis" in text  # the observed turn: its angle and axis


def test_scalar9_refusal_of_a_narrow_cone_describes_the_cone_not_a_single_axis_turn():
    """Finding: scalar9 refused an aircraft calibration box as a "single-axis turn" when the body-frame field
    stayed in a cone of 20-45 deg; the message now describes the cone, the covered fraction, the side never seen."""
    import re

    from trimag.errors import IdentifiabilityError

    with pytest.raises(IdentifiabilityError) as info:
        trimag.fit(_cone(2000, 20.0), model="scalar9", reference=50_000.0, units="nT")
    text = str(info.value)
    assert "single axis" not in text
    cone = re.search(r"within a cone of half-angle (\d+) deg about the sensor's \+z axis \((\d+)% of the sphere", text)
    assert cone is not None, text
    assert 17 <= int(cone.group(1)) <= 23 and 5 <= int(cone.group(2)) <= 10
    assert "-z axis" in text and "tilt the sensor further" in text


@pytest.mark.skipif(not (SHARED_DATA / "magnav-tl" / "test_data_TL.mat").exists(),
                    reason="../shared/data/magnav-tl absent (SGL data may not be copied into the repository)")
def test_scalar9_refusal_of_a_real_aircraft_box_describes_its_cone():
    """The finding's case on real data: the SGL survey aircraft's fluxgate in flight (MagNav.jl's test segment)."""
    import re

    import scipy.io

    from trimag.errors import IdentifiabilityError

    d = scipy.io.loadmat(SHARED_DATA / "magnav-tl" / "test_data_TL.mat", squeeze_me=True,
                         struct_as_record=False)["TL_data"]
    B = np.column_stack([d.flux_a_x, d.flux_a_y, d.flux_a_z]).astype(float)
    with pytest.raises(IdentifiabilityError) as info:
        trimag.fit(B, model="scalar9", reference=np.asarray(d.mag_1_uc, float), units="nT")
    text = str(info.value)
    cone = re.search(r"within a cone of half-angle (\d+) deg", text)
    assert cone is not None and 20 <= int(cone.group(1)) <= 45 and "single axis" not in text, text


def test_poorly_covered_ellipsoid_warning_names_the_cone():
    """Diagnoses describe the observed geometry: the cone half-angle and the direction never seen."""
    from trimag.errors import IdentifiabilityWarning

    with pytest.warns(IdentifiabilityWarning, match=r"within a cone of half-angle (29|3\d) deg about the sensor's "
                      r"\+z axis .*no sample within \d+ deg of its -z axis"):
        cal = trimag.fit(_cone(3000, 30.0), model="ellipsoid", reference=50_000.0, units="nT")
    geometry = cal.diagnostics["coverage"]
    assert geometry["shape"] == "cone" and geometry["cone_half_angle_deg"] == pytest.approx(30.0, abs=2.0)


def test_messages_never_dump_arrays():
    """Finding: passing a per-sample background vector (N, 3) dumped the whole array (a 537 235-character message)."""
    from trimag.errors import TrimagInputError
    from trimag.fields.reference import as_vector

    with pytest.raises(TrimagInputError) as info:
        as_vector(np.ones((50_000, 3)))
    assert len(str(info.value)) < 300 and "shape (50000, 3)" in str(info.value)
    with pytest.raises(TrimagInputError) as info2:
        trimag.Calibration.from_matrix_offset(np.full((3, 3), np.nan), [0, 0, 0])
    assert len(str(info2.value)) < 300


def test_twostep_with_a_per_sample_reference_that_varies_little():
    """Finding: `twostep` with a per-sample reference returned mean |B| 22 420 against a 53 941 reference (only
    `converged: False` and "poorly identified"); on main it refused such logs ("found no ellipsoid"). A reference
    that varies by a few nT (IGRF along a survey line, a scalar magnetometer) leaves TWOSTEP's centred step as
    degenerate as a constant one: the algebraic start is now used unless the centred one fits better."""
    B = simulate_ellipsoid(2000, noise=5.0, seed=1, F=50_000.0)
    F = 50_000.0 + 1.0 * np.sin(np.linspace(0.0, 9.0, len(B)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = trimag.fit(B, model="ellipsoid", method="twostep", reference=F, units="nT")
    assert np.mean(np.linalg.norm(cal.apply(B), axis=1)) == pytest.approx(50_000.0, abs=2.0)
    assert cal.stats["rms_after"] < 7.0 and cal.diagnostics["step1_start"] == "algebraic"


def test_twostep_with_a_per_sample_reference_that_varies_a_lot_keeps_its_centred_step():
    """Alonso & Shuster's case (the magnitude varies along an orbit): the centred linear step is used."""
    from trimag.simulate import uniform_directions

    W, b = ellipsoid_truth()
    F = 40_000.0 + 15_000.0 * np.sin(np.linspace(0.0, 9.0, 2000))
    rng = np.random.default_rng(3)
    B = np.linalg.solve(W, (F[:, None] * uniform_directions(2000, seed=2)).T).T + b
    B += rng.normal(scale=5.0, size=B.shape)
    cal = trimag.fit(B, model="ellipsoid", method="twostep", reference=F, units="nT")
    assert cal.diagnostics["step1_start"] == "centred"
    assert np.sqrt(np.mean((np.linalg.norm(cal.apply(B), axis=1) - F) ** 2)) < 7.0


@pytest.mark.skipif(not (SHARED_DATA / "magnav-tl" / "test_data_TL.mat").exists(),
                    reason="../shared/data/magnav-tl absent (SGL data may not be copied into the repository)")
def test_twostep_with_the_scalar_magnetometer_as_reference_on_a_real_aircraft():
    """The finding's kind of log: the SGL aircraft's fluxgate against its scalar magnetometer (per sample)."""
    import scipy.io

    d = scipy.io.loadmat(SHARED_DATA / "magnav-tl" / "test_data_TL.mat", squeeze_me=True,
                         struct_as_record=False)["TL_data"]
    B = np.column_stack([d.flux_a_x, d.flux_a_y, d.flux_a_z]).astype(float)
    F = np.asarray(d.mag_1_uc, float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = trimag.fit(B, model="ellipsoid", method="twostep", reference=F, units="nT")
    assert np.mean(np.linalg.norm(cal.apply(B), axis=1)) == pytest.approx(np.mean(F), abs=5.0)
    assert cal.stats["rms_after"] < 0.1 * cal.stats["rms_before"]


def test_a_log_whose_gain_changes_halfway_is_flagged_and_its_sigmas_widened():
    """Finding (issue 32, item 7): the halves of a real log differed by 1.5 RMS z with no warning: the drift check
    refitted the offsets only. A gain that changes halfway (x axis +3 %, as with a temperature step) is now named, and
    the sigmas cover the difference; a stable log is left alone."""
    B = simulate_ellipsoid(4000, noise=10.0, seed=2)
    stable = trimag.fit(B, model="ellipsoid", units="nT")
    assert stable.diagnostics["drift"]["drift"] is False and "halves_disagree" not in stable.uncertainty["inflation"]
    centre = np.asarray(stable.offset)
    B[2000:, 0] = centre[0] + 1.03 * (B[2000:, 0] - centre[0])
    moved = trimag.fit(B, model="ellipsoid", units="nT")
    drift = moved.diagnostics["drift"]
    assert drift["drift"] is True and "w11" in drift["moved"] and abs(drift["z"]["w11"]) > 10
    assert moved.uncertainty["inflation"]["halves_disagree"] > 10
    assert any("w11 by" in w and "changed during the log" in w for w in moved.diagnostics["warnings"])


@requires_shared
def test_the_office_log_whose_halves_differ_by_1_5_rms_z_is_told():
    """Finding (issue 32, item 7): on a real office log (ck-explorer, hand-turned) the halves differ by 1.5 RMS z; it
    was passed in silence. Its sigmas are widened to cover the difference, and a warning says so."""
    from trimag.io import read_samples

    cal = trimag.fit(read_samples(SHARED_DATA / "ck-explorer-accmag" / "acc_mag_log.csv").field)
    drift = cal.diagnostics["drift"]
    assert 1.3 < drift["rms_z"] < 1.8 and drift["p_value"] < 0.05 and drift["drift"]
    assert cal.uncertainty["inflation"]["halves_disagree"] > 1.5
    assert any("RMS z 1.5" in w for w in cal.diagnostics["warnings"])


def test_the_halves_warning_reaches_the_command_line(tmp_path: Path):
    """Finding (issue 32, item 7): the warning of a log whose halves disagree was kept in the calibration file's
    diagnostics; `trimag fit` never printed it."""
    B = simulate_ellipsoid(4000, noise=20.0, seed=1)
    B[2000:] += np.array([150.0, 0.0, 0.0])
    path = tmp_path / "log.csv"
    np.savetxt(path, B, delimiter=",", header="x,y,z", comments="")
    r = run_trimag("fit", path, "--units", "nT")
    assert r.returncode == 0 and "changed during the log" in r.stderr and "hard_iron_x by" in r.stderr, r.stderr


def test_a_mat_file_with_a_repeated_variable_reads_without_scipy_warnings(tmp_path: Path):
    """Finding (unseen real logs, rasteiro-robot): scipy's MatReadWarning ("Duplicate variable name") leaked three
    lines to stderr before trimag's own message."""
    import io

    import scipy.io

    data = simulate_ellipsoid(600, noise=0.2, seed=4, F=50.0)
    first, second = io.BytesIO(), io.BytesIO()
    scipy.io.savemat(first, {"mag": data})
    scipy.io.savemat(second, {"mag": data})
    path = tmp_path / "dup.mat"
    path.write_bytes(first.getvalue() + second.getvalue()[128:])  # the same variable twice, as the robot's files
    r = run_trimag("fit", path, "--units", "uT")
    assert r.returncode == 0 and "Warning" not in r.stderr and "Duplicate" not in r.stderr, r.stderr
