"""Firmware-space fits (``trimag fit --target ardupilot|px4``, issue 30): exactly the parameters the autopilot loads,
within its limits, at the level the data identify.

The parameters and each firmware's formula are :mod:`trimag.models.firmware` (ArduPilot
``AP_Compass_Backend::correct_field``, PX4 ``Magnetometer::Correct``); the levels and their residuals are
:mod:`trimag.vehicle._firmware_levels`. The fit:

1. **Orientation** (vector residual only: a magnitude cannot see it). Every standard rotation of the target's enum
   is tried with one scale and the offsets; the log's own orientation is kept unless another fits the field at least
   :data:`SWITCH_RATIO` times better. The rotation the standard one leaves (the rotation of the unconstrained affine
   fit's polar factor: left for ArduPilot, whose matrix acts after the rotation; right for PX4, whose rotation acts
   last) is left to the symmetric matrix only up to :data:`ORIENTATION_TOLERANCE_DEG`; beyond it by more than two
   of its standard deviations, the fit is refused naming the angle. An internal compass (ArduPilot
   ``COMPASS_EXTERNALn`` = 0, PX4 ``CAL_MAGn_ROT`` = -1) follows
   the board's rotation: its orientation is kept and a better one is only reported.
2. **Levels** (:data:`~trimag.vehicle.firmware_levels.LEVELS`, each with and without the motor term): each is fitted
   on all samples and on :data:`N_FOLDS` contiguous folds (fitted on the others, evaluated on the one left out); a
   level is *identified* when its parameters' standard deviations are within :data:`IDENTIFIED` (of the field for
   offsets and motor terms over the logged range, absolute for the matrix); ``level="auto"`` picks the simplest
   identified level within the firmware's limits whose held-out RMS is within :data:`AUTO_TOLERANCE` of the best.
3. **Limits**: a level whose unconstrained solution the firmware cannot load is refitted with bounds (trust-region
   least squares): the parameters at a bound are named; a calibration still outside the limits is refused naming
   the parameter and the limit (:meth:`~trimag.models.firmware.FirmwareCompass.violations`). A scale more than
   :data:`SCALE_CONTRADICTION` times off the reference field is refused first: the reference (or the unit) is wrong.
4. **Uncertainty**: ``s^2 (J^T J)^-1`` of the level's parameters, inflated like every fit's
   (:func:`trimag.quality.honesty.correlation_time` of the residuals, repeated rows), propagated to the firmware's
   parameters and recorded with :func:`trimag.calibration.make_uncertainty`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..calibration import Calibration, jsonable, make_uncertainty
from ..errors import IdentifiabilityError, TrimagInputError
from ..models.firmware import ORIENTATION_TOLERANCE_DEG, FirmwareCompass, firmware_class, rotation_matrix
from ..quality.honesty import correlation_time, count_repeated_rows
from ..units import convert
from ._firmware_levels import LEVELS, LevelProblem, LevelSolution

__all__ = [
    "AUTO_TOLERANCE",
    "IDENTIFIED",
    "LEVELS",
    "N_FOLDS",
    "ORIENTATION_TOLERANCE_DEG",
    "FirmwareFit",
    "firmware_calibration",
    "fit_firmware",
    "level_table",
]

#: Another orientation replaces the log's only when it fits the field this many times better (RMS).
SWITCH_RATIO = 2.0
#: Contiguous folds of the held-out RMS.
N_FOLDS = 5
#: auto: the simplest level whose held-out RMS is within this fraction of the best.
AUTO_TOLERANCE = 0.02
#: A level is identified when one standard deviation of each parameter moves the corrected field by less than the
#: residual noise per axis (or ``fraction`` of the field, if larger), and the column-scaled condition number of its
#: Jacobian is below ``condition`` (:func:`_identified`).
IDENTIFIED = {"fraction": 0.005, "condition": 1e7}
#: A fitted scale beyond this factor (either way) of the reference contradicts it: refused before any limit.
SCALE_CONTRADICTION = 2.0
_MOTOR_KINDS = ("current", "throttle")


@dataclass
class FirmwareFit:
    """The result of :func:`fit_firmware`.

    Attributes
    ----------
    compass : FirmwareCompass
        The parameters (:mod:`trimag.models.firmware`).
    level : str
        The level chosen (or asked for).
    table : list of dict
        One row per level tried: ``level``, ``motor``, ``n_params``, ``rms``, ``heldout_rms``, ``identified``,
        ``within_limits``, ``at_limit`` (parameter names), ``chosen``, ``note``.
    param_std : dict
        Standard deviation of each fitted firmware parameter (its name at instance 0), firmware unit.
    covariance, covariance_order
        The fitted parameters' covariance.
    held : dict
        Parameters held at the firmware's values (name -> value).
    orientation : dict
        How the orientation was decided (``kept``/``chosen``, ``candidates``, ``remaining_angle_deg``, ...).
    residual_kind : str
        ``"vector"`` or ``"magnitude"``.
    rms_before, rms_after : float
        RMS of the residual with the firmware's calibration in the log (or none) and with the fit, firmware unit.
    P_u, P_h : ndarray, shape (3, 3)
        Raw input -> firmware frame, body -> fit frame (``B~ = P_h B``).
    motor_mean : float
        Mean of the motor channel over the samples (0 without one).
    inflation : dict
        The uncertainty inflation (as :func:`trimag.quality.honesty.honest_uncertainty` records it).
    messages : list of str
    """

    compass: FirmwareCompass
    level: str
    table: list[dict[str, Any]]
    param_std: dict[str, float]
    covariance: NDArray[np.float64]
    covariance_order: list[str]
    held: dict[str, float]
    orientation: dict[str, Any]
    residual_kind: str
    rms_before: float
    rms_after: float
    P_u: NDArray[np.float64]
    P_h: NDArray[np.float64]
    motor_mean: float
    inflation: dict[str, Any]
    noise_std: float
    n_samples: int = 0
    messages: list[str] = field(default_factory=list)

    def affine(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``(W, b, m_body)`` with ``B = W (v - b) + m_body x`` for raw input ``v`` (the calibration's form)."""
        A, o, m = self.compass.algebra()
        W = self.P_h.T @ A @ self.P_u
        return W, -self.P_u.T @ o, self.P_h.T @ m


