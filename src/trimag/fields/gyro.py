"""A gyroscope beside the magnetometer: its angular rate, integrated into the relative attitude that tells a fit how
the field must turn between samples (issue 31; docs/method-gyro.md).

Convention (docs/conventions-attitude.md): the gyroscope measures the body's angular rate ``omega`` in its own
frame, rad/s, right-handed. The body's attitude ``G`` (body -> a fixed frame) obeys ``dG/dt = G [omega]x``, so a
field fixed in space is seen in the body frame as ``h = G^T h_fixed``, which obeys ``dh/dt = -omega x h``.

``G`` is integrated on the gyroscope's own time stamps, from ``G_0 = I``:

    G_{k+1} = G_k exp([phi_k]x),  phi_k = int_{t_k}^{t_k+1} (omega - bias) dt + (dt^2 / 12) omega_k x omega_{k+1}

with the integral of the cubic Hermite interpolant of the rate (trapezoid plus the end correction
``dt^2/12 (omega'_k - omega'_{k+1})``, rates' derivatives by :func:`numpy.gradient`; local error ``O(dt^5)``) and
the classical two-sample coning correction (Savage 1998, "Strapdown inertial navigation integration algorithm
design", part 1, eq. 41: the first-order rotation-vector term for a linearly varying rate). The products
``G_k`` are a prefix product: taken in ``ceil(log2 M)`` vectorised passes (Hillis-Steele), not one per sample.
Between gyroscope samples the attitude is interpolated on the quaternion great circle (slerp).

The fit needs, besides ``G``, how it moves with the gyroscope's bias: ``G_k(bias + d) = G_k exp([e_k]x)`` to first
order with ``e_k = -G_k^T S_k d`` and ``S_k = sum_{j<k} G_{j+1} J_r(phi_j) dt_j`` (``J_r`` the right Jacobian of
SO(3); Forster et al. 2017, "On-manifold preintegration", eq. 44-47): a cumulative sum, interpolated linearly
between samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError

__all__ = ["RATE_UNITS", "AngularRate", "GyroAttitude", "integrate_rate", "rate_in_rad_s"]

#: Units a gyroscope's rate may be given in, and their factor to rad/s.
RATE_UNITS: dict[str, float] = {"rad/s": 1.0, "deg/s": np.pi / 180.0}


def rate_in_rad_s(values: ArrayLike, unit: str) -> NDArray[np.float64]:
    """``values`` (any shape) in ``unit`` (``"rad/s"`` or ``"deg/s"``) converted to rad/s."""
    key = str(unit).strip().lower().replace(" ", "")
    key = {"rad": "rad/s", "rads": "rad/s", "radps": "rad/s", "deg": "deg/s", "degs": "deg/s", "dps": "deg/s",
           "degps": "deg/s"}.get(key, key)
    if key not in RATE_UNITS:
        raise TrimagInputError(f"a gyroscope's unit is rad/s or deg/s; got {unit!r}")
    return np.asarray(values, dtype=np.float64) * RATE_UNITS[key]


@dataclass(frozen=True)
class AngularRate:
    """A gyroscope's angular rate beside a magnetometer's samples (the ``attitude`` argument of the gyro-aided fit,
    :class:`trimag.estimators.gyro.GyroAided`).

    Attributes
    ----------
    time_s : ndarray, shape (N,)
        The magnetometer samples' time stamps, s.
    gyro_time_s : ndarray, shape (M,)
        The gyroscope's time stamps, s, strictly increasing (the same array as ``time_s`` when the two share rows).
    rate : ndarray, shape (M, 3)
        Angular rate in the gyroscope's frame, rad/s.
    lag_s : float
        Gyroscope clock - magnetometer clock: the sample stamped ``t`` takes the gyroscope's attitude at
        ``t + lag_s`` (the start of an estimated lag, or a known one).
    own_clock : bool
        True when the gyroscope has its own time stamps (a second file): its lag can be estimated.
    source : str
        Where the rate came from, for the user.
    """

    time_s: NDArray[np.float64]
    gyro_time_s: NDArray[np.float64]
    rate: NDArray[np.float64]
    lag_s: float = 0.0
    own_clock: bool = False
    source: str = ""

    @classmethod
    def same_rows(cls, time_s: ArrayLike, rate: ArrayLike, *, unit: str = "rad/s", source: str = "") -> AngularRate:
        """The rate logged in the magnetometer's own rows (one time stamp per row)."""
        t = np.asarray(time_s, dtype=np.float64)
        return cls(t, t, rate_in_rad_s(rate, unit), 0.0, False, source)

    def check(self, n: int) -> None:
        """Refuse what cannot be integrated: shapes that do not match ``n`` magnetometer samples, non-finite
        values, time stamps that do not increase, magnetometer samples outside the gyroscope's span."""
        t, tg, w = self.time_s, self.gyro_time_s, self.rate
        if t.shape != (n,):
            raise TrimagInputError(f"the gyro-aided fit needs one time stamp per sample: {n} samples, {t.shape} times")
        if w.ndim != 2 or w.shape[1] != 3 or len(w) != len(tg):
            raise TrimagInputError(f"the angular rate must be (M, 3) with one time stamp per row; got {w.shape} rates "
                                   f"and {tg.shape} times")
        if len(tg) < 3:
            raise TrimagInputError("the gyroscope has fewer than 3 samples")
        if not (np.isfinite(t).all() and np.isfinite(tg).all() and np.isfinite(w).all()):
            raise TrimagInputError("the time stamps or the angular rate contain NaN or inf: drop those rows first")
        if np.any(np.diff(tg) <= 0):
            k = int(np.flatnonzero(np.diff(tg) <= 0)[0])
            raise TrimagInputError(f"the gyroscope's time stamps must increase: row {k + 1} ({tg[k + 1]:.9g} s) does "
                                   f"not come after row {k} ({tg[k]:.9g} s)")
        lo, hi = t.min() + self.lag_s, t.max() + self.lag_s
        if lo < tg[0] - 1e-9 or hi > tg[-1] + 1e-9:
            raise TrimagInputError(f"magnetometer samples at {lo:.6g}..{hi:.6g} s (gyroscope clock) lie outside the "
                                   f"gyroscope's span {tg[0]:.6g}..{tg[-1]:.6g} s: drop them first")

    @property
    def median_interval(self) -> float:
        """Median time between gyroscope samples, s."""
        return float(np.median(np.diff(self.gyro_time_s)))


