"""The halves check of a firmware-space fit (:mod:`trimag.vehicle.firmware`): does the chosen level predict data it
was not fitted to better than the calibration the vehicle already has?

The level choice's held-out folds all lie within the log; a log whose field changed part-way (an aircraft handled on
the ground beside metal, a battery or payload moved) passes them. Here the chosen level (its motor term, its
identified directions) is refitted on each half of the log and each half's parameters are put through the
firmware's own formula (:meth:`~trimag.models.firmware.FirmwareCompass.correct`: ArduPilot
``AP_Compass_Backend::correct_field``, PX4 ``Magnetometer::Correct``) on the **other** half, against the log's
calibration in force on that same half, with the fit's own residual (vector, heading-free or magnitude):

- **worse than the log's**: on either half, the other half's fit leaves more than ``1 + HALVES_TOLERANCE`` times the
  log's RMS: the fit is not shown to improve on what the vehicle has. When, on such a half, the whole log's fit (what
  would be written) is itself worse than the log's calibration (``refuse``), it would make the vehicle worse where its
  calibration held: :func:`trimag.vehicle.firmware.fit_firmware` refuses it under ``level="auto"`` (exit 3, keep the
  log's, as it refuses a level that does not beat the log's on the folds); otherwise it is a warning (the whole fit
  improves both halves, but neither half predicts the other: its gain on a new flight is unproven);
- **moved**: the halves' parameters differ beyond their sigmas by a large margin (``z = (p2 - p1) / sqrt(s1^2 +
  s2^2)`` over :data:`HALVES_Z`, twice the general fit's :func:`~trimag.quality.honesty.drift_check` threshold: the
  sigmas from ``s^2 (J^T J)^-1`` times the residuals' correlation time understate a log's halves about 2x on simulated
  flights logged as int16 with attitude errors) and the change matters: on a half, the other half's fit leaves more
  than :data:`HALVES_MOVED_RATIO` times the whole log's fit's RMS (a heading-free full level on half a steady
  simulated flight moves its parameters 10-20 sigma along a shallow valley, yet predicts the other half within 1.3x):
  a warning.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..models.firmware import FirmwareCompass, rotation_matrix
from ..quality.honesty import DRIFT_Z, correlation_time
from ._firmware_levels import LevelProblem, LevelSolution

__all__ = ["HALVES_MIN_SAMPLES", "HALVES_MOVED_RATIO", "HALVES_TOLERANCE", "HALVES_Z", "firmware_rms", "halves_check",
           "halves_message"]

#: The other half's fit is "worse than the log's" when its RMS exceeds the log's by more than this fraction (a fit on
#: half the data carries its own estimation error: a log whose calibration is right is already told to keep it).
HALVES_TOLERANCE = 0.1
#: Parameters that moved between the halves are reported only when, on a half, the other half's fit leaves more than
#: this times the whole log's fit's RMS there (a significant but harmless change is not a finding).
HALVES_MOVED_RATIO = 1.5
#: A parameter moved between the halves beyond this many of their sigmas (and :data:`HALVES_MOVED_RATIO`) is named.
HALVES_Z = 2.0 * DRIFT_Z
#: Gauss-Newton steps of a half's fit from the whole log's solution: the half's own minimum near it (a heading-free
#: full level on half a steady simulated flight has another, 5 % lower, 900 mGauss of offsets away).
HALF_STEPS = 5
#: Fewer samples than this in the log: the halves are not checked (said so in the record).
HALVES_MIN_SAMPLES = 50


def firmware_rms(compass: FirmwareCompass, raw_sensor: NDArray[np.float64], field: NDArray[np.float64],
                 motors: Mapping[str, NDArray[np.float64]], tilt: NDArray[np.float64] | None) -> float:
    """RMS of the fit's residual of ``compass`` (the firmware's formula) on raw readings in the sensor frame.

    ``field``: the body-frame field (N, 3) or its magnitude (N,); ``tilt`` (N, 3, 3, body -> level, roll and pitch):
    the heading-free residual (horizontal and vertical components), as the fit's."""
    x = motors.get(compass.motor_type) if compass.motor_type else None
    B = compass.correct(raw_sensor, x)
    if field.ndim == 1:
        return float(np.sqrt(np.mean((np.linalg.norm(B, axis=1) - field) ** 2)))
    if tilt is not None:
        L = np.einsum("nij,nj->ni", tilt, B)
        H = np.einsum("nij,nj->ni", tilt, field)
        d = np.column_stack([np.hypot(L[:, 0], L[:, 1]) - np.hypot(H[:, 0], H[:, 1]), L[:, 2] - H[:, 2]])
        return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
    return float(np.sqrt(np.mean(np.sum((B - field) ** 2, axis=1))))


