"""Attitude conventions (docs/conventions-attitude.md) against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from trimag.errors import TrimagInputError
from trimag.fields.attitude import (
    ENU_TO_NED,
    attitude_from_table,
    background_from_samples,
    body_field,
    from_euler,
    from_quaternion,
)
from trimag.io.background import background_from_run

S = np.sqrt(0.5)


@pytest.mark.parametrize(
    ("yaw", "pitch", "roll", "body_vec", "ned_vec"),
    [
        pytest.param(90, 0, 0, [1, 0, 0], [0, 1, 0], id="yaw90-forward-points-east"),
        pytest.param(0, 90, 0, [1, 0, 0], [0, 0, -1], id="pitch90-nose-up"),
        pytest.param(0, 0, 90, [0, 1, 0], [0, 0, 1], id="roll90-right-wing-down"),
        pytest.param(45, 0, 0, [1, 0, 0], [S, S, 0], id="yaw45-north-east"),
        # Z-Y-X: after yaw 90 body y points south (NED -x); pitching about body y leaves it there.
        pytest.param(90, 90, 0, [0, 1, 0], [-1, 0, 0], id="yaw90-pitch90-y-south"),
    ],
)
def test_from_euler_hand_cases(yaw, pitch, roll, body_vec, ned_vec):
    R = from_euler(yaw, pitch, roll)
    np.testing.assert_allclose(R.apply(body_vec), ned_vec, atol=1e-12)


def test_from_euler_matrix_is_Rz_Ry_Rx():
    y, p, r = np.radians([30.0, 20.0, -10.0])
    cz, sz, cy, sy, cx, sx = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    np.testing.assert_allclose(from_euler(30, 20, -10).as_matrix(), Rz @ Ry @ Rx, atol=1e-14)
    np.testing.assert_allclose(
        from_euler(y, p, r, degrees=False).as_matrix(), Rz @ Ry @ Rx, atol=1e-14
    )


def test_body_field_north_seen_left_after_yaw_east():
    # heading east: north is on the vehicle's left, i.e. body -y
    np.testing.assert_allclose(body_field(from_euler(90, 0, 0), [1.0, 0, 0]), [[0, -1, 0]], atol=1e-12)


def test_euler_shapes_and_broadcast():
    assert from_euler(10, 0, 0).single
    R = from_euler([0, 10, 20], 5.0, 0.0)
    assert len(R) == 3
    with pytest.raises(TrimagInputError, match="same length"):
        from_euler([0, 1], [0, 1, 2], 0)
    with pytest.raises(TrimagInputError, match="pitch"):
        from_euler(0, 95, 0)
    with pytest.raises(TrimagInputError, match="NaN"):
        from_euler([0, np.nan], 0, 0)


def test_quaternion_orders_agree():
    rng = np.random.default_rng(3)
    R = Rotation.random(20, random_state=rng)
    q_wxyz = R.as_quat(scalar_first=True)
    a = from_quaternion(q_wxyz, scalar_first=True)
    b = from_quaternion(q_wxyz[:, [1, 2, 3, 0]], scalar_first=False)
    np.testing.assert_allclose(a.as_matrix(), R.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(b.as_matrix(), R.as_matrix(), atol=1e-12)


def test_quaternion_hand_case_yaw90():
    # 90 degrees about NED z (down): q = (cos 45, 0, 0, sin 45)
    R = from_quaternion([S, 0, 0, S])
    np.testing.assert_allclose(R.apply([1, 0, 0]), [0, 1, 0], atol=1e-12)


def test_enu_quaternion_converted_to_ned():
    # identity in ENU: body x = east, y = north, z = up -> in NED (0,1,0), (1,0,0), (0,0,-1)
    R = from_quaternion([1.0, 0, 0, 0], frame="enu")
    np.testing.assert_allclose(R.as_matrix(), ENU_TO_NED, atol=1e-15)
    # a body pointing its x axis north in ENU (yaw +90 about up) points it north in NED too
    q_enu = [S, 0, 0, S]  # +90 deg about ENU z (up): body x -> north (ENU y)
    R2 = from_quaternion(q_enu, frame="enu")
    np.testing.assert_allclose(R2.apply([1, 0, 0]), [1, 0, 0], atol=1e-12)
    # body axes are NOT relabelled: body z stays the body's own "up" axis, i.e. NED -z here
    np.testing.assert_allclose(R2.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)
    # field vectors: the same physical field, ENU components vs NED components, gives the same body field
    rng = np.random.default_rng(0)
    Renu = Rotation.random(5, random_state=rng)
    h_enu = np.array([100.0, 20000.0, -45000.0])
    h_ned = ENU_TO_NED @ h_enu
    np.testing.assert_allclose(
        body_field(from_quaternion(Renu.as_quat(scalar_first=True), frame="enu"), h_ned),
        Renu.inv().apply(h_enu), atol=1e-9,
    )


def test_quaternion_bad_input():
    with pytest.raises(TrimagInputError, match="shape"):
        from_quaternion([1, 0, 0])
    with pytest.raises(TrimagInputError, match="unit length"):
        from_quaternion([10.0, 0, 0, 0])
    with pytest.raises(TrimagInputError, match="frame"):
        from_quaternion([1.0, 0, 0, 0], frame="nwu")
    with pytest.raises(TrimagInputError, match="NaN"):
        from_quaternion([[1.0, 0, 0, 0], [np.nan, 0, 0, 0]])


def test_attitude_from_table_euler_and_quaternion():
    df = pd.DataFrame(
        {"hdg": [0.0, 90.0], "pit": [0.0, 0.0], "rol": [0.0, 0.0],
         "qw": [1.0, S], "qx": [0.0, 0.0], "qy": [0.0, 0.0], "qz": [0.0, S]}
    )
    Re = attitude_from_table(df, euler_columns="hdg,pit,rol")
    Rq = attitude_from_table(df, quaternion_columns=["qw", "qx", "qy", "qz"])
    np.testing.assert_allclose(Re.as_matrix(), Rq.as_matrix(), atol=1e-12)
    Rq2 = attitude_from_table(df, quaternion_columns="qx,qy,qz,qw", scalar_first=False)
    np.testing.assert_allclose(Rq2.as_matrix(), Rq.as_matrix(), atol=1e-12)
    with pytest.raises(TrimagInputError, match="exactly one"):
        attitude_from_table(df)
    with pytest.raises(TrimagInputError, match="not found"):
        attitude_from_table(df, euler_columns="yaw,pitch,roll")
    with pytest.raises(TrimagInputError, match="3 comma-separated"):
        attitude_from_table(df, euler_columns="hdg,pit")


def test_background_from_run_recovers_vector():
    rng = np.random.default_rng(1)
    R = Rotation.random(10, random_state=rng)
    H_n = np.array([18000.0, 1200.0, 46000.0])
    H_n_hat, spread = background_from_samples(R.inv().apply(H_n), R)
    np.testing.assert_allclose(H_n_hat, H_n, atol=1e-8)
    assert spread < 1e-8
    with pytest.raises(TrimagInputError, match="attitudes"):
        background_from_samples(np.zeros((3, 3)), R)


def test_background_from_run_file(tmp_path):
    rng = np.random.default_rng(2)
    y, p, r = rng.uniform(0, 360, 8), rng.uniform(-40, 40, 8), rng.uniform(-40, 40, 8)
    R = from_euler(y, p, r)
    H_n = np.array([30000.0, -2000.0, 35000.0])
    H = body_field(R, H_n)
    # file with its own attitude columns
    pd.DataFrame({"x": H[:, 0], "y": H[:, 1], "z": H[:, 2], "yaw": y, "pitch": p, "roll": r}).to_csv(
        tmp_path / "own.csv", index=False
    )
    vec, source = background_from_run(tmp_path / "own.csv", units="nT", attitude_columns="yaw,pitch,roll")
    np.testing.assert_allclose(vec, H_n, atol=1e-6)
    assert "own attitude columns" in source
    # file without attitudes: the data's attitudes, row for row
    pd.DataFrame({"x": H[:, 0], "y": H[:, 1], "z": H[:, 2]}).to_csv(tmp_path / "bare.csv", index=False)
    vec, source = background_from_run(tmp_path / "bare.csv", units="nT", attitude=R,
                                      attitude_columns="yaw,pitch,roll")
    np.testing.assert_allclose(vec, H_n, atol=1e-6)
    assert "row for row" in source
    with pytest.raises(TrimagInputError, match="same attitudes"):
        background_from_run(tmp_path / "bare.csv", units="nT", attitude=R[:5], attitude_columns="yaw,pitch,roll")
