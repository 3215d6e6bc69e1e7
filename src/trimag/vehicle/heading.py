"""Heading error a calibration predicts, from its covariance (issue 20; conventions: docs/conventions-attitude.md).

A level sensor heading ``psi`` (degrees clockwise from magnetic north) in a field of magnitude ``F`` and
inclination ``I`` sees, in its body frame (forward-right-down), ``n(psi) = F [cos I cos psi, -cos I sin psi, sin I]``;
the raw reading is ``x = W^-1 n + b``. An error ``d theta`` of the calibration's parameters moves the corrected
field by ``dy = G d theta`` and the heading ``atan2(-y_2, y_1)`` by ``d psi = (y_2 dy_1 - y_1 dy_2) / (y_1^2 + y_2^2)``,
so ``sigma_psi(psi)^2 = g C g'`` with ``C`` the covariance of the fit. Computed for the ellipsoid model's gauge
(upper-triangular ``W`` and the hard iron), the covariance every ellipsoid estimator reports.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError

__all__ = ["predicted_heading_sigma"]



def predicted_heading_sigma(
    cal: Calibration, inclination_deg: float, headings_deg: NDArray[np.float64] | None = None
) -> dict[str, Any]:
    """1-sigma heading error (degrees) of a level sensor at each heading, from ``cal``'s covariance.

    Returns
    -------
    dict
        ``headings_deg``, ``sigma_deg`` (per heading), ``rms_deg``, ``max_deg``, ``inclination_deg``.

    Raises
    ------
    TrimagInputError
        The calibration has no covariance in the ellipsoid model's gauge.
    """
    C = _entry_covariance(cal)
    W = np.asarray(cal.matrix)
    b = np.asarray(cal.offset)
    F = float((cal.reference or {}).get("value") or np.linalg.norm(W @ (np.zeros(3) - b)))
    psi = np.radians(np.arange(0.0, 360.0, 5.0) if headings_deg is None else np.asarray(headings_deg, float))
    inc = np.radians(inclination_deg)
    n = F * np.column_stack([np.cos(inc) * np.cos(psi), -np.cos(inc) * np.sin(psi), np.full(len(psi), np.sin(inc))])
    x = np.linalg.solve(W, n.T).T + b
    d = x - b
    # dy/dtheta for theta = (W's nine entries, row-major, then b_x, b_y, b_z): y = W (x - b)
    G = np.zeros((len(psi), 3, 12))
    for i in range(3):
        G[:, i, 3 * i:3 * i + 3] = d
    G[:, :, 9:] = -W
    y = n
    g = (y[:, 1:2] * G[:, 0, :] - y[:, 0:1] * G[:, 1, :]) / (y[:, 0:1] ** 2 + y[:, 1:2] ** 2)
    sigma = np.degrees(np.sqrt(np.clip(np.einsum("ni,ij,nj->n", g, C, g), 0.0, None)))
    return {"headings_deg": np.degrees(psi).tolist(), "sigma_deg": sigma.tolist(),
            "rms_deg": float(np.sqrt(np.mean(sigma**2))), "max_deg": float(sigma.max()),
            "inclination_deg": float(inclination_deg)}


def _entry_covariance(cal: Calibration) -> NDArray[np.float64]:
    """The covariance (12, 12) of ``W``'s nine entries (row-major) and the offset, from the calibration's covariance
    in its own parameters: the upper-triangular ``w11 .. w33`` of the ellipsoid estimators, the symmetric
    ``m11 .. m33`` of a level turn (``m12`` both ``W[0, 1]`` and ``W[1, 0]``), or none (a matrix held: the offset's
    only)."""
    unc = cal.uncertainty or {}
    order = list(unc.get("covariance_order") or [])
    offset = ("hard_iron_x", "hard_iron_y", "hard_iron_z")
    if unc.get("covariance") is None or not all(n in order for n in offset):
        raise TrimagInputError("a predicted heading error needs a calibration of the ellipsoid model with its "
                               "covariance (fit with model ellipsoid, method ml, twostep, als or ellipsoid-fit)")
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    names: list[str] = []
    T_rows: list[NDArray[np.float64]] = []  # entry -> parameter: theta_full = T^T p
    for prefix, symmetric in (("w", False), ("m", True)):
        if all(f"{prefix}{i + 1}{j + 1}" in order for i, j in pairs):
            for i, j in pairs:
                t = np.zeros(12)
                t[3 * i + j] = 1.0
                if symmetric:
                    t[3 * j + i] = 1.0
                names.append(f"{prefix}{i + 1}{j + 1}")
                T_rows.append(t)
            break
    for k, name in enumerate(offset):
        t = np.zeros(12)
        t[9 + k] = 1.0
        names.append(name)
        T_rows.append(t)
    idx = [order.index(n) for n in names]
    C = np.asarray(unc["covariance"], dtype=np.float64)[np.ix_(idx, idx)]
    T = np.array(T_rows).T  # (12, p)
    return np.asarray(T @ C @ T.T, dtype=np.float64)


def tilt_compensated_heading(
    field: ArrayLike, accel: ArrayLike, *, declination_deg: float = 0.0
) -> NDArray[np.float64]:
    """Heading (degrees clockwise from north, 0-360) from a body-frame field and the accelerometer.

    The down direction is ``d = -a / |a|`` (specific force; at rest and level ``a = (0, 0, -g)``), magnetic east
    ``e = d x h / |d x h|`` and north ``n = e x d`` in the body frame (forward-right-down); the heading is the angle
    of the forward axis, ``atan2(e_x, n_x)``, plus the declination. It is the yaw of the Z-Y-X attitude
    (docs/conventions-attitude.md) at any tilt short of the forward axis pointing straight up or down.

    Parameters
    ----------
    field : array_like, shape (N, 3)
        Corrected field in the accelerometer's (body) frame, any unit.
    accel : array_like, shape (N, 3)
        Specific force, any unit.
    declination_deg : float
        Magnetic declination, degrees east of true north: the result is true heading.

    Returns
    -------
    ndarray, shape (N,)

    Examples
    --------
    >>> float(tilt_compensated_heading([[0.0, -20.0, 40.0]], [[0.0, 0.0, -9.81]])[0])   # north on the left: east
    90.0
    """
    h = np.atleast_2d(np.asarray(field, dtype=np.float64))
    a = np.atleast_2d(np.asarray(accel, dtype=np.float64))
    if h.shape != a.shape or h.shape[-1] != 3:
        raise TrimagInputError(f"field and accelerometer must both have shape (N, 3); got {h.shape} and {a.shape}")
    d = -a / np.linalg.norm(a, axis=1, keepdims=True)
    east = np.cross(d, h)
    east /= np.linalg.norm(east, axis=1, keepdims=True)
    north = np.cross(east, d)
    psi = np.degrees(np.arctan2(east[:, 0], north[:, 0])) + declination_deg
    return np.asarray(np.mod(psi, 360.0), dtype=np.float64)


def heading_difference(a_deg: ArrayLike, b_deg: ArrayLike) -> NDArray[np.float64]:
    """``a - b`` wrapped into [-180, 180) degrees (359 against 1 is -2, not 358)."""
    diff = np.asarray(a_deg, dtype=np.float64) - np.asarray(b_deg, dtype=np.float64)
    return np.asarray(np.mod(diff + 180.0, 360.0) - 180.0, dtype=np.float64)


def heading_error_stats(estimate_deg: ArrayLike, reference_deg: ArrayLike) -> dict[str, float]:
    """RMS, maximum absolute, mean and standard deviation (degrees) of the wrapped heading error."""
    e = heading_difference(estimate_deg, reference_deg)
    return {"heading_error_rms_deg": float(np.sqrt(np.mean(e**2))),
            "heading_error_max_deg": float(np.max(np.abs(e))),
            "heading_error_mean_deg": float(np.mean(e)),
            "heading_error_std_deg": float(np.std(e))}


def deviation_card(
    reference_deg: ArrayLike, before_deg: ArrayLike, after_deg: ArrayLike | None = None, *, step_deg: float = 15.0,
    after_sigma: Any = None,
) -> dict[str, Any]:
    """A compass deviation card: the heading error against the heading, before and after a calibration.

    The samples are put into bins of ``step_deg`` of the reference heading (centred on 0, 15, 30 ... degrees); each
    bin gives the mean and RMS of the wrapped errors ``before - reference`` and ``after - reference`` (degrees; the
    deviation with the sign of compass minus reference). Bins without samples are kept, with ``n = 0`` and empty
    (None) values. Without an independent reference (a level turn has none), the calibrated heading is the reference:
    ``after`` is then None and the card gives the deviation of the compass before, and the heading error the new
    calibration predicts (``after_sigma``).

    Parameters
    ----------
    reference_deg, before_deg : array_like, shape (N,)
        The reference heading and the compass heading before, degrees.
    after_deg : array_like, shape (N,), optional
        The compass heading after the calibration, degrees.
    step_deg : float
        Bin width, degrees (a divisor of 360, at most 90).
    after_sigma : callable, optional
        ``after_sigma(headings_deg) -> sigma_deg``: the heading error the calibration predicts (1 sigma) at each
        bin's heading (:func:`predicted_heading_sigma`), stored as ``after_sigma_deg``.

    Returns
    -------
    dict
        ``headings_deg`` (bin centres), ``n``, ``before_mean_deg``, ``before_rms_deg`` (per bin), ``before`` (the
        whole log, :func:`heading_error_stats`), the same for ``after`` when given, and ``after_sigma_deg`` (or None).
    """
    if not (0 < step_deg <= 90 and abs(360.0 / step_deg - round(360.0 / step_deg)) < 1e-9):
        raise TrimagInputError(f"the deviation card's step must divide 360 degrees; got {step_deg}")
    ref = np.asarray(reference_deg, dtype=np.float64)
    centres = np.arange(0.0, 360.0, step_deg)
    k = np.mod(np.round(np.mod(ref, 360.0) / step_deg), len(centres)).astype(int)
    n = np.bincount(k, minlength=len(centres))
    card: dict[str, Any] = {"headings_deg": centres.tolist(), "n": n.tolist(), "step_deg": float(step_deg)}
    for name, heading in (("before", before_deg), ("after", after_deg)):
        if heading is None:
            card[name] = None
            continue
        e = heading_difference(heading, ref)
        total = np.bincount(k, weights=e, minlength=len(centres))
        squares = np.bincount(k, weights=e * e, minlength=len(centres))
        with np.errstate(invalid="ignore", divide="ignore"):
            mean, rms = total / n, np.sqrt(squares / n)
        card[f"{name}_mean_deg"] = [float(v) if c else None for v, c in zip(mean, n, strict=True)]
        card[f"{name}_rms_deg"] = [float(v) if c else None for v, c in zip(rms, n, strict=True)]
        card[name] = heading_error_stats(heading, ref)
    card["after_sigma_deg"] = None if after_sigma is None else [float(v) for v in after_sigma(centres)]
    return card


def deviation_table(card: dict[str, Any]) -> str:
    """The deviation card as text: one line per heading bin with samples, then the whole log (degrees)."""
    sigma, after = card.get("after_sigma_deg"), card.get("after")
    head = f"{'heading':>8}{'n':>6}{'before: mean':>14}{'rms':>7}"
    head += f"{'after: mean':>13}{'rms':>7}" if after else ""
    head += f"{'after: predicted 1 sigma':>26}" if sigma else ""
    lines = [head + "   [deg]"]
    for k, centre in enumerate(card["headings_deg"]):
        if not card["n"][k]:
            continue
        line = f"{centre:8.0f}{card['n'][k]:6d}{card['before_mean_deg'][k]:14.2f}{card['before_rms_deg'][k]:7.2f}"
        line += f"{card['after_mean_deg'][k]:13.2f}{card['after_rms_deg'][k]:7.2f}" if after else ""
        lines.append(line + (f"{sigma[k]:26.3f}" if sigma else ""))
    b = card["before"]
    last = f"{'all':>8}{sum(card['n']):6d}{b['heading_error_mean_deg']:14.2f}{b['heading_error_rms_deg']:7.2f}"
    if after:
        last += f"{after['heading_error_mean_deg']:13.2f}{after['heading_error_rms_deg']:7.2f}"
    if sigma:
        last += f"{float(np.sqrt(np.mean(np.square(sigma)))):26.3f}"
    return "\n".join([*lines, last])


__all__ += ["deviation_card", "deviation_table", "heading_difference", "heading_error_stats",
            "tilt_compensated_heading"]