def _fit_half(problem: LevelProblem, sol: LevelSolution, bounds: Any, rows: NDArray[np.int64],
              scales: NDArray[np.float64], identified: Mapping[str, float], F: float) -> LevelSolution:
    """The chosen level refitted on ``rows``, as the fit does a level: within the directions the whole log
    identified, those this half identifies too (the fit's own rule, :data:`trimag.vehicle.firmware.IDENTIFIED`, from
    the covariance at the half's solution); the others are held at the whole log's solution (half a log may not
    identify what all of it does, and a direction it does not identify wanders off and would read as a change)."""
    whole = sol.basis if sol.basis is not None else np.eye(problem.n_params)
    part = problem.solve_in(sol.theta, whole, scales, rows=rows, max_steps=HALF_STEPS)
    del bounds
    r = part.residual
    J = (part.jacobian * scales) @ whole
    tau = max(1.0, max(correlation_time(s) for s in r.reshape(-1, problem.width).T))
    s2 = float(r @ r) / max(len(r) - whole.shape[1], 1) * tau
    eigval, eigvec = np.linalg.eigh(np.linalg.pinv(J.T @ J) * s2)
    limit = max(float(np.sqrt(np.mean(r**2))), identified["fraction"] * F)
    good = np.sqrt(np.clip(eigval, 0, None)) <= identified["noise_factor"] * limit
    if good.all():
        return part
    return problem.solve_in(sol.theta, whole @ eigvec[:, good], scales, rows=rows)


def _half_covariance(problem: LevelProblem, sol: LevelSolution) -> NDArray[np.float64]:
    """``s^2 (J^T J)^-1`` of a half's parameters (within its identified directions), times the residuals'
    correlation time."""
    series = sol.residual.reshape(-1, problem.width).T
    tau = max(1.0, max(correlation_time(s) for s in series))
    if sol.basis is not None and sol.scales is not None:
        B = sol.scales[:, None] * sol.basis
        J = sol.jacobian @ B
        cov = np.asarray(B @ np.linalg.pinv(J.T @ J) @ B.T, dtype=np.float64)
        dof = max(len(sol.residual) - sol.basis.shape[1], 1)
    else:
        cov = np.asarray(np.linalg.pinv(sol.jacobian.T @ sol.jacobian), dtype=np.float64)
        dof = max(len(sol.residual) - sol.jacobian.shape[1], 1)
    return np.asarray(cov * float(sol.residual @ sol.residual) / dof * tau, dtype=np.float64)