@dataclass
class _Frame:
    """The fit's frame for one orientation: ``u = P_u v``, target ``P_h h``."""

    orientation: int
    P_u: NDArray[np.float64]
    P_h: NDArray[np.float64]


def _frame(target: str, orientation: int, applied: int | None) -> _Frame:
    R = rotation_matrix(target, orientation)
    R0 = np.eye(3) if applied is None else rotation_matrix(target, applied)
    if target == "ardupilot":
        return _Frame(orientation, R @ R0.T, np.eye(3))
    return _Frame(orientation, R0.T, R.T)


def _unique_rotations(target: str) -> list[int]:
    """The enum values with distinct matrices (the lower number of a repeated one)."""
    out: list[int] = []
    seen: list[NDArray[np.float64]] = []
    for value in sorted(firmware_class(target).rotations):
        R = rotation_matrix(target, value)
        if not any(np.allclose(R, S, atol=1e-9) for S in seen):
            out.append(value)
            seen.append(R)
    return out


def _scale_rms(u: NDArray[np.float64], h: NDArray[np.float64]) -> tuple[float, float]:
    """RMS of ``l u + c - h`` at its least-squares ``(l, c)`` (the orientation test), and ``l``."""
    n = len(u)
    design = np.zeros((n, 3, 4))
    design[:, :, 0] = u
    design[:, :, 1:] = np.eye(3)
    X, *_ = np.linalg.lstsq(design.reshape(3 * n, 4), h.ravel(), rcond=None)
    r = design.reshape(3 * n, 4) @ X - h.ravel()
    return float(np.sqrt(np.mean(r**2) * 3)), float(X[0])


def _polar_angle(G: NDArray[np.float64]) -> float:
    """Angle (degrees) of the rotation ``Q`` of ``G = P Q`` (ArduPilot: the matrix after the rotation), which is
    also the ``Q`` of ``G = Q P`` (PX4: the rotation last): ``U S V^T = (U S U^T)(U V^T) = (U V^T)(V S V^T)``."""
    U, _, Vt = np.linalg.svd(G)
    Q = U @ Vt
    return float(np.degrees(np.arccos(np.clip((np.trace(Q) - 1.0) / 2.0, -1.0, 1.0))))


def _choose_orientation(
    target: str, raw: NDArray[np.float64], h: NDArray[np.float64], held: FirmwareCompass, applied: int | None,
    external: bool, tolerance_deg: float, motors: Mapping[str, NDArray[np.float64]],
) -> tuple[_Frame, dict[str, Any], list[str]]:
    """The orientation (step 1 of the module docstring) and what was decided."""
    results = []
    scales = {}
    for value in _unique_rotations(target):
        fr = _frame(target, value, applied)
        rms, scales[value] = _scale_rms(raw @ fr.P_u.T, h @ fr.P_h.T)
        results.append((rms if scales[value] > 0 else np.inf, value))
    results.sort()
    best_rms, best = results[0]
    _refuse_contradicted_scale(scales[best], float(np.median(np.linalg.norm(h, axis=1))), type(held))
    current = int(held.orientation)
    current_rms = next(r for r, v in results if v == current)
    name = type(held)(orientation=best).rotation_name
    messages: list[str] = []
    info: dict[str, Any] = {"log_value": current, "best_value": best, "best_rms": best_rms,
                            "log_rms": current_rms, "external": external}
    chosen = current
    if best != current and current_rms > SWITCH_RATIO * best_rms:
        if external:
            chosen = best
            messages.append(f"orientation: {name} ({best}) fits the field {current_rms / best_rms:.3g}x better than "
                            f"the log's {current}: chosen")
        else:
            messages.append(f"warning: the field fits {name} ({best}) {current_rms / best_rms:.3g}x better than the "
                            f"log's {current}, but this compass is internal: its orientation follows the board's "
                            "(AHRS_ORIENTATION / SENS_BOARD_ROT); check the board's orientation")
    info["decision"] = "chosen" if chosen != current else "kept"
    fr = _frame(target, chosen, applied)
    info["value"] = chosen
    angle, sigma = _remaining_angle(raw @ fr.P_u.T, h @ fr.P_h.T, motors)
    info["remaining_angle_deg"], info["remaining_angle_sigma_deg"] = angle, sigma
    if angle is not None and sigma is not None:
        messages.append(f"orientation: the nearest standard rotation leaves {angle:.1f} +- {sigma:.1f} deg, left to "
                        "the symmetric matrix (it stays as a heading error of about that size)")
    if angle is not None and sigma is not None and angle - 2.0 * sigma > tolerance_deg:
        chosen_name = type(held)(orientation=chosen).rotation_name
        raise TrimagInputError(
            f"the compass is rotated {angle:.1f} deg from the nearest standard orientation {chosen_name} ({chosen}); "
            f"the symmetric matrix the firmware takes leaves at most {tolerance_deg:g} deg to it: mount the compass "
            "square to the vehicle (or set a custom rotation: ArduPilot COMPASS_ORIENT 101 with CUST_ROT1_*, PX4 "
            "CAL_MAGn_ROT 100 with CAL_MAGn_ROLL/PITCH/YAW) and record again"
        )
    return fr, info, messages


