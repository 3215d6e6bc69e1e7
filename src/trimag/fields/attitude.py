"""Attitudes: Euler angles and quaternions to :class:`scipy.spatial.transform.Rotation`, one convention.

Convention (``docs/conventions-attitude.md``; methods.md, paper C)
------------------------------------------------------------------
* Navigation frame: **NED** (x north, y east, z down), right-handed.
* Body frame: x forward, y right, z down (the sensor's own axes; trimag never relabels body axes).
* An attitude is the rotation **body -> navigation**: ``R.apply(v_body)`` gives ``v`` in NED, and a
  navigation-frame field is seen by the sensor as ``H_b = R.inv().apply(H_n)`` (``trimag.simulate``).
* Euler angles are yaw (heading) ``psi``, pitch ``theta``, roll ``gamma``, applied in the intrinsic
  Z-Y-X sequence: ``C_b^n = Rz(psi) @ Ry(theta) @ Rx(gamma)``. Heading is clockwise from north seen from
  above, pitch is positive nose-up, roll positive right-wing-down. Files give degrees (``degrees=True``).
* Quaternions are unit quaternions of the same body -> navigation rotation. Their component order is a
  keyword (``scalar_first``, as in scipy). Quaternions referenced to **ENU** (x east, y north, z up; e.g.
  optical motion capture, ROS) are converted to NED by ``R_ned = T @ R_enu`` with
  ``T = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]`` (a 180 degree turn about the axis (1, 1, 0)/sqrt(2), which
  swaps north/east and flips up to down). **Body-frame assumption:** the body axes are left as they are
  (no forward-left-up to forward-right-down relabelling); the sensor's axes are whatever frame the
  quaternion's body frame is. A constant misalignment between that frame and the magnetometer's axes is
  absorbed by the interference matrix ``K`` of ``interference12``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .._core.chunks import row_blocks
from ..errors import TrimagInputError

__all__ = [
    "ENU_TO_NED",
    "attitude_from_table",
    "background_from_samples",
    "body_field",
    "column_names",
    "from_euler",
    "from_quaternion",
    "parse_columns",
]

#: Rotation matrix taking ENU components to NED components: ``v_ned = ENU_TO_NED @ v_enu``.
ENU_TO_NED: NDArray[np.float64] = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
ENU_TO_NED.setflags(write=False)


def _angles(value: ArrayLike, name: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TrimagInputError(f"`{name}` must be numeric (an angle or an array of angles)") from None
    if arr.ndim > 1:
        raise TrimagInputError(f"`{name}` must be a scalar or have shape (N,); got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise TrimagInputError(f"`{name}` has {bad} NaN or inf value(s); drop those rows first")
    return arr


def from_euler(yaw: ArrayLike, pitch: ArrayLike, roll: ArrayLike, *, degrees: bool = True) -> Rotation:
    """Attitude (body -> NED) from yaw/heading, pitch and roll, intrinsic Z-Y-X.

    ``C_b^n = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Parameters
    ----------
    yaw, pitch, roll : float or array_like, shape (N,)
        Heading (clockwise from north), pitch (nose up) and roll (right wing down); broadcast together.
    degrees : bool
        Angles in degrees (default, as in files) or radians.

    Returns
    -------
    Rotation
        Single rotation for scalar input, ``N`` rotations for arrays.

    Examples
    --------
    >>> R = from_euler(90.0, 0.0, 0.0)
    >>> R.apply([1.0, 0.0, 0.0]).round(12)          # body x (forward) points east
    array([0., 1., 0.])
    >>> len(from_euler([0, 10, 20], 5.0, 0.0))
    3
    """
    y, p, r = (_angles(v, n) for v, n in ((yaw, "yaw"), (pitch, "pitch"), (roll, "roll")))
    try:
        y, p, r = np.broadcast_arrays(y, p, r)
    except ValueError:
        raise TrimagInputError(
            f"yaw, pitch and roll must have the same length; got {y.shape}, {p.shape}, {r.shape}"
        ) from None
    angles = np.stack([y, p, r], axis=-1)
    limit = 90.0 if degrees else np.pi / 2
    if np.any(np.abs(p) > limit * (1 + 1e-12)):
        raise TrimagInputError(
            f"pitch must lie within -90..90 degrees (Z-Y-X convention); got {float(np.max(np.abs(p))):.6g}"
            + (" degrees" if degrees else " rad")
        )
    return Rotation.from_euler("ZYX", angles, degrees=degrees)


def from_quaternion(q: ArrayLike, *, scalar_first: bool = True, frame: str = "ned") -> Rotation:
    """Attitude (body -> NED) from unit quaternions of the body -> ``frame`` rotation.

    Parameters
    ----------
    q : array_like, shape (4,) or (N, 4)
        Quaternions; normalised here (a norm far from 1, below 0.5 or above 2, is refused as a column mix-up).
    scalar_first : bool
        ``(w, x, y, z)`` when True (default), ``(x, y, z, w)`` when False.
    frame : {"ned", "enu"}
        Navigation frame the quaternion refers to. ENU quaternions are converted to NED by
        ``R_ned = T @ R_enu`` (see the module docstring); body axes are not relabelled.

    Returns
    -------
    Rotation

    Examples
    --------
    >>> R = from_quaternion([1.0, 0.0, 0.0, 0.0], frame="enu")   # body axes along E, N, U
    >>> R.apply([0.0, 0.0, 1.0]).round(12)                        # body z = up = -down
    array([ 0.,  0., -1.])
    """
    try:
        arr = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError):
        raise TrimagInputError("`q` must be numeric with shape (4,) or (N, 4)") from None
    if arr.shape[-1:] != (4,) or arr.ndim > 2:
        raise TrimagInputError(f"`q` must have shape (4,) or (N, 4); got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=-1))) if arr.ndim == 2 else 1
        raise TrimagInputError(f"`q` has {bad} row(s) with NaN or inf; drop those rows first")
    norms = np.linalg.norm(arr, axis=-1)
    if np.any(norms < 0.5) or np.any(norms > 2.0):
        raise TrimagInputError(
            f"quaternions must be unit length; got norms from {norms.min():.3g} to {norms.max():.3g} "
            "(are the quaternion columns right?)"
        )
    frame_key = str(frame).strip().lower()
    if frame_key not in ("ned", "enu"):
        raise TrimagInputError(f"quaternion frame must be 'ned' or 'enu'; got {frame!r}")
    rot = Rotation.from_quat(arr, scalar_first=scalar_first)
    if frame_key == "enu":
        rot = Rotation.from_matrix(ENU_TO_NED) * rot
    return rot


def parse_columns(spec: str | Sequence[str] | None, n: int, *, option: str) -> list[str] | None:
    """Split ``"a,b,c"`` (a command-line value) into ``n`` column names; ``None`` passes through."""
    if spec is None:
        return None
    names = [s.strip() for s in spec.split(",")] if isinstance(spec, str) else [str(s) for s in spec]
    if len(names) != n or any(not s for s in names):
        raise TrimagInputError(f"{option} takes {n} comma-separated column names; got {spec!r}")
    return names


def column_names(items: Sequence[str], available: Sequence[str]) -> list[str]:
    """``items`` with each 0-based index that is not itself a column name replaced by that column's name (indices
    are accepted wherever a column is named, as ``columns`` does); out-of-range indices are left as they are."""
    return [available[int(c)] if c not in available and c.isdigit() and int(c) < len(available) else c
            for c in items]


def attitude_from_table(
    table: object,
    *,
    euler_columns: str | Sequence[str] | None = None,
    quaternion_columns: str | Sequence[str] | None = None,
    scalar_first: bool = True,
    frame: str = "ned",
    degrees: bool = True,
) -> Rotation:
    """Per-row attitudes from named columns of a table.

    Parameters
    ----------
    table : pandas.DataFrame
        One row per sample.
    euler_columns : str or sequence of 3 str
        Yaw, pitch, roll columns (``"yaw,pitch,roll"``), in degrees unless ``degrees=False``; Z-Y-X, NED.
    quaternion_columns : str or sequence of 4 str
        Quaternion columns **in the order they are to be read** (``"w,x,y,z"`` with ``scalar_first=True``,
        ``"x,y,z,w"`` with ``scalar_first=False``).
    scalar_first, frame, degrees
        As in :func:`from_quaternion` and :func:`from_euler`.

    Returns
    -------
    Rotation of length ``len(table)``

    Raises
    ------
    TrimagInputError
        Neither or both column sets given, a column missing, or non-finite values.
    """
    if (euler_columns is None) == (quaternion_columns is None):
        raise TrimagInputError(
            "give the attitude either as Euler angles (`attitude_columns=yaw,pitch,roll`) or as quaternions "
            "(`quaternion_columns=w,x,y,z`), exactly one of them"
        )
    cols = (
        parse_columns(euler_columns, 3, option="`attitude_columns`")
        if euler_columns is not None
        else parse_columns(quaternion_columns, 4, option="`quaternion_columns`")
    )
    assert cols is not None
    available = [str(c) for c in getattr(table, "columns", [])]
    cols = column_names(cols, available)
    missing = [c for c in cols if c not in available]
    if missing:
        raise TrimagInputError(f"attitude column(s) {missing} not found; the table has columns {available}")
    values = np.asarray(table[cols], dtype=np.float64)  # type: ignore[index]
    if euler_columns is not None:
        return from_euler(values[:, 0], values[:, 1], values[:, 2], degrees=degrees)
    return from_quaternion(values, scalar_first=scalar_first, frame=frame)


def body_field(attitude: Rotation, field_nav: ArrayLike) -> NDArray[np.float64]:
    """Navigation-frame field (3,) or (N, 3) seen in the body frame: ``H_b = R.inv().apply(H_n)``, shape (N, 3).

    Taken chunk by chunk (:func:`~trimag._core.chunks.chunk_rows`): the inverted rotations and the rotation's
    temporaries exist for one chunk at a time (whole, they took 880 MB at N = 1e7 besides the 240 MB result).
    """
    H_n = np.asarray(field_nav, dtype=np.float64)
    if attitude.single:
        return np.atleast_2d(attitude.inv().apply(H_n))
    n = len(attitude)
    out = np.empty((n, 3))
    for rows in row_blocks(n):
        h = H_n[rows] if H_n.ndim == 2 else H_n
        out[rows] = attitude[rows].inv().apply(h)
    return out


def background_from_samples(B_free: ArrayLike, attitude: Rotation) -> tuple[NDArray[np.float64], float]:
    """Background field in NED from an iron-free run: the mean of ``R_i.apply(B_i)``.

    Parameters
    ----------
    B_free : array_like, shape (N, 3)
        Sensor readings without the interfering iron (body frame), any unit.
    attitude : Rotation, N rotations
        The attitudes at which they were recorded (body -> NED).

    Returns
    -------
    H_n : ndarray, shape (3,)
        Mean navigation-frame field, same unit as ``B_free``.
    spread : float
        RMS distance of the single rotated readings from that mean (same unit): a check that the run is
        iron-free and the attitudes are right (it should be near the sensor noise).
    """
    B = np.asarray(B_free, dtype=np.float64)
    if B.ndim != 2 or B.shape[1] != 3:
        raise TrimagInputError(f"the background run must have shape (N, 3); got {B.shape}")
    n_att = 1 if attitude.single else len(attitude)
    if n_att != len(B):
        raise TrimagInputError(
            f"the background run has {len(B)} samples but {n_att} attitudes; give one per row"
        )
    if not np.isfinite(B).all():
        raise TrimagInputError("the background run has NaN or inf values; drop those rows first")
    nav = np.atleast_2d(attitude.apply(B))
    mean = nav.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((nav - mean) ** 2, axis=1))))
    return mean, spread