def skew(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """``[v]x`` (..., 3, 3) of vectors ``v`` (..., 3): ``[v]x w = v x w``."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def right_jacobian(phi: NDArray[np.float64]) -> NDArray[np.float64]:
    """The right Jacobian of SO(3), ``J_r(phi) = I - (1 - cos a)/a^2 [phi]x + (a - sin a)/a^3 [phi]x^2`` with
    ``a = |phi|`` (series near 0), shape (..., 3, 3): ``exp([phi + d]x) = exp([phi]x) exp([J_r(phi) d]x)`` to first
    order."""
    a = np.linalg.norm(phi, axis=-1)
    small = a < 1e-4
    a_safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a**2 / 24.0, (1.0 - np.cos(a_safe)) / a_safe**2)
    c2 = np.where(small, 1.0 / 6.0 - a**2 / 120.0, (a_safe - np.sin(a_safe)) / a_safe**3)
    K = skew(phi)
    return np.eye(3) - c1[..., None, None] * K + c2[..., None, None] * (K @ K)


def _quat_multiply(p: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hamilton products ``p q`` of quaternions (..., 4), scalar first."""
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw], axis=-1)


def _rotvec_to_quat(phi: NDArray[np.float64]) -> NDArray[np.float64]:
    a = np.linalg.norm(phi, axis=-1)
    half = 0.5 * a
    s = np.where(a < 1e-8, 0.5 - a**2 / 48.0, np.sin(half) / np.where(a < 1e-8, 1.0, a))
    return np.concatenate([np.cos(half)[..., None], phi * s[..., None]], axis=-1)