def _remaining_angle(u: NDArray[np.float64], h: NDArray[np.float64],
                     motors: Mapping[str, NDArray[np.float64]]) -> tuple[float | None, float | None]:
    """The rotation (degrees) of the unconstrained affine fit ``h = G u + c (+ motor terms)`` and its standard
    deviation; None when it is not measured to half of :data:`ORIENTATION_TOLERANCE_DEG`."""
    design = np.column_stack([u, np.ones(len(u)), *motors.values()])
    X, *_ = np.linalg.lstsq(design, h, rcond=None)
    r = h - design @ X
    s2 = float(np.sum(r**2)) / max(3 * (len(u) - design.shape[1]), 1)
    try:
        var = np.diag(np.linalg.inv(design.T @ design))[:3] * s2
    except np.linalg.LinAlgError:
        return None, None
    sigma = float(np.degrees(np.sqrt(np.max(var)) / max(float(np.median(np.linalg.norm(h, axis=1))), 1e-300)
                             * np.sqrt(np.mean(np.linalg.norm(u, axis=1) ** 2))))
    if not sigma < ORIENTATION_TOLERANCE_DEG / 2:
        return None, sigma
    return _polar_angle(np.asarray(X[:3].T, dtype=np.float64)), sigma


# ------------------------------------------------------------------ the uncertainty of one level
def _inflation(residual: NDArray[np.float64], vector: bool, raw: NDArray[np.float64]) -> dict[str, Any]:
    """The honest inflation (:mod:`trimag.quality.honesty`) of a level's covariance."""
    series = residual.reshape(-1, 3).T if vector else residual[None, :]
    n = series.shape[1]
    window = slice(max(0, (n - 4096) // 2), max(0, (n - 4096) // 2) + 4096)
    tau = max(correlation_time(s[window]) for s in series)
    repeats = count_repeated_rows(raw[:20_000])
    factors: dict[str, float] = {}
    if tau > 1.0:
        factors["correlated_residuals"] = tau
    if repeats:
        factors["repeated_rows"] = len(raw) / max(len(raw) - repeats, 1)
    total = float(np.prod(list(factors.values()))) if factors else 1.0
    return {"total": total, **factors, "n_distinct": len(raw) - repeats,
            "note": "covariance x total (trimag.quality.honesty): repeated rows, correlated residuals"}


def _covariance(sol: LevelSolution, total: float) -> tuple[NDArray[np.float64], float]:
    J, r = sol.jacobian, sol.residual
    dof = max(len(r) - J.shape[1], 1)
    s2 = float(r @ r) / dof
    cov = np.linalg.pinv(J.T @ J) * s2 * total
    return cov, float(np.sqrt(s2))


def _condition(J: NDArray[np.float64]) -> float:
    norms = np.linalg.norm(J, axis=0)
    if np.any(norms == 0):
        return float("inf")
    s = np.linalg.svd(J / norms, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def _identified(problem: LevelProblem, sol: LevelSolution, cov: NDArray[np.float64], F: float, x_range: float,
                noise: float) -> tuple[bool, list[str]]:
    """Whether the level's parameters are identified (:data:`IDENTIFIED`), and the names of those that are not.

    A parameter is identified when one standard deviation of it moves the corrected field by less than the fit's
    own residual noise per axis ``noise`` (or ``IDENTIFIED["fraction"]`` of the field ``F``, if larger): an offset
    by its sigma, a matrix entry by sigma x F, a motor term by sigma x half the logged range ``x_range``.
    """
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    weak = []
    if _condition(sol.jacobian) > IDENTIFIED["condition"]:
        weak.append("condition")
    limit = max(noise, IDENTIFIED["fraction"] * F)
    for name, s in zip(problem.names(), std, strict=True):
        if name.startswith("o_"):
            moved = s
        elif name.startswith("m_"):
            moved = s * x_range / 2.0
        else:
            moved = s * F
        if not moved <= limit:
            weak.append(name)
    return not weak, weak


# ------------------------------------------------------------------ one level: fit, limits, held-out RMS
@dataclass
class _Candidate:
    level: str
    motor: str | None
    problem: LevelProblem
    solution: LevelSolution
    compass: FirmwareCompass
    covariance: NDArray[np.float64]
    noise: float
    inflation: dict[str, Any]
    identified: bool
    weak: list[str]
    violations: list[str]
    at_limit: list[str]
    heldout_rms: float
    held_motor: bool = False


def _bounds(problem: LevelProblem, klass: type[FirmwareCompass], held_scale: float,
            offsets_max: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Box bounds of a level's parameters that keep the firmware's limits (module docstring, step 3)."""
    lo = np.full(problem.n_params, -np.inf)
    hi = np.full(problem.n_params, np.inf)
    ap = klass.target == "ardupilot"
    diag_lo, diag_hi = (0.2 / 1.5, 5.0 * 1.5) if ap else (0.1, 3.0)
    for k, name in enumerate(problem.names()):
        if name == "l":
            lo[k], hi[k] = ((1 / 1.5) / held_scale, 1.5 / held_scale) if ap else (0.1, 3.0)
        elif name.startswith("d_") or name in ("A_xx", "A_yy", "A_zz"):
            lo[k], hi[k] = diag_lo, diag_hi
        elif name.startswith("A_") and ap:
            lo[k], hi[k] = -1.5, 1.5
        elif name.startswith("o_") and ap:
            lo[k], hi[k] = -offsets_max, offsets_max
        elif name.startswith("m_") and ap:
            lo[k], hi[k] = -1000.0, 1000.0
    return lo, hi


def _compass(klass: type[FirmwareCompass], sol: LevelSolution, level: str, orientation: int, motor: str | None,
             held: FirmwareCompass | None, held_motor: bool = False) -> FirmwareCompass:
    """The firmware parameters of a solution; the lower levels keep the held values exactly, and ``held_motor``
    keeps the firmware's own motor term."""
    if held is not None and level in ("offsets", "scale") and held.orientation == orientation:
        A, o, m = sol.A, sol.o, sol.m
        base = klass.from_algebra(A, o, m, orientation=orientation, motor_type=motor)
        changes: dict[str, Any] = {"offsets": base.offsets}
        if not held_motor:
            changes.update(motor=base.motor, motor_type=motor)
        if level == "scale":
            A_held = held.algebra()[0]
            ratio = float(np.sum(A * A_held) / np.sum(A_held * A_held))
            if klass.target == "ardupilot":
                s_eff = held.effective_scale  # type: ignore[attr-defined]
                changes["scale"] = ratio * s_eff
                if not np.any(held.diagonal):
                    changes["diagonal"] = np.ones(3)
            else:
                changes["diagonal"] = held.diagonal * ratio
                changes["offdiagonal"] = held.offdiagonal * ratio
        return dataclasses.replace(held, **changes)
    out = klass.from_algebra(sol.A, sol.o, sol.m, orientation=orientation, motor_type=motor)
    if held_motor and held is not None:
        out = dataclasses.replace(out, motor=held.motor, motor_type=held.motor_type)
    return out


def _folds(n: int) -> list[NDArray[np.int64]]:
    edges = np.linspace(0, n, N_FOLDS + 1).astype(int)
    return [np.arange(edges[k], edges[k + 1]) for k in range(N_FOLDS)]


def _heldout(problem: LevelProblem, sol: LevelSolution, bounds: Any) -> float:
    """RMS over every sample of the residual (vector length or magnitude) predicted by the fit on the other folds."""
    n = len(problem.u)
    if n < 5 * N_FOLDS:
        return float("nan")
    errors = []
    for fold in _folds(n):
        train = np.setdiff1d(np.arange(n), fold)
        try:
            part = problem.solve(sol.theta, rows=train, bounds=bounds)
        except (np.linalg.LinAlgError, ValueError):
            return float("inf")
        r = problem.residual(part.theta, rows=fold)
        errors.append(r.reshape(-1, 3) if problem.vector else r[:, None])
    e = np.concatenate(errors)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def _fit_level(
    level: str, motor: str | None, u: NDArray[np.float64], target: NDArray[np.float64],
    motor_values: Mapping[str, NDArray[np.float64]], klass: type[FirmwareCompass], held: FirmwareCompass,
    A_held: NDArray[np.float64], o_held: NDArray[np.float64], start: NDArray[np.float64] | None, orientation: int,
    offsets_max: float, raw: NDArray[np.float64], held_same_frame: bool,
) -> _Candidate:
    x = None if motor is None else motor_values[motor]
    fixed = None
    if motor is None and held.motor_type in motor_values and np.any(held.motor):
        # the firmware's own motor term is held (PX4's COMP with the held scale matrix: COMP acts inside S)
        fixed = motor_values[str(held.motor_type)][:, None] * held.algebra()[2]
    problem = LevelProblem(u, level, x, target, A_held, o_held, fixed)
    if problem.vector:
        p0 = problem.linear_start()
    elif start is not None:
        p0 = problem.pack(*start) if isinstance(start, tuple) else start
    else:
        p0 = problem.sphere_start()
    sol = problem.solve(p0)
    held_for_params = held if held_same_frame else None
    if fixed is not None:  # the fit kept the firmware's motor term: so do the parameters
        held_for_params = held
    compass = _compass(klass, sol, level, orientation, motor, held_for_params, fixed is not None)
    bounds = None
    if compass.violations(offsets_max=offsets_max):
        bounds = _bounds(problem, klass, held.effective_scale if klass.target == "ardupilot" else 1.0,  # type: ignore[attr-defined]
                         offsets_max)
        sol = problem.solve(sol.theta, bounds=bounds)
        compass = _compass(klass, sol, level, orientation, motor, held_for_params, fixed is not None)
    inflation = _inflation(sol.residual, problem.vector, raw)
    cov, noise = _covariance(sol, inflation["total"])
    F = float(np.median(np.linalg.norm(target, axis=1) if problem.vector else target))
    x_range = float(np.ptp(x)) if x is not None else 1.0
    per_axis = noise if not problem.vector else float(np.sqrt(np.mean(sol.residual**2)))
    identified, weak = _identified(problem, sol, cov, F, x_range, per_axis)
    names = problem.names()
    return _Candidate(level, motor, problem, sol, compass, cov, noise, inflation, identified, weak,
                      [str(v) for v in compass.violations(offsets_max=offsets_max)],
                      [names[k] for k in sol.at_bound], _heldout(problem, sol, bounds), fixed is not None)


# ------------------------------------------------------------------ the fit
def _check_inputs(raw: ArrayLike, field_body: ArrayLike | None, magnitude: ArrayLike | None,
                  motor_values: Mapping[str, ArrayLike] | None) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                                       dict[str, NDArray[np.float64]]]:
    v = np.asarray(raw, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise TrimagInputError(f"`raw` must be finite with shape (N, 3); got {v.shape}")
    if (field_body is None) == (magnitude is None):
        raise TrimagInputError("give either `field_body` (N, 3: the body-frame field, a flight with attitudes) or "
                               "`magnitude` (the field's magnitude), not both")
    if field_body is not None:
        target = np.asarray(field_body, dtype=np.float64)
        shape: tuple[int, ...] = (len(v), 3)
    else:
        target = np.broadcast_to(np.asarray(magnitude, dtype=np.float64), (len(v),)).copy()
        shape = (len(v),)
    if target.shape != shape or not np.isfinite(target).all():
        raise TrimagInputError(f"the reference must be finite with shape {shape}; got {target.shape}")
    motors: dict[str, NDArray[np.float64]] = {}
    for kind, values in (motor_values or {}).items():
        if kind not in _MOTOR_KINDS:
            raise TrimagInputError(f"motor channels are 'current' (A) or 'throttle' (0..1); got {kind!r}")
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape != (len(v),) or not np.isfinite(arr).all():
            raise TrimagInputError(f"the {kind} channel must be {len(v)} finite values")
        if np.ptp(arr) > 0:
            motors[kind] = arr
    n_min = 12 if target.ndim == 2 else 30
    if len(v) < n_min:
        raise IdentifiabilityError(f"{len(v)} samples: a firmware fit needs at least {n_min}; log the magnetometer "
                                   "longer or faster")
    return v, target, motors


def _motor_choices(motor: str, motors: Mapping[str, NDArray[np.float64]]) -> list[str | None]:
    if motor == "none":
        return [None]
    if motor == "auto":
        return [None, *motors]
    if motor not in motors:
        have = ", ".join(motors) or "none that varies"
        raise TrimagInputError(f"`motor={motor}` needs a logged {motor} channel that varies; this log has {have}")
    return [motor]


def fit_firmware(
    target: str, raw: ArrayLike, *, field_body: ArrayLike | None = None, magnitude: ArrayLike | None = None,
    motor_values: Mapping[str, ArrayLike] | None = None, held: FirmwareCompass | None = None,
    applied_orientation: int | None = None, external: bool = True, level: str = "auto", motor: str = "auto",
    tolerance_deg: float = ORIENTATION_TOLERANCE_DEG, offsets_max: float | None = None,
) -> FirmwareFit:
    """Fit ``target``'s parameters (see the module docstring).

    Parameters
    ----------
    target : {"ardupilot", "px4"}
    raw : array_like, shape (N, 3)
        Raw readings in the firmware's unit (mGauss, gauss), in the frame of the rotation ``applied_orientation``
        (an ArduPilot log's readings are rotated by the orientation in force; None: the sensor's own frame).
    field_body, magnitude : array_like
        The body-frame field (N, 3) at each sample (a flight with attitudes: vector residual) or its magnitude
        (N,) or () (magnitude residual; the orientation is then kept).
    motor_values : mapping, optional
        ``{"current": (N,) A, "throttle": (N,) 0..1}``: the channels a motor term may use.
    held : FirmwareCompass, optional
        The calibration the firmware had (from the log's parameters): the orientation and the values the lower levels
        hold. Default: orientation ``applied_orientation`` (or 0), identity matrix.
    external : bool
        False for an internal compass (its orientation is the board's: kept).
    level : {"auto", "offsets", "scale", "diagonal", "full"}
    motor : {"auto", "none", "current", "throttle"}
    tolerance_deg : float
        :data:`ORIENTATION_TOLERANCE_DEG`.
    offsets_max : float, optional
        ArduPilot's ``COMPASS_OFFS_MAX`` (default 1800).

    Raises
    ------
    TrimagInputError
        Bad input, a reference the data contradict, a rotation the firmware cannot hold, or no level within the
        firmware's limits (exit 2).
    IdentifiabilityError
        The data identify no level (or not the one asked for): exit 3, naming what is not identified.
    """
    klass = firmware_class(target)
    if level not in ("auto", *LEVELS):
        raise TrimagInputError(f"`level` must be auto, {', '.join(LEVELS)}; got {level!r}")
    if motor not in ("auto", "none", *_MOTOR_KINDS):
        raise TrimagInputError(f"`motor` must be auto, none, current or throttle; got {motor!r}")
    v, h, motors = _check_inputs(raw, field_body, magnitude, motor_values)
    if held is None:
        held = klass(orientation=applied_orientation or 0)
    if not isinstance(held, klass):
        raise TrimagInputError(f"`held` must be a {klass.__name__}")
    omax = float(offsets_max) if offsets_max else float(getattr(klass, "OFFSETS_MAX", np.inf))
    vector = h.ndim == 2
    messages: list[str] = []
    if vector:
        fr, orientation, more = _choose_orientation(target, v, h, held, applied_orientation, external, tolerance_deg,
                                                    motors)
        messages += more
    else:
        fr = _frame(target, int(held.orientation), applied_orientation)
        orientation = {"decision": "kept", "value": int(held.orientation), "log_value": int(held.orientation),
                       "note": "a magnitude-only fit cannot see the orientation"}
    u, hh = v @ fr.P_u.T, (h @ fr.P_h.T if vector else h)
    same_frame = fr.orientation == int(held.orientation)
    A_held, o_held, _ = held.algebra()
    if not same_frame:  # the held matrix and offsets seen in the new frame (module docstring of _firmware_levels)
        T = fr.P_u @ _frame(target, int(held.orientation), applied_orientation).P_u.T
        A_held, o_held = T @ A_held @ T.T, T @ o_held
    F = float(np.median(np.linalg.norm(hh, axis=1) if vector else hh))
    if not vector:
        _refuse_contradicted_scale(_sphere_scale(u, F), F, klass)
    table, candidates = _run_levels(level, motor, motors, u, hh, klass, held, A_held, o_held, fr.orientation, omax, v,
                                    same_frame)
    chosen = _choose(level, candidates)
    for row, cand in zip(table, candidates, strict=True):
        row["chosen"] = cand is chosen
    held_frame = _frame(target, int(held.orientation), applied_orientation)
    return _result(chosen, table, klass, held, fr, held_frame, orientation, vector, v, h, motors, messages, same_frame)


def _refuse_contradicted_scale(scale: float, F: float, klass: type[FirmwareCompass]) -> None:
    """Refuse a reference ``F`` the data contradict: the scale that maps the data's field onto it (the one-scale
    fit of the best orientation, or the reference over the radius of the sphere through the readings) more than
    :data:`SCALE_CONTRADICTION` times off 1."""
    ratio = 1.0 / abs(scale) if scale else float("inf")
    if not 1.0 / SCALE_CONTRADICTION <= ratio <= SCALE_CONTRADICTION:
        raise TrimagInputError(
            f"the data's field is {ratio:.3g}x the reference field ({F * ratio:.4g} against {F:.4g} {klass.unit}): "
            f"{klass.target} loads a scale within [0.667, 1.5] at most; the reference or the data's unit is wrong: "
            "give the field magnitude (`reference`) or the IGRF site, and the data, in the right unit"
        )


def _sphere_scale(u: NDArray[np.float64], F: float) -> float:
    """``F`` over the radius of the sphere through the readings (algebraic fit of ``|u - c|^2 = r^2``)."""
    design = np.column_stack([2.0 * u, np.ones(len(u))])
    X, *_ = np.linalg.lstsq(design, np.sum(u * u, axis=1), rcond=None)
    radius = float(np.sqrt(max(X[3] + X[:3] @ X[:3], 0.0)))  # |u|^2 = 2 u.c + (r^2 - |c|^2)
    return F / radius if radius > 0 else float("inf")


def _run_levels(
    level: str, motor: str, motors: Mapping[str, NDArray[np.float64]], u: NDArray[np.float64],
    target: NDArray[np.float64], klass: type[FirmwareCompass], held: FirmwareCompass, A_held: NDArray[np.float64],
    o_held: NDArray[np.float64], orientation: int, omax: float, raw: NDArray[np.float64], same_frame: bool,
) -> tuple[list[dict[str, Any]], list[_Candidate]]:
    levels = LEVELS if level == "auto" else (level,)
    table: list[dict[str, Any]] = []
    candidates: list[_Candidate] = []
    start: Any = None
    for lv in levels:
        for mk in _motor_choices(motor, motors):
            try:
                cand = _fit_level(lv, mk, u, target, motors, klass, held, A_held, o_held,
                                  start if mk is None else None, orientation, omax, raw, same_frame)
            except (IdentifiabilityError, np.linalg.LinAlgError):
                continue
            if mk is None:
                start = (cand.solution.A, cand.solution.o, cand.solution.m)
            candidates.append(cand)
            sol = cand.solution
            rms = float(np.sqrt(np.mean(sol.residual.reshape(len(u), -1) ** 2) * (3 if target.ndim == 2 else 1)))
            held_motor = "held" if cand.held_motor else None
            table.append({"level": lv, "motor": mk or held_motor, "n_params": cand.problem.n_params, "rms": rms,
                          "heldout_rms": cand.heldout_rms, "identified": cand.identified,
                          "not_identified": cand.weak, "within_limits": not cand.violations,
                          "violations": cand.violations, "at_limit": cand.at_limit, "chosen": False})
    return table, candidates


def _choose(level: str, candidates: list[_Candidate]) -> _Candidate:
    """The level chosen (module docstring, step 2), or the refusal."""
    usable = [c for c in candidates if c.identified and not c.violations]
    if not usable:
        outside = [c for c in candidates if c.identified and c.violations]
        if outside:
            raise TrimagInputError(
                f"the firmware cannot load this calibration: {outside[0].violations[0]} (level {outside[0].level}); "
                "move the compass away from iron or magnets, or check the reference"
            )
        weakest = candidates[0] if candidates else None
        what = ("" if weakest is None else
                f" (level {weakest.level}: {', '.join(weakest.weak)} not identified)")
        asked = "" if level == "auto" else f"the {level} level asked for is not identified; `level=auto` fits " \
                                           "what the data identify. "
        raise IdentifiabilityError(
            f"{asked}this log identifies no firmware calibration{what}: record the vehicle turning through all "
            "headings, and for the matrix also pitched and rolled; for the offsets alone a few headings at level "
            "with the attitude and a GPS fix logged"
        )
    best = min(c.heldout_rms if np.isfinite(c.heldout_rms) else np.inf for c in usable)
    if not np.isfinite(best):
        return min(usable, key=lambda c: c.problem.n_params)
    for c in sorted(usable, key=lambda c: c.problem.n_params):
        if c.heldout_rms <= best * (1.0 + AUTO_TOLERANCE):
            return c
    return usable[0]


def _held_names(klass: type[FirmwareCompass], level: str, held: FirmwareCompass, motor: str | None,
                held_motor: bool) -> dict[str, float]:
    """The parameters the level held at the firmware's values (name at instance 0 -> value)."""
    params = held.parameters(0)
    keep = {"offsets": ["SCALE", "DIA", "ODI"], "scale": ["DIA", "ODI"], "diagonal": ["ODI"], "full": []}[level]
    if klass.target == "px4":
        keep = {"offsets": ["SCALE", "ODIAG"], "scale": ["ODIAG"], "diagonal": ["ODIAG"], "full": []}[level]
    out = {k: v for k, v in params.items() if any(t in k for t in keep) and "_MOT" not in k and not k.endswith("COMP")}
    if held_motor:
        out.update({k: v for k, v in params.items() if "_MOT" in k or k.endswith(("COMP", "COMP_TYP"))})
    elif motor is None:
        out["motor term"] = 0.0
    return out


def _param_covariance(cand: _Candidate, klass: type[FirmwareCompass], orientation: int,
                      held: FirmwareCompass | None) -> tuple[list[str], NDArray[np.float64]]:
    """The covariance of the firmware parameters (instance 0 names) that the level fits, by a numerical Jacobian
    of parameters against the level's vector."""
    theta = cand.solution.theta
    problem = cand.problem

    def values(t: NDArray[np.float64]) -> dict[str, float]:
        A, o, m = problem.unpack(t)
        sol = dataclasses.replace(cand.solution, A=A, o=o, m=m, theta=t)
        return _compass(klass, sol, cand.level, orientation, cand.motor, held, cand.held_motor).parameters(0)

    base = values(theta)
    names = [k for k in base if not k.endswith("ORIENT") and not k.endswith("_ROT") and k not in
             ("COMPASS_MOTCT", "CAL_MAG_COMP_TYP")]
    G = np.zeros((len(names), len(theta)))
    for j in range(len(theta)):
        step = 1e-6 * max(1.0, abs(theta[j]))
        t = theta.copy()
        t[j] += step
        moved = values(t)
        G[:, j] = [(moved[k] - base[k]) / step for k in names]
    cov = G @ cand.covariance @ G.T
    fitted = [i for i, k in enumerate(names) if np.any(G[i] != 0)]
    return [names[i] for i in fitted], cov[np.ix_(fitted, fitted)]


def _result(
    chosen: _Candidate, table: list[dict[str, Any]], klass: type[FirmwareCompass], held: FirmwareCompass,
    fr: _Frame, held_frame: _Frame, orientation: dict[str, Any], vector: bool, raw: NDArray[np.float64],
    target: NDArray[np.float64],
    motors: Mapping[str, NDArray[np.float64]], messages: list[str], same_frame: bool,
) -> FirmwareFit:
    names, cov = _param_covariance(chosen, klass, fr.orientation,
                                   held if same_frame or chosen.held_motor else None)
    std = dict(zip(names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist(), strict=True))
    rms_after = float(np.sqrt(np.mean(chosen.solution.residual**2) * (3 if vector else 1)))
    rms_before = _rms_before(held, raw, target, held_frame, vector, motors)
    kind = chosen.compass.motor_type
    x = motors.get(kind) if kind else None
    held_values = _held_names(klass, chosen.level, held, chosen.motor, chosen.held_motor)
    if chosen.at_limit:
        messages.append(f"warning: the fit holds {', '.join(chosen.at_limit)} at the firmware's limit: the firmware "
                        "cannot represent what the data ask for there")
    return FirmwareFit(chosen.compass, chosen.level, table, std, cov, names, held_values, orientation,
                       "vector" if vector else "magnitude", rms_before, rms_after, fr.P_u, fr.P_h,
                       float(np.mean(x)) if x is not None else 0.0, chosen.inflation, chosen.noise, len(raw),
                       messages)


def _rms_before(held: FirmwareCompass, raw: NDArray[np.float64], field: NDArray[np.float64], hf: _Frame,
                vector: bool, motors: Mapping[str, NDArray[np.float64]]) -> float:
    """RMS of the residual of the firmware's calibration in the log (in its own orientation ``hf``), firmware
    unit; ``field`` the body-frame field (N, 3) or its magnitude (N,)."""
    A, o, m = held.algebra()
    x = motors.get(held.motor_type or "", np.zeros(len(raw)))
    B = (raw @ hf.P_u.T + o) @ A.T + x[:, None] * m
    if vector:
        return float(np.sqrt(np.mean(np.sum((B - field @ hf.P_h.T) ** 2, axis=1))))
    return float(np.sqrt(np.mean((np.linalg.norm(B, axis=1) - field) ** 2)))


def level_table(table: list[dict[str, Any]], unit: str) -> str:
    """The fit report's table of levels: level, parameters, RMS, held-out RMS, identified, limits, chosen."""
    lines = [f"{'level':<10}{'motor':<10}{'params':>7}{'rms':>11}{'held-out':>11}  {'identified':<11}"
             f"{'limits':<9}chosen   [{unit}]"]
    for row in table:
        ident = "yes" if row["identified"] else "no"
        limits = "ok" if row["within_limits"] else "outside"
        if row["at_limit"]:
            limits = "at limit"
        lines.append(f"{row['level']:<10}{row['motor'] or '-':<10}{row['n_params']:>7}{row['rms']:>11.4g}"
                     f"{row['heldout_rms']:>11.4g}  {ident:<11}{limits:<9}{'<--' if row['chosen'] else ''}")
    return "\n".join(lines)


def firmware_calibration(
    fit: FirmwareFit, *, units: str, motor_channel: str | None = None, reference: Mapping[str, Any] | None = None,
    input_orientation: int | None = None, diagnostics: Mapping[str, Any] | None = None,
) -> Calibration:
    """The :class:`~trimag.calibration.Calibration` of a firmware fit, in the data's ``units``.

    ``apply`` gives the firmware's corrected field (converted to ``units``): ``W (v - b - k (x - mean))`` with the
    motor term as a regressor named ``motor_channel`` (the logged column: ``current_A``, ``throttle``). The exact
    parameters are in ``diagnostics["firmware"]`` (what ``trimag export`` writes), with the level table, what was
    held, the orientation decision and ``input_orientation`` (the rotation already applied to the raw input).
    """
    compass = fit.compass
    factor = convert(1.0, compass.unit, units)
    W, b, m_body = fit.affine()
    regressors = None
    b_data = b * factor
    if compass.motor_type is not None:
        k = -np.linalg.solve(W, m_body) * factor  # W (v - b) + m x = W (v - b - k x)
        regressors = {"names": [motor_channel or compass.motor_type], "means": [fit.motor_mean],
                      "coefficients": [k.tolist()],
                      "units": ["A" if compass.motor_type == "current" else "throttle 0..1"],
                      "note": f"the firmware's motor term ({compass.motor_type})"}
        b_data = b_data + k * fit.motor_mean
    names = list(fit.param_std)
    uncertainty = make_uncertainty(
        names, covariance=fit.covariance, basis=f"s^2 (J^T J)^-1 of the {fit.level} level's parameters, propagated "
        "to the firmware's (instance 0 names, firmware unit)", noise_std=fit.noise_std * factor,
        inflation=fit.inflation, unit=compass.unit,
    )
    firmware = {**compass.as_dict(), "level": fit.level, "levels": fit.table, "held": fit.held,
                "orientation_decision": fit.orientation, "residual": fit.residual_kind,
                "input_orientation": input_orientation, "motor_channel": motor_channel if regressors else None,
                "param_std": fit.param_std, "rms_before": fit.rms_before, "rms_after": fit.rms_after}
    warnings = [m[len("warning: "):] for m in fit.messages if m.startswith("warning: ")]
    diag: dict[str, Any] = {"firmware": jsonable(firmware), **(diagnostics or {})}
    if warnings:
        diag["warnings"] = list(diag.get("warnings", [])) + warnings
    stats = {"n_samples": int(fit.n_samples), "n_used": int(fit.n_samples), "iterations": 1, "converged": True,
             "rms_before": fit.rms_before * factor, "rms_after": fit.rms_after * factor,
             "residual": fit.residual_kind}
    return Calibration.from_matrix_offset(
        W, b_data, units=units, model="affine", method=f"firmware-{compass.target}", params=compass.parameters(0),
        reference=None if reference is None else dict(reference), stats=stats, uncertainty=uncertainty,
        diagnostics=diag, regressors=regressors,
    )