def halves_check(
    problem: LevelProblem, sol: LevelSolution, bounds: Any, to_compass: Callable[[LevelSolution], FirmwareCompass],
    held: FirmwareCompass, raw: NDArray[np.float64], field: NDArray[np.float64],
    motors: Mapping[str, NDArray[np.float64]], tilt: NDArray[np.float64] | None, applied: int | None,
    names: list[str], effect_scales: NDArray[np.float64], F: float, identified: Mapping[str, float],
) -> dict[str, Any]:
    """Refit the chosen level on each half and judge it on the other (module docstring).

    Parameters
    ----------
    problem, sol, bounds
        The chosen level's problem (all samples), its solution and the bounds it was solved with.
    to_compass
        A solution -> the firmware's parameters (as the fit writes them).
    held
        The calibration in force in the log.
    raw : ndarray, shape (N, 3)
        The readings as the fit received them (rotated by ``applied``), firmware unit.
    field, tilt
        The body-frame field (N, 3) or magnitude (N,), and the heading-free rotations (or None).
    names, effect_scales
        The firmware's name of each parameter and how much one unit of it moves the field.
    F : float
        The field's magnitude.
    identified : mapping
        The fit's rule for an identified direction (:data:`trimag.vehicle.firmware.IDENTIFIED`).

    Returns
    -------
    dict
        ``first``/``second``: ``rows``, ``rms_log`` (the log's calibration), ``rms_other_half_fit`` (the other half's
        parameters), ``rms_whole_fit`` (the chosen level on the whole log); ``worse_than_log`` (the halves where the
        other half's fit is worse), ``refuse`` (those where the whole log's fit is worse than the log's too), ``z``
        and ``change`` per parameter, ``moved``, ``flagged``.
    """
    n = len(raw)
    if n < HALVES_MIN_SAMPLES:
        return {"checked": False, "flagged": False, "worse_than_log": [], "refuse": [], "moved": [],
                "note": f"{n} samples: the halves are checked from {HALVES_MIN_SAMPLES}"}
    R0 = np.eye(3) if applied is None else rotation_matrix(held.target, applied)
    sensor = raw @ R0  # the raw readings in the sensor's own frame (the firmware's formula rotates them)
    halves = (np.arange(n // 2), np.arange(n // 2, n))
    fits = [_fit_half(problem, sol, bounds, rows, effect_scales, identified, F) for rows in halves]
    whole = to_compass(sol)
    out: dict[str, Any] = {"checked": True, "tolerance": HALVES_TOLERANCE}
    worse, refuse = [], []
    for k, (name, rows) in enumerate(zip(("first", "second"), halves, strict=True)):
        part = {kind: v[rows] for kind, v in motors.items()}
        t = None if tilt is None else tilt[rows]
        rms_log = firmware_rms(held, sensor[rows], field[rows], part, t)
        rms_other = firmware_rms(to_compass(fits[1 - k]), sensor[rows], field[rows], part, t)
        out[name] = {"rows": [int(rows[0]), int(rows[-1]) + 1], "rms_log": rms_log, "rms_other_half_fit": rms_other,
                     "rms_whole_fit": firmware_rms(whole, sensor[rows], field[rows], part, t)}
        if rms_other > (1.0 + HALVES_TOLERANCE) * rms_log:
            worse.append(name)
            if out[name]["rms_whole_fit"] > rms_log:
                refuse.append(name)
    d = fits[1].theta - fits[0].theta
    var = np.diag(_half_covariance(problem, fits[0]) + _half_covariance(problem, fits[1]))
    fitted = var > 0
    z = np.where(fitted, d / np.sqrt(np.where(fitted, var, 1.0)), 0.0)
    matters = any(out[k]["rms_other_half_fit"] > HALVES_MOVED_RATIO * out[k]["rms_whole_fit"]
                  for k in ("first", "second"))
    moved = [names[i] for i in range(len(d)) if abs(z[i]) > HALVES_Z] if matters else []
    out.update(worse_than_log=worse, refuse=refuse, z=dict(zip(names, z.tolist(), strict=True)),
               change=dict(zip(names, d.tolist(), strict=True)), moved=moved, flagged=bool(worse or moved),
               z_threshold=HALVES_Z, moved_ratio=HALVES_MOVED_RATIO)
    return out


def halves_message(halves: dict[str, Any], level: str, unit: str) -> str:
    """One line: what the halves say, their numbers and the likely cause."""
    first, second = halves["first"], halves["second"]
    numbers = (f"on the first half the second half's fit leaves {first['rms_other_half_fit']:.4g} against the log's "
               f"calibration's {first['rms_log']:.4g}, on the second half the first half's fit leaves "
               f"{second['rms_other_half_fit']:.4g} against {second['rms_log']:.4g} {unit}")
    cause = ("the field or the vehicle changed between the halves (handled beside metal, a battery or payload moved, "
             "the log's own processing changed)")
    head = (f"refitted on each half of the log, the {level} level predicts the other half worse than the log's own "
            f"calibration ({numbers})")
    if halves["refuse"]:
        k = halves["refuse"][0]
        return (f"{head}, and the whole log's fit is worse than the log's on the {k} half too "
                f"({halves[k]['rms_whole_fit']:.4g} against {halves[k]['rms_log']:.4g} {unit}): {cause}; keep the "
                "log's calibration, fit the part that matches the vehicle as it flies (`--rows`), or record a "
                "calibration flight away from metal")
    if halves["worse_than_log"]:
        return (f"{head}, though the whole log's fit improves on it on both halves ({first['rms_whole_fit']:.4g} and "
                f"{second['rms_whole_fit']:.4g} {unit}): {cause}, or the halves saw different conditions (currents, "
                "attitudes); its gain on another flight is unproven: check it on a calibration flight away from metal")
    z, change = halves["z"], halves["change"]
    parts = [f"{k} by {change[k]:.4g} ({abs(z[k]):.1f} sigma)"
             for k in sorted(halves["moved"], key=lambda k: -abs(z[k]))]
    return (f"refitted on each half of the log, the {level} level's parameters move beyond their sigmas "
            f"({', '.join(parts[:4])}{' ...' if len(parts) > 4 else ''}; {numbers}): {cause}; each half still "
            "improves on the log's calibration, but record a calibration flight away from metal to be sure")