def quaternion_prefix(steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """``Q_0 = 1``, ``Q_{k+1} = Q_k steps_k``: the prefix products of unit quaternions ``steps`` (M - 1, 4), scalar
    first, shape (M, 4). Hillis-Steele scan: ``ceil(log2 M)`` vectorised passes, each renormalised."""
    out = np.empty((len(steps) + 1, 4))
    out[0] = (1.0, 0.0, 0.0, 0.0)
    out[1:] = steps
    d = 1
    while d < len(out):
        nxt = _quat_multiply(out[:-d], out[d:])
        out[d:] = nxt / np.linalg.norm(nxt, axis=1, keepdims=True)
        d *= 2
    return out


def _quat_to_matrix(q: NDArray[np.float64]) -> NDArray[np.float64]:
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def step_rotations(
    t: NDArray[np.float64], rate: NDArray[np.float64], bias: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The rotation vectors ``phi_k`` (M - 1, 3) between consecutive gyroscope samples (module docstring) and the
    intervals ``dt_k`` (M - 1,)."""
    w = rate - bias
    dt = np.diff(t)
    dw = np.gradient(w, t, axis=0)
    phi = 0.5 * dt[:, None] * (w[:-1] + w[1:]) + (dt**2 / 12.0)[:, None] * (dw[:-1] - dw[1:])
    phi += (dt**2 / 12.0)[:, None] * np.cross(w[:-1], w[1:])
    return phi, dt


@dataclass(frozen=True)
class GyroAttitude:
    """The integrated attitude at the magnetometer's samples (:func:`integrate_rate`).

    ``G`` (N, 3, 3): attitude body -> the integration's fixed frame (``G = I`` at the gyroscope's first sample);
    ``S`` (N, 3, 3): its sensitivity to the bias (module docstring); ``rate`` (N, 3): the bias-corrected rate at
    the samples, rad/s (the sensitivity to the lag: ``dG/dlag = G [rate]x``)."""

    G: NDArray[np.float64]
    S: NDArray[np.float64]
    rate: NDArray[np.float64]


def integrate_rate(gyro: AngularRate, bias: ArrayLike, lag: float) -> GyroAttitude:
    """Integrate the gyroscope's rate less ``bias`` (rad/s) on its own time stamps and take the attitude, its bias
    sensitivity and the rate at the magnetometer's samples ``time_s + lag`` (slerp between gyroscope samples;
    the sensitivity and the rate linearly)."""
    b = np.asarray(bias, dtype=np.float64)
    tg = gyro.gyro_time_s
    phi, dt = step_rotations(tg, gyro.rate, b)
    q = quaternion_prefix(_rotvec_to_quat(phi))
    G_all = _quat_to_matrix(q)
    terms = np.einsum("kij,kjl->kil", G_all[1:], right_jacobian(phi)) * dt[:, None, None]
    S_all = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(terms, axis=0)])
    w_all = gyro.rate - b
    tq = gyro.time_s + lag
    if tq.shape == tg.shape and lag == 0.0 and np.array_equal(tq, tg):
        return GyroAttitude(G_all, S_all, w_all)
    k = np.clip(np.searchsorted(tg, tq, side="right") - 1, 0, len(tg) - 2)
    f = np.clip((tq - tg[k]) / (tg[k + 1] - tg[k]), 0.0, 1.0)
    # slerp within the step k -> k+1: G(t) = G_k exp(f [phi_k]x) (the integration's own path between the samples)
    G = G_all[k] @ _quat_to_matrix(_rotvec_to_quat(f[:, None] * phi[k]))
    S = S_all[k] + f[:, None, None] * (S_all[k + 1] - S_all[k])
    w = w_all[k] + f[:, None] * (w_all[k + 1] - w_all[k])
    return GyroAttitude(G, S, w)


def describe(gyro: AngularRate) -> dict[str, Any]:
    """What the fit records of the gyroscope's stream (for the calibration's diagnostics)."""
    return {"source": gyro.source, "n_gyro_samples": len(gyro.gyro_time_s),
            "gyro_interval_s": gyro.median_interval, "own_clock": bool(gyro.own_clock),
            "rate_rms_rad_s": float(np.sqrt(np.mean(np.sum(gyro.rate**2, axis=1))))}
