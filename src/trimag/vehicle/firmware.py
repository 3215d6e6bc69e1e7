"""Firmware-space fits (``trimag fit --target ardupilot|px4``, issue 30): exactly the parameters the autopilot loads,
within its limits, at the level the data identify.

The parameters and each firmware's formula are :mod:`trimag.models.firmware` (ArduPilot
``AP_Compass_Backend::correct_field``, PX4 ``Magnetometer::Correct``); the levels and their residuals are
:mod:`trimag.vehicle._firmware_levels`. The fit:

0. **Residual**: the vector one (``B - h``, the field rotated into the body frame by each sample's attitude) when
   the attitudes are trusted; with ``heading_free`` (an attitude whose yaw an EKF estimated with this very compass)
   the field's horizontal and vertical components under the logged roll and pitch (MAGFit's cost, as least
   squares), falling back to the vector one when that identifies nothing (a log that never changed heading);
   the magnitude without attitudes.
1. **Orientation** (attitudes only: a magnitude cannot see it). Every standard rotation of the target's enum is
   tried with one scale and the offsets (vector residual: 45-degree steps are robust to a few degrees of yaw
   error); the log's own orientation is kept unless another fits the field at least :data:`SWITCH_RATIO` times
   better. The rotation the standard one leaves (the rotation of the unconstrained affine fit's polar factor) is
   left to the symmetric matrix only up to :data:`ORIENTATION_TOLERANCE_DEG`; beyond it by more than two of its
   standard deviations (inflated by the residuals' correlation time), the fit is refused (exit 3) naming the
   angle and what to check (the reference, the log's orientation and attitudes), heading-free too (issue 38); a
   log whose field directions stay within :data:`MIN_CONE_DEG` does not measure it. An internal compass
   (ArduPilot ``COMPASS_EXTERNALn`` = 0, PX4 ``CAL_MAGn_ROT`` = -1) follows the board's rotation: its orientation
   is kept and a better one reported.
2. **Levels** (:data:`~trimag.vehicle._firmware_levels.LEVELS`, nested, each without and with each logged motor
   channel): the directions of a level's parameters that the data do not identify (one standard deviation moving
   the field by more than :data:`IDENTIFIED` allows) are held at the level below's solution (the log's values for
   the first) and the others fitted; each level is judged by its RMS on :data:`N_FOLDS` contiguous folds, each
   fitted on the others (held-out RMS); ``level="auto"`` picks the simplest level within the firmware's limits whose
   held-out RMS is within :data:`AUTO_TOLERANCE` of the best, and says what it held; a level asked for must be
   identified whole. Identification also needs the data's own **excitation**
   (:mod:`trimag.vehicle._firmware_trust`): a direction the fitted rows barely move is not identified whatever the
   noise, and offsets that are not all excited (a heading-free fit of a log that never turned: two equations for
   three offsets) are refused before any level (:class:`~trimag.vehicle._firmware_trust.NotExcited`, exit 3).
3. **Limits**: a level whose unconstrained solution the firmware cannot load is refitted with bounds (trust-region
   least squares): the parameters at a bound are named; a calibration still outside the limits is refused naming
   the parameter and the limit (:meth:`~trimag.models.firmware.FirmwareCompass.violations`). A scale more than
   :data:`SCALE_CONTRADICTION` times off the reference field is refused first: the reference (or the unit) is wrong.
4. **Uncertainty**: ``s^2 (J^T J)^-1`` of the level's parameters, inflated like every fit's
   (:func:`trimag.quality.honesty.correlation_time` of the residuals, repeated rows), propagated to the firmware's
   parameters and recorded with :func:`trimag.calibration.make_uncertainty`.
5. **Halves** (:mod:`trimag.vehicle._firmware_halves`): the chosen level refitted on each half of the log and judged
   on the other through the firmware's formula against the log's calibration on that half: refused
   (:class:`KeepTheLogs`, ``level="auto"``) when the other half's fit and the whole fit are both worse than the log's
   on a half, else warned of (and recorded in :attr:`FirmwareFit.halves`).
6. **Heading** (heading-free fits, :mod:`trimag.vehicle._firmware_heading`): the heading error against the logged
   yaw with the log's calibration and with the fit, reported; a fit that turns it far is warned of or refused
   (:class:`KeepTheLogs`, ``level="auto"``) and recorded in :attr:`FirmwareFit.heading`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from typing import Any, ParamSpec

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.threads import one_blas_thread
from ..calibration import Calibration, jsonable, make_uncertainty
from ..errors import IdentifiabilityError, TrimagError, TrimagInputError
from ..models.firmware import (
    FEATURE_NAMES,
    FIRMWARE_FEATURES,
    ORIENTATION_TOLERANCE_DEG,
    ArduPilotCompass,
    FirmwareCompass,
    firmware_class,
    instance_names,
    rotation_matrix,
)
from ..quality.honesty import correlation_time, count_repeated_rows
from ..units import convert
from ._firmware_halves import halves_check, halves_message
from ._firmware_heading import heading_check, heading_decision
from ._firmware_levels import LEVELS, LevelProblem, LevelSolution
from ._firmware_trust import (
    DIRECTION_EXCITATION_MIN,
    EXCITATION_MIN,
    Excitation,
    NotExcited,
    excitation,
    fold_rms,
    heading_free_excitation,
    not_excited_message,
    parameter_gradient,
    parameter_status,
    restrict_basis,
    unfitted_verdict,
    verdict_message,
)

__all__ = [
    "AUTO_TOLERANCE",
    "IDENTIFIED",
    "LEVELS",
    "N_FOLDS",
    "ORIENTATION_TOLERANCE_DEG",
    "FirmwareFit",
    "KeepTheLogs",
    "candidate_field",
    "firmware_calibration",
    "fit_firmware",
    "level_table",
]

#: Another orientation replaces the log's only when it fits the field this many times better (RMS).
SWITCH_RATIO = 2.0
#: The orientation is only chosen when the field directions spread over more than this (degrees from their mean).
MIN_CONE_DEG = 20.0
#: A chosen level whose held-out RMS exceeds this fraction of the field is refused: nothing was identified.
MAX_UNEXPLAINED = 0.2
#: A chosen level whose held-out RMS exceeds this fraction of the field is written with a warning (a poor compass).
POOR_UNEXPLAINED = 0.1
#: Contiguous folds of the held-out RMS.
N_FOLDS = 5
#: auto on a longer log compares the levels on evenly spread samples, at most this many, and fits and judges only the
#: chosen level on every sample (issue 40 item 3: a 5 h log at 10 Hz is 180 000 samples; the held-out RMS of 30 000
#: spread over the flight differs in its third digit at most).
LEVEL_CHOICE_MAX_ROWS = 30_000
#: auto: the simplest level whose held-out RMS is within this fraction of the best.
AUTO_TOLERANCE = 0.02
#: A direction of a level's parameters is identified when one standard deviation along it moves the corrected field
#: by less than ``noise_factor`` times the residual noise per axis (or ``fraction`` of the field, if larger)
#: (:func:`_identified`).
IDENTIFIED = {"fraction": 0.005, "noise_factor": 2.0}
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
        ``within_limits``, ``at_limit`` (parameter names), ``chosen``, ``note``, ``compass`` (the level's
        candidate parameters, :meth:`~trimag.models.firmware.FirmwareCompass.as_dict`: :func:`candidate_field`).
    param_std : dict
        Standard deviation of each fitted firmware parameter (by the compass's own name: ``instance``), firmware
        unit.
    covariance, covariance_order
        The fitted parameters' covariance.
    held : dict
        The parameters the level did not fit on their own: name -> ``{"value": v, "why": text}`` (keys are the
        firmware's parameter names; ``why``: held at the log's value, no motor term at this level, or not identified
        alone and moved only with the identified directions).
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
    held: dict[str, dict[str, Any]]
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
    #: the halves check (:func:`trimag.vehicle._firmware_halves.halves_check`): both halves' RMS and the log's
    halves: dict[str, Any] | None = None
    #: the parts of the firmware's calibration the log's firmware lacks (:data:`FIRMWARE_FEATURES`): never fitted
    absent: tuple[str, ...] = ()
    #: the heading check of a heading-free fit (:func:`trimag.vehicle._firmware_heading.heading_check`)
    heading: dict[str, Any] | None = None
    #: the compass's 0-based instance: every parameter name above is its own (``COMPASS_OFS2_X``, ``CAL_MAG1_XOFF``)
    instance: int = 0
    #: the parameters against the log's calibration on data they were not fitted to
    #: (:func:`trimag.vehicle._firmware_trust.unfitted_verdict`)
    verdict: dict[str, Any] | None = None
    #: each written parameter (the compass's own names): "fitted", "held", "not identified" (no sigma), "kept"/"chosen"
    param_status: dict[str, str] = field(default_factory=dict)

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


class _ScaleFit:
    """RMS of ``l P_u u + c - P_h h`` at its least-squares ``(l, c)`` (the orientation test) for any rotations, in
    closed form from one pass over the samples.

    With ``a = u - mean(u)`` and ``b = h - mean(h)`` the least-squares ``c`` is ``mean(P_h h) - l mean(P_u u)``, and
    ``l = trace(P_h^T P_u C) / S_uu`` with ``C = sum a b^T``; rotations keep ``S_uu = sum |a|^2`` and
    ``S_hh = sum |b|^2``, so the residual's sum of squares is ``S_hh - l^2 S_uu`` for every orientation: the search
    over a firmware's rotations costs one cross-covariance, not one regression over every sample per rotation."""

    def __init__(self, u: NDArray[np.float64], h: NDArray[np.float64]) -> None:
        a = u - u.mean(axis=0)
        b = h - h.mean(axis=0)
        self.n = len(u)
        self.C = a.T @ b
        self.S_uu = float(np.einsum("ni,ni->", a, a))
        self.S_hh = float(np.einsum("ni,ni->", b, b))

    def rms(self, P_u: NDArray[np.float64], P_h: NDArray[np.float64]) -> tuple[float, float]:
        """``(rms, l)`` of the fit of ``P_h h`` by ``l P_u u + c``."""
        if self.S_uu <= 0:
            return float(np.sqrt(self.S_hh / self.n)), 0.0
        S_uh = float(np.trace(P_h.T @ P_u @ self.C))
        scale = S_uh / self.S_uu
        return float(np.sqrt(max(self.S_hh - scale * S_uh, 0.0) / self.n)), scale


def _polar_angle(G: NDArray[np.float64]) -> float:
    """Angle (degrees) of the rotation ``Q`` of ``G = P Q`` (ArduPilot: the matrix after the rotation), which is
    also the ``Q`` of ``G = Q P`` (PX4: the rotation last): ``U S V^T = (U S U^T)(U V^T) = (U V^T)(V S V^T)``."""
    U, _, Vt = np.linalg.svd(G)
    Q = U @ Vt
    return float(np.degrees(np.arccos(np.clip((np.trace(Q) - 1.0) / 2.0, -1.0, 1.0))))


def _choose_orientation(
    target: str, raw: NDArray[np.float64], h: NDArray[np.float64], held: FirmwareCompass, applied: int | None,
    external: bool, tolerance_deg: float, motors: Mapping[str, NDArray[np.float64]], heading_free: bool = False,
) -> tuple[_Frame, dict[str, Any], list[str]]:
    """The orientation (step 1 of the module docstring) and what was decided."""
    results = []
    scales = {}
    scale_fit = _ScaleFit(raw, h)  # every rotation's one-scale fit from one pass over the samples
    for value in _unique_rotations(target):
        fr = _frame(target, value, applied)
        rms, scales[value] = scale_fit.rms(fr.P_u, fr.P_h)
        results.append((rms if scales[value] > 0 else np.inf, value))
    results.sort()
    best_rms, best = results[0]
    F = float(np.median(np.linalg.norm(h, axis=1)))
    own = F / float(np.median(np.linalg.norm(raw, axis=1)))  # with the regression's scale: a poorly turned log
    _refuse_contradicted_scale(scales[best] if abs(np.log(abs(own))) > np.log(SCALE_CONTRADICTION) else own, F,
                               type(held))  # attenuates the regression's (errors in u), so both must disagree
    current = int(held.orientation)
    current_rms = next(r for r, v in results if v == current)
    name = type(held)(orientation=best).rotation_name
    messages: list[str] = []
    info: dict[str, Any] = {"log_value": current, "best_value": best, "best_rms": best_rms,
                            "log_rms": current_rms, "external": external}
    chosen = current
    cone = _cone_deg(raw)
    info["cone_deg"] = cone
    if cone < MIN_CONE_DEG:
        messages.append(f"orientation: kept (the field direction stayed within {cone:.0f} deg: too little turning to "
                        "tell the sensor's orientation)")
        best = current
    elif best != current and np.isfinite(best_rms) and current_rms > SWITCH_RATIO * best_rms:
        better = (f"{current_rms / best_rms:.3g}x better than the log's {current}" if np.isfinite(current_rms) else
                  f"while the log's {current} sees the field reversed (a negative scale)")
        if external:
            chosen = best
            messages.append(f"orientation: {name} ({best}) fits the field {better}: chosen")
        else:
            messages.append(f"warning: the field fits {name} ({best}) {better}, but this compass is internal: its "
                            "orientation follows the board's (AHRS_ORIENTATION / SENS_BOARD_ROT); check the board's "
                            "orientation")
    info["decision"] = "chosen" if chosen != current else "kept"
    fr = _frame(target, chosen, applied)
    info["value"] = chosen
    angle, sigma = (_remaining_angle(raw @ fr.P_u.T, h @ fr.P_h.T, motors) if cone >= MIN_CONE_DEG else
                    (None, None))  # a log that barely turned cannot tell a rotation from an affine map (issue 38)
    info["remaining_angle_deg"], info["remaining_angle_sigma_deg"] = angle, sigma
    if angle is not None and sigma is not None:
        messages.append(f"orientation: the nearest standard rotation leaves {angle:.1f} +- {sigma:.1f} deg, left to "
                        "the symmetric matrix (it stays as a heading error of about that size)")
    elif cone < MIN_CONE_DEG:
        messages.append(f"orientation: the rotation beyond the nearest standard one is not measured (the field "
                        f"direction stayed within {cone:.0f} deg)")
    if angle is not None and sigma is not None and angle - 2.0 * sigma > tolerance_deg:
        raise _orientation_refusal(type(held), chosen, angle, sigma, tolerance_deg, heading_free)
    return fr, info, messages


def _orientation_refusal(klass: type[FirmwareCompass], chosen: int, angle: float, sigma: float, tolerance_deg: float,
                         heading_free: bool) -> IdentifiabilityError:
    """The refusal (exit 3) of a compass the nearest standard rotation leaves more than ``tolerance_deg`` from
    the field the attitudes and the reference give (issue 38, item 2): the angle and what to check."""
    chosen_name = klass(orientation=chosen).rotation_name
    orient = ("COMPASS_ORIENTn, AHRS_ORIENTATION and AHRS_TRIM" if klass.target == "ardupilot" else
              "CAL_MAGn_ROT, SENS_BOARD_ROT and its SENS_BOARD_X/Y/Z_OFF trims")
    yaw = (" (the yaw is the EKF's, which used this compass: a compass that disagrees with the other compasses "
           "turns it too)" if heading_free else "")
    return IdentifiabilityError(
        f"the field the log's attitudes and the reference give is rotated {angle:.1f} +- {sigma:.1f} deg from the "
        f"compass's readings in the nearest standard orientation {chosen_name} ({chosen}); the symmetric matrix the "
        f"firmware takes holds at most {tolerance_deg:g} deg of it, so the parameters would leave a heading error "
        f"of that size: check the reference (the site: the log's GPS fix or --igrf), the log's orientation "
        f"({orient}) and its attitudes{yaw}; if the compass is mounted askew, mount it square to the vehicle (or "
        "set a custom rotation: ArduPilot COMPASS_ORIENT 101 with CUST_ROT1_*, PX4 CAL_MAGn_ROT 100 with "
        "CAL_MAGn_ROLL/PITCH/YAW) and record again"
    )


def _cone_deg(raw: NDArray[np.float64]) -> float:
    """How far (degrees) the field's direction in the sensor strayed from its mean: how much the vehicle turned."""
    directions = raw / np.linalg.norm(raw, axis=1, keepdims=True)
    mean = directions.mean(axis=0) / np.linalg.norm(directions.mean(axis=0))
    return float(np.degrees(np.arccos(np.clip(directions @ mean, -1.0, 1.0))).max())


def _remaining_angle(u: NDArray[np.float64], h: NDArray[np.float64],
                     motors: Mapping[str, NDArray[np.float64]]) -> tuple[float | None, float | None]:
    """The rotation (degrees) of the unconstrained affine fit ``h = G u + c (+ motor terms)`` and its standard
    deviation; None when it is not measured to half of :data:`ORIENTATION_TOLERANCE_DEG`."""
    design = np.column_stack([u, np.ones(len(u)), *motors.values()])
    X, *_ = np.linalg.lstsq(design, h, rcond=None)
    r = h - design @ X
    tau = max(correlation_time(r[:, k]) for k in range(3))  # correlated residuals carry less information
    s2 = float(np.sum(r**2)) / max(3 * (len(u) - design.shape[1]), 1) * tau
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
def _inflation(residual: NDArray[np.float64], width: int, raw: NDArray[np.float64]) -> dict[str, Any]:
    """The honest inflation (:mod:`trimag.quality.honesty`) of a level's covariance (``width`` residuals per
    sample)."""
    series = residual.reshape(-1, width).T
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


def _effect_scales(problem: LevelProblem, F: float, x_range: float) -> NDArray[np.float64]:
    """How much one unit of each parameter moves the corrected field: offsets 1, matrix entries ``F``, a motor term
    half the logged range ``x_range``."""
    return np.array([1.0 if n.startswith("o_") else (x_range / 2.0 if n.startswith("m_") else F)
                     for n in problem.names()])


def _identified(problem: LevelProblem, cov: NDArray[np.float64], scales: NDArray[np.float64], F: float,
                noise: float, change: NDArray[np.float64]) -> tuple[NDArray[np.float64], list[str]]:
    """The directions of the level's parameters that the data identify, and the names of those they do not.

    Parameters are compared by their effect on the corrected field (:func:`_effect_scales`). A direction (an
    eigenvector of the scaled covariance) is identified when one standard deviation along it moves the field by
    less than ``IDENTIFIED["noise_factor"]`` times the fit's residual noise ``noise`` (or ``IDENTIFIED["fraction"]``
    of the field ``F``, if larger). ``change`` (the solution minus the held values) is not used.

    Returns
    -------
    basis : ndarray, shape (p, k)
        The identified directions (columns, in parameters over ``scales``).
    weak : list of str
        For each direction not identified, the parameter that dominates it (a parameter named once).
    """
    limit = max(noise, IDENTIFIED["fraction"] * F)
    scaled = cov / np.outer(scales, scales)
    eigval, eigvec = np.linalg.eigh((scaled + scaled.T) / 2.0)
    good = np.sqrt(np.clip(eigval, 0, None)) <= IDENTIFIED["noise_factor"] * limit
    del change
    names = problem.names()
    weak: list[str] = []
    for k in np.flatnonzero(~good):
        name = names[int(np.argmax(np.abs(eigvec[:, k])))]
        if name not in weak:
            weak.append(name)
    return eigvec[:, good], weak


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
    n_identified: int = 0
    bounds: Any = None
    #: the data's excitation of the level's directions (:mod:`trimag.vehicle._firmware_trust`)
    excitation: Excitation | None = None


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
    """RMS over every sample of the residual (vector length, heading-free or magnitude) predicted by the fit on the
    other folds."""
    n = len(problem.u)
    if n < 5 * N_FOLDS:
        return float("nan")
    errors = []
    refit = problem.fold_refitter(sol) if bounds is None else None  # Gauss-Newton from the whole log's solution
    for fold in _folds(n):
        train = np.concatenate([np.arange(fold[0]), np.arange(fold[-1] + 1, n)])  # the folds are contiguous
        try:
            theta = refit(int(fold[0]), int(fold[-1]) + 1) if refit is not None else None
            if theta is None and sol.basis is not None and sol.theta_ref is not None and sol.scales is not None:
                theta = problem.solve_in(sol.theta_ref, sol.basis, sol.scales, rows=train).theta
            elif theta is None:
                theta = problem.solve(sol.theta, rows=train, bounds=bounds).theta
        except (np.linalg.LinAlgError, ValueError):
            return float("inf")
        r = problem.residual(theta, rows=fold)
        errors.append(r.reshape(-1, problem.width))
    e = np.concatenate(errors)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def _fit_level(
    level: str, motor: str | None, u: NDArray[np.float64], target: NDArray[np.float64],
    motor_values: Mapping[str, NDArray[np.float64]], klass: type[FirmwareCompass], held: FirmwareCompass,
    A_held: NDArray[np.float64], o_held: NDArray[np.float64], start: NDArray[np.float64] | None, orientation: int,
    offsets_max: float, raw: NDArray[np.float64], held_same_frame: bool, tilt: NDArray[np.float64] | None = None,
) -> _Candidate:
    x = None if motor is None else motor_values[motor]
    fixed = None
    if motor is None and held.motor_type in motor_values and np.any(held.motor):
        # the firmware's own motor term is held (PX4's COMP with the held scale matrix: COMP acts inside S)
        fixed = motor_values[str(held.motor_type)][:, None] * held.algebra()[2]
    problem = LevelProblem(u, level, x, target, A_held, o_held, fixed, tilt)
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
    inflation = _inflation(sol.residual, problem.width, raw)
    cov, noise = _covariance(sol, inflation["total"])
    F = float(np.median(np.linalg.norm(target, axis=1) if target.ndim == 2 else target))
    x_range = float(np.ptp(x)) if x is not None else 1.0
    scales = _effect_scales(problem, F, x_range)
    m_held = held.algebra()[2] if fixed is None and held.motor_type == motor else np.zeros(3)
    reference = problem.pack(*start) if isinstance(start, tuple) else problem.pack(A_held, o_held, m_held)
    basis, weak = _identified(problem, cov, scales, F, float(np.sqrt(np.mean(sol.residual**2))),
                              sol.theta - reference)
    exc = excitation(problem, sol.jacobian, F)  # what the rows move at all, whatever the noise (issue 38)
    basis = restrict_basis(basis, scales, exc)
    weak = weak + [n for n in exc.unexcited if n not in weak]
    if weak and basis.shape[1] and bounds is None:  # fit what is identified; hold the rest at the log's values
        sol = problem.solve_in(reference, basis, scales)
        compass = _compass(klass, sol, level, orientation, motor, held_for_params, fixed is not None)
        J = (sol.jacobian * scales) @ basis
        s2 = float(sol.residual @ sol.residual) / max(len(sol.residual) - basis.shape[1], 1)
        cov = (scales[:, None] * basis) @ np.linalg.pinv(J.T @ J) @ (scales[:, None] * basis).T * s2 \
            * inflation["total"]
    names = problem.names()
    return _Candidate(level, motor, problem, sol, compass, cov, noise, inflation, not weak, weak,
                      [str(v) for v in compass.violations(offsets_max=offsets_max)],
                      [names[k] for k in sol.at_bound], _heldout(problem, sol, bounds), fixed is not None,
                      basis.shape[1], bounds, exc)


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


_P = ParamSpec("_P")


def _instance_named_errors(fit: Callable[_P, FirmwareFit]) -> Callable[_P, FirmwareFit]:
    """``fit`` whose refusals name the compass's own parameters, as its result does (:func:`_named`; issue 39,
    item 2: one naming everywhere): a :class:`~trimag.errors.TrimagError` raised for compass ``instance`` is raised
    again, the same type with the same attributes, its message in the names the firmware loads for that compass
    (``COMPASS_OFS2_X``, not compass 1's ``COMPASS_OFS_X``)."""

    @functools.wraps(fit)
    def named(*args: _P.args, **kwargs: _P.kwargs) -> FirmwareFit:
        try:
            return fit(*args, **kwargs)
        except TrimagError as exc:
            target, instance = kwargs.get("target", args[0] if args else None), kwargs.get("instance", 0)
            if not isinstance(target, str) or not isinstance(instance, int) or instance == 0:
                raise
            text = instance_names(target, str(exc), instance)
            if text == str(exc):
                raise
            renamed = type(exc)(text)
            renamed.__dict__.update(vars(exc))
            raise renamed from None

    return named


@_instance_named_errors
@one_blas_thread()  # small BLAS products only: a second thread would spin-wait (trimag._core.threads)
def fit_firmware(
    target: str, raw: ArrayLike, *, field_body: ArrayLike | None = None, magnitude: ArrayLike | None = None,
    motor_values: Mapping[str, ArrayLike] | None = None, held: FirmwareCompass | None = None,
    applied_orientation: int | None = None, external: bool = True, level: str = "auto", motor: str = "auto",
    tolerance_deg: float = ORIENTATION_TOLERANCE_DEG, offsets_max: float | None = None,
    heading_free: ArrayLike | None = None, absent: Collection[str] = (), instance: int = 0,
    unfitted: Mapping[str, Any] | None = None,
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
    heading_free : array_like, shape (N, 3, 3), optional
        With ``field_body``: each sample's roll-and-pitch rotation (body -> level frame). The levels are then fitted
        to the heading-free residual (the field's horizontal and vertical components: the heading does not enter),
        for attitudes whose yaw is not to be trusted (an EKF's that fused this compass); the orientation is still
        chosen among the standard rotations with the vector residual (45-degree steps), and what remains beyond
        ``tolerance_deg`` refused as for the vector residual.
    absent : collection of str
        The parts of the firmware's calibration the log's firmware lacks (:data:`FIRMWARE_FEATURES`): never fitted.
    instance : int
        The compass's 0-based instance: the result names its parameters as the firmware does for it
        (``COMPASS_OFS2_X``, ``CAL_MAG1_XOFF``; :func:`trimag.models.firmware.instance_names`).
    unfitted : mapping, optional
        Rows of the log the fit is not given (``--rows``/``--where`` left them out): ``raw`` (n, 3, as ``raw``),
        ``field`` (n, 3 body frame, or (n,) magnitude), ``motors``, ``tilt`` (as ``heading_free``, or None),
        ``what``. The parameters are judged against ``held`` on them (else on held-out folds): the verdict
        (:func:`trimag.vehicle._firmware_trust.unfitted_verdict`, :attr:`FirmwareFit.verdict`).

    Raises
    ------
    TrimagInputError
        Bad input, a reference the data contradict, or no level within the firmware's limits (exit 2).
    IdentifiabilityError
        The data identify no level (or not the one asked for), a compass rotated beyond ``tolerance_deg`` from every
        standard orientation: exit 3, naming what is not identified or the angle.

    Every refusal names compass ``instance``'s parameters, as the result does.
    """
    klass = firmware_class(target)
    if level not in ("auto", *LEVELS):
        raise TrimagInputError(f"`level` must be auto, {', '.join(LEVELS)}; got {level!r}")
    if motor not in ("auto", "none", *_MOTOR_KINDS):
        raise TrimagInputError(f"`motor` must be auto, none, current or throttle; got {motor!r}")
    v, h, motors = _check_inputs(raw, field_body, magnitude, motor_values)
    absent = _check_absent(target, absent, level, motor)
    if "motor" in absent:
        motors = {}
    held_given = held is not None
    if held is None:
        held = klass(orientation=applied_orientation or 0)
    if not isinstance(held, klass):
        raise TrimagInputError(f"`held` must be a {klass.__name__}")
    omax = float(offsets_max) if offsets_max else float(getattr(klass, "OFFSETS_MAX", np.inf))
    vector = h.ndim == 2
    messages: list[str] = []
    tilt = None if heading_free is None else np.asarray(heading_free, dtype=np.float64)
    if tilt is not None and (not vector or tilt.shape != (len(v), 3, 3)):
        raise TrimagInputError(f"`heading_free` needs `field_body` and one 3x3 rotation per sample ({len(v)}, 3, 3)")
    if tilt is not None:  # before the orientation step: a log that never turned is refused for what it is
        _require_heading_free_excited(h, tilt, _frame(target, int(held.orientation), applied_orientation), klass, v)
    if vector:
        fr, orientation, more = _choose_orientation(target, v, h, held, applied_orientation, external,
                                                    tolerance_deg, motors, tilt is not None)
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
    if not vector:  # the sphere's radius is undefined for readings that barely turned: the held calibration's
        # field must disagree too (its |B| is the log's own magnitude), as the vector path's two scales must
        held_G = float(np.median(np.linalg.norm((u + o_held) @ A_held.T, axis=1)))
        own = F / held_G if held_G > 0 else np.inf
        _refuse_contradicted_scale(own if abs(np.log(own)) <= np.log(SCALE_CONTRADICTION) else _sphere_scale(u, F),
                                   F, klass)
    held_frame = _frame(target, int(held.orientation), applied_orientation)
    try:
        table, candidates, chosen, tilt = _levels(level, motor, motors, u, hh, h, v, klass, held, A_held, o_held, fr,
                                                  held_frame, omax, same_frame, tilt, vector, F, messages, absent)
    except IdentifiabilityError as exc:  # what the orientation step found explains many a refusal
        said = [m[len("warning: "):] for m in messages if m.startswith("warning: the field fits")]
        if said:
            raise type(exc)(f"{exc}; {said[0]}") from None
        raise
    for row, cand in zip(table, candidates, strict=True):
        row["chosen"] = cand is chosen
    halves = _halves(chosen, klass, held, fr.orientation, same_frame, v, h, motors, tilt, applied_orientation, F)
    if halves["flagged"]:
        text = halves_message(halves, chosen.level, klass.unit)
        if halves["refuse"] and level == "auto":
            raise KeepTheLogs(f"the calibration in the log is the better one: {text}")
        messages.append(f"warning: {text}")
    heading = None
    if heading_free is not None:  # the heading the fit could not see, against the logged yaw (_firmware_heading)
        heading = heading_check(chosen.compass, held, v, h, motors, np.asarray(heading_free, dtype=np.float64),
                                applied_orientation)
        said, refusal = heading_decision(heading, level,
                                          barely_turned=orientation.get("cone_deg", np.inf) < MIN_CONE_DEG)
        if refusal is not None:
            raise KeepTheLogs(refusal)
        messages += said
    messages += _poor(chosen, F, klass.unit)
    if "scale" in absent and isinstance(chosen.compass, ArduPilotCompass) and chosen.compass.scale:
        c = chosen.compass  # no COMPASS_SCALE in this firmware: the whole gain in DIA/ODI (the same correction)
        A, o, m = c.algebra()
        chosen.compass = dataclasses.replace(
            ArduPilotCompass.from_algebra(A, o, m, orientation=c.orientation, motor_type=c.motor_type, scale=1.0),
            motor=c.motor, scale=0.0)
    verdict = _verdict(chosen, klass, held, held_given, fr.orientation, same_frame, v, h, motors, tilt,
                       applied_orientation, unfitted, level, messages)
    fit = _result(chosen, table, klass, held, fr, held_frame, orientation, vector, v, h, motors, messages, same_frame,
                  tilt)
    fit.halves, fit.heading, fit.verdict = halves, heading, verdict
    fit.absent = tuple(absent)
    return _named(fit, target, instance)


def _named(fit: FirmwareFit, target: str, instance: int) -> FirmwareFit:
    """``fit`` with every parameter name (keys, lists, texts) the compass's own (``instance``, 0-based)."""
    if instance == 0:
        return fit
    renamed = {name: instance_names(target, getattr(fit, name), instance) for name in
               ("table", "param_std", "covariance_order", "held", "orientation", "messages", "halves", "heading",
                "verdict", "param_status")}
    return dataclasses.replace(fit, **renamed, instance=instance)


_NEEDS = {("ardupilot", "scale"): "scale", ("ardupilot", "diagonal"): "matrix", ("ardupilot", "full"): "matrix",
          ("px4", "full"): "offdiagonal"}

def _loadable(target: str, level: str, absent: Collection[str]) -> bool:
    """Whether the log's firmware has the parameters ``level`` fits (``absent``: :func:`absent_features`)."""
    return _NEEDS.get((target, level)) not in absent


def _check_absent(target: str, absent: Collection[str], level: str, motor: str) -> tuple[str, ...]:
    """``absent`` checked against :data:`FIRMWARE_FEATURES`; a level or motor term asked for that the firmware
    lacks is refused."""
    out = tuple(absent)
    unknown = [a for a in out if a not in FIRMWARE_FEATURES[target]]
    if unknown:
        raise TrimagInputError(f"`absent` takes {', '.join(FIRMWARE_FEATURES[target])} for {target}; got {unknown}")
    if level != "auto" and not _loadable(target, level, out):
        missing = FEATURE_NAMES[_NEEDS[(target, level)]]
        raise TrimagInputError(f"the log's firmware has no {missing} (not among its parameters): the {level} level "
                               "cannot be loaded; use --level auto or a lower level")
    if motor in _MOTOR_KINDS and "motor" in out:
        raise TrimagInputError(f"the log's firmware has no {FEATURE_NAMES['motor']} (not among its parameters): "
                               "use --motor none")
    return out


def _poor(chosen: _Candidate, F: float, unit: str) -> list[str]:
    """A warning when the chosen level leaves more than :data:`POOR_UNEXPLAINED` of the field unexplained (under
    the :data:`MAX_UNEXPLAINED` refusal: kept, as it may still be far better than the log's, but said)."""
    rms = chosen.heldout_rms
    if not np.isfinite(rms) or rms <= POOR_UNEXPLAINED * F:
        return []
    heading = float(np.degrees(np.arctan2(rms, F)))
    return [f"warning: a poor compass: the {chosen.level} level leaves {rms:.4g} of the field {F:.4g} {unit} "
            f"unexplained (held-out RMS, {100 * rms / F:.0f}%): heading errors of about {heading:.0f} deg where the "
            "field is horizontal, more where it dips; the compass sits in a disturbed field (motors, power wiring, "
            "iron) or the log's processing changed its readings: move it, or let the autopilot use a better compass "
            "(ArduPilot COMPASS_USEn 0, PX4 CAL_MAGn_PRIO 0 for this one)"]


def _halves(chosen: _Candidate, klass: type[FirmwareCompass], held: FirmwareCompass, orientation: int,
            same_frame: bool, raw: NDArray[np.float64], field: NDArray[np.float64],
            motors: Mapping[str, NDArray[np.float64]], tilt: NDArray[np.float64] | None, applied: int | None,
            F: float) -> dict[str, Any]:
    """The halves check of the chosen level (:mod:`trimag.vehicle._firmware_halves`)."""
    params_held = held if same_frame or chosen.held_motor else None

    def to_compass(sol: LevelSolution) -> FirmwareCompass:
        return _compass(klass, sol, chosen.level, orientation, chosen.motor, params_held, chosen.held_motor)

    x = motors.get(chosen.motor) if chosen.motor else None
    scales = _effect_scales(chosen.problem, F, float(np.ptp(x)) if x is not None else 1.0)
    names = [_firmware_name(klass, n) for n in chosen.problem.names()]
    return halves_check(chosen.problem, chosen.solution, chosen.bounds, to_compass, held, raw, field, motors, tilt,
                        applied, names, scales, F, IDENTIFIED)


def _verdict(chosen: _Candidate, klass: type[FirmwareCompass], held: FirmwareCompass, held_given: bool,
             orientation: int, same_frame: bool, raw: NDArray[np.float64], field: NDArray[np.float64],
             motors: Mapping[str, NDArray[np.float64]], tilt: NDArray[np.float64] | None, applied: int | None,
             unfitted: Mapping[str, Any] | None, level: str, messages: list[str]) -> dict[str, Any]:
    """The parameters to be written against the log's calibration on data they were not fitted to (issue 38, item
    3): the rows ``unfitted`` when given, else the held-out folds, through the firmware's formula. Worse: refused
    (:class:`KeepTheLogs`) under ``level="auto"``, a warning for a level asked for; better: one line."""
    params_held = held if same_frame or chosen.held_motor else None

    def to_compass(sol: LevelSolution) -> FirmwareCompass:
        return _compass(klass, sol, chosen.level, orientation, chosen.motor, params_held, chosen.held_motor)

    R0 = np.eye(3) if applied is None else rotation_matrix(klass.target, applied)
    if unfitted is not None:
        part = dict(unfitted)
        part["tilt"] = part.get("tilt") if tilt is not None else None  # the fit's own residual
        if chosen.compass.motor_type and chosen.compass.motor_type not in (part.get("motors") or {}):
            part = {}  # the rows left out lack the motor channel the fit uses: judged on the folds instead
    else:
        part = {}
    if part:
        verdict = unfitted_verdict(chosen.compass, held, applied, unfitted=part)
    else:
        verdict = unfitted_verdict(
            chosen.compass, held, applied, raw=raw, field_body=field, motors=motors, tilt=tilt,
            folds=lambda: fold_rms(chosen.problem, chosen.solution, chosen.bounds, N_FOLDS, to_compass, raw @ R0,
                                   field, motors, tilt))
    verdict["against"] = "the log's calibration" if held_given else "no calibration (the raw readings)"
    text = verdict_message(verdict, klass.unit)
    if verdict["better"] or not held_given:
        verdict["decision"] = "better" if verdict["better"] else "worse than the raw readings"
        messages.append(text)
    elif level == "auto":
        verdict["decision"] = "refused"
        raise KeepTheLogs(f"the calibration in the log is the better one: {text}")
    else:
        verdict["decision"] = "warned"
        messages.append(f"warning: {text}")
    return verdict


def _levels(
    level: str, motor: str, motors: Mapping[str, NDArray[np.float64]], u: NDArray[np.float64],
    hh: NDArray[np.float64], h: NDArray[np.float64], v: NDArray[np.float64], klass: type[FirmwareCompass],
    held: FirmwareCompass, A_held: NDArray[np.float64], o_held: NDArray[np.float64], fr: _Frame, held_frame: _Frame,
    omax: float, same_frame: bool, tilt: NDArray[np.float64] | None, vector: bool, F: float, messages: list[str],
    absent: tuple[str, ...] = (),
) -> tuple[list[dict[str, Any]], list[_Candidate], _Candidate, NDArray[np.float64] | None]:
    """The levels' table and candidates and the one chosen (:func:`_levels_on`); a log of more than
    :data:`LEVEL_CHOICE_MAX_ROWS` samples under ``level="auto"`` has its levels compared on evenly spread rows and only
    the chosen one fitted and judged on every row (its row of the table then holds the figures of every row)."""
    n = len(u)
    if level != "auto" or n <= LEVEL_CHOICE_MAX_ROWS:
        return _levels_on(level, motor, motors, u, hh, h, v, klass, held, A_held, o_held, fr, held_frame, omax,
                          same_frame, tilt, vector, F, messages, absent)
    step = -(-n // LEVEL_CHOICE_MAX_ROWS)
    rows = np.arange(0, n, step)
    said: list[str] = []
    table, candidates, chosen, sub_tilt = _levels_on(
        level, motor, {k: x[rows] for k, x in motors.items()}, u[rows], hh[rows], h[rows], v[rows], klass, held,
        A_held, o_held, fr, held_frame, omax, same_frame, None if tilt is None else tilt[rows], vector, F, said,
        absent)
    tilt_given, tilt = tilt, (None if sub_tilt is None else tilt)
    below = [c for c in candidates if c.motor == chosen.motor and LEVELS.index(c.level) < LEVELS.index(chosen.level)]
    start: Any = None  # the level below's (A, o, m): the start, and what the level holds where it identifies nothing
    if below:
        sol = max(below, key=lambda c: LEVELS.index(c.level)).solution
        start = (sol.A, sol.o, sol.m)
    target = hh if tilt is None else _heading_free_target(tilt, h)
    try:
        whole = _fit_level(chosen.level, chosen.motor, u, target, motors, klass, held, A_held, o_held, start,
                           fr.orientation, omax, v, same_frame, None if tilt is None else tilt @ fr.P_h)
    except (IdentifiabilityError, np.linalg.LinAlgError):
        whole = None
    if whole is None or whole.violations or (whole.at_limit and not chosen.at_limit):
        return _levels_on(level, motor, motors, u, hh, h, v, klass, held, A_held, o_held, fr, held_frame, omax,
                          same_frame, tilt_given, vector, F, messages, absent)
    k = next(i for i, c in enumerate(candidates) if c is chosen)
    candidates[k] = whole
    table[k] = {**table[k], **_level_row(whole), "rows": n}
    messages += said
    suffix = {2: "nd", 3: "rd"}.get(step % 10, "th") if step % 100 not in (12, 13) else "th"
    nth = f"{step}{suffix}"
    messages.append(f"levels compared on every {nth} sample ({len(rows)} of {n}: the table's figures but the "
                    f"chosen level's); the chosen level fitted and judged on all {n}")
    return table, candidates, whole, tilt


def _heading_free_target(tilt: NDArray[np.float64], h: NDArray[np.float64]) -> NDArray[np.float64]:
    """The heading-free residual's target (N, 2): the body field ``h`` (N, 3) under the tilt's roll and pitch
    (body -> level), as its horizontal length and its vertical component."""
    level_field = np.einsum("nij,nj->ni", tilt, h)
    return np.column_stack([np.hypot(level_field[:, 0], level_field[:, 1]), level_field[:, 2]])


def _level_row(cand: _Candidate) -> dict[str, Any]:
    """A candidate's figures in the levels' table (:func:`_run_levels`)."""
    sol = cand.solution
    return {"n_params": cand.problem.n_params, "rms": float(np.sqrt(np.mean(sol.residual**2) * cand.problem.width)),
            "heldout_rms": cand.heldout_rms, "identified": cand.identified, "n_identified": cand.n_identified,
            "not_identified": cand.weak, "within_limits": not cand.violations, "violations": cand.violations,
            "at_limit": cand.at_limit, **_excitation_row(cand), "compass": cand.compass.as_dict()}


def _levels_on(
    level: str, motor: str, motors: Mapping[str, NDArray[np.float64]], u: NDArray[np.float64],
    hh: NDArray[np.float64], h: NDArray[np.float64], v: NDArray[np.float64], klass: type[FirmwareCompass],
    held: FirmwareCompass, A_held: NDArray[np.float64], o_held: NDArray[np.float64], fr: _Frame, held_frame: _Frame,
    omax: float, same_frame: bool, tilt: NDArray[np.float64] | None, vector: bool, F: float, messages: list[str],
    absent: tuple[str, ...] = (),
) -> tuple[list[dict[str, Any]], list[_Candidate], _Candidate, NDArray[np.float64] | None]:
    """The levels' table and candidates and the one chosen, heading-free first where asked (module docstring)."""
    if tilt is not None:  # heading-free first; the vector (the untrusted yaw) only where it identifies nothing
        hz = _heading_free_target(tilt, h)
        table, candidates = _run_levels(level, motor, motors, u, hz, klass, held, A_held, o_held, fr.orientation,
                                        omax, v, same_frame, tilt @ fr.P_h, absent)
        try:
            chosen = _choose(level, candidates, _rms_before(held, v, h, held_frame, vector, motors, tilt), F)
        except (KeepTheLogs, NotExcited):
            raise
        except IdentifiabilityError as exc:
            cone = _cone_deg(v)
            if cone < MIN_CONE_DEG:  # the vector would take every offset from the yaw this compass made
                raise IdentifiabilityError(
                    f"the vehicle barely turned (the field's direction stayed within {cone:.0f} deg) and, without "
                    f"the heading, {exc}; the only offsets left would come from the logged yaw, which the EKF took "
                    "from this compass: for a vehicle at rest give its true heading (`trimag fit LOG --heading DEG` "
                    "without --target, as ArduPilot's MAG_CAL_YAW, then `trimag export`), or record a calibration "
                    "turn through all headings"
                ) from None
            messages.append(f"warning: heading-free, {exc}; fitted to the vector with the attitude's own yaw instead "
                            "(which used this compass: the orientation about the vertical and the horizontal soft "
                            "iron lean toward the calibration in the log)")
            tilt = None
    if tilt is None:
        table, candidates = _run_levels(level, motor, motors, u, hh, klass, held, A_held, o_held, fr.orientation,
                                        omax, v, same_frame, None, absent)
        if not vector:  # a vector residual's offsets are always excited (dB/do = A); heading-free: fit_firmware
            _require_excited(candidates, klass, _cone_deg(v))
        chosen = _choose(level, candidates, _rms_before(held, v, h, held_frame, vector, motors, None), F)
    return table, candidates, chosen, tilt


def _excitation_row(cand: _Candidate) -> dict[str, Any]:
    """The level table's record of a candidate's excitation (:mod:`trimag.vehicle._firmware_trust`)."""
    exc = cand.excitation
    if exc is None:
        return {"excitation": None}
    return {"excitation": exc.weakest, "offsets_excitation": exc.offsets, "unexcited": list(exc.unexcited)}


def _require_excited(candidates: list[_Candidate], klass: type[FirmwareCompass], cone: float) -> None:
    """Refuse (:class:`NotExcited`, exit 3) when no level's offsets are excited by the data (a magnitude
    residual): nothing identified can be written, whatever the residual (issue 38, item 1)."""
    excs = [c.excitation for c in candidates if c.excitation is not None]
    if not excs or any(e.offsets_excited for e in excs):
        return
    best = max(excs, key=lambda e: e.offsets)
    names = [_firmware_name(klass, f"o_{a}") for a in "xyz"]
    raise NotExcited(not_excited_message(best, names, False, cone))


def _require_heading_free_excited(h: NDArray[np.float64], tilt: NDArray[np.float64], fr: _Frame,
                                  klass: type[FirmwareCompass], raw: NDArray[np.float64]) -> Excitation:
    """The heading-free offsets' excitation from the reference (:func:`heading_free_excitation`), in the fit's
    frame ``fr``; refused (:class:`NotExcited`, exit 3) below :data:`EXCITATION_MIN` (issue 38, item 1)."""
    exc = heading_free_excitation(h, tilt)
    d = fr.P_h @ exc.offsets_direction  # body -> the fit's frame (where the offsets are the firmware's)
    exc.offsets_direction = d / max(float(np.linalg.norm(d)), 1e-300)
    if not exc.offsets_excited:
        names = [_firmware_name(klass, f"o_{a}") for a in "xyz"]
        raise NotExcited(not_excited_message(exc, names, True, _cone_deg(raw)))
    return exc


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
    tilt: NDArray[np.float64] | None = None, absent: tuple[str, ...] = (),
) -> tuple[list[dict[str, Any]], list[_Candidate]]:
    levels = tuple(lv for lv in LEVELS if _loadable(klass.target, lv, absent)) if level == "auto" else (level,)
    table: list[dict[str, Any]] = []
    candidates: list[_Candidate] = []
    previous: dict[str | None, Any] = {}  # each motor choice's solution of the level below: its start and what
    for lv in levels:                      # the next level holds where the data do not identify it (nested levels)
        for mk in _motor_choices(motor, motors):
            try:
                cand = _fit_level(lv, mk, u, target, motors, klass, held, A_held, o_held, previous.get(mk),
                                  orientation, omax, raw, same_frame, tilt)
            except (IdentifiabilityError, np.linalg.LinAlgError):
                continue
            previous[mk] = (cand.solution.A, cand.solution.o, cand.solution.m)
            candidates.append(cand)
            held_motor = "held" if cand.held_motor else None
            table.append({"level": lv, "motor": mk or held_motor, **_level_row(cand), "chosen": False})
    return table, candidates


class KeepTheLogs(IdentifiabilityError):
    """The calibration in the log fits the data better than any level fitted to them (exit 3: nothing to change)."""


def _choose(level: str, candidates: list[_Candidate], before: float | None = None, F: float | None = None
            ) -> _Candidate:
    """The level chosen (module docstring, step 2), or the refusal; ``before``: the RMS of the calibration in the
    log on these data (it was not fitted to them: a level whose held-out RMS does not beat it is no improvement)."""
    if level != "auto":  # a level asked for must be identified whole
        whole = [c for c in candidates if c.identified]
        if not whole:
            weak = ", ".join(candidates[0].weak) if candidates else "its parameters"
            raise IdentifiabilityError(
                f"the {level} level asked for is not identified ({weak}); `level=auto` fits what the data identify "
                "and holds the rest at the log's values"
            )
        candidates = whole
    usable = [c for c in candidates if c.n_identified and not c.violations and (level != "auto" or _adds(c))]
    inside = [c for c in usable if not c.at_limit]  # a level the limits hold back is only taken if it is all there is
    if level == "auto" and usable and not inside:
        c = min(usable, key=lambda c: c.heldout_rms)
        raise TrimagInputError(
            f"the data push {', '.join(c.at_limit)} of the {c.level} level to the firmware's limit: what they ask for "
            "cannot be loaded (a reference or unit off, iron near the compass, or a log that barely turned); check "
            "the reference and record a calibration turning through all headings, pitched and rolled"
        )
    usable = inside if level == "auto" else usable
    if not usable:
        outside = [c for c in candidates if c.n_identified and c.violations]
        if outside:
            raise TrimagInputError(
                f"the firmware cannot load this calibration: {outside[0].violations[0]} (level {outside[0].level}); "
                "move the compass away from iron or magnets, or check the reference"
            )
        raise IdentifiabilityError(
            "this log identifies no firmware calibration, not even the offsets: record the vehicle turning through "
            "all headings, and for the matrix also pitched and rolled; for the offsets alone a few headings at level "
            "with the attitude and a GPS fix logged"
        )
    best = min(c.heldout_rms if np.isfinite(c.heldout_rms) else np.inf for c in usable)
    if F is not None and np.isfinite(best) and best > MAX_UNEXPLAINED * F:
        raise IdentifiabilityError(
            f"the best level leaves {best:.4g} of the field {F:.4g} unexplained (held-out RMS, "
            f"{100 * best / F:.0f}%): these data cannot identify a calibration (a log that barely turned, readings "
            "the log's own processing changed, or a field disturbed by the vehicle); record a calibration turning "
            "through all headings, pitched and rolled, with the raw magnetometer logged"
        )
    if level == "auto" and before is not None and np.isfinite(best) and best >= before:
        raise KeepTheLogs(
            f"the calibration in the log fits these data (RMS {before:.4g}) better than any level fitted to them "
            f"(best held-out RMS {best:.4g}): keep it; to improve on it, record the vehicle turning through all "
            "headings, pitched and rolled"
        )
    if not np.isfinite(best):
        return min(usable, key=lambda c: c.problem.n_params)
    for c in sorted(usable, key=lambda c: c.problem.n_params):
        if c.heldout_rms <= best * (1.0 + AUTO_TOLERANCE):
            return c
    return usable[0]


def _adds(c: _Candidate) -> bool:
    """Whether the level identifies something it adds to the offsets: not when every one of its motor parameters, or
    every one of its matrix parameters, is unidentified (auto then takes the level without them)."""
    names = c.problem.names()
    motor = [n for n in names if n.startswith("m_")]
    matrix = [n for n in names if not n.startswith(("o_", "m_"))]
    weak = set(c.weak)
    return not ((motor and weak.issuperset(motor)) or (matrix and weak.issuperset(matrix)))


def _held_names(klass: type[FirmwareCompass], level: str, held: FirmwareCompass, motor: str | None,
                held_motor: bool) -> dict[str, dict[str, Any]]:
    """The parameters the level held (instance 0 names -> ``{"value", "why"}``): the log's values of the parts the
    level does not fit, and the motor term's (the log's, or zero without one at this level)."""
    params = held.parameters(0)
    keep = {"offsets": ["SCALE", "DIA", "ODI"], "scale": ["DIA", "ODI"], "diagonal": ["ODI"], "full": []}[level]
    if klass.target == "px4":
        keep = {"offsets": ["SCALE", "ODIAG"], "scale": ["ODIAG"], "diagonal": ["ODIAG"], "full": []}[level]
    why = f"held at the log's value (the {level} level does not fit it)"
    out = {k: {"value": v, "why": why} for k, v in params.items()
           if any(t in k for t in keep) and "_MOT" not in k and not k.endswith("COMP")}
    if held_motor:
        out.update({k: {"value": v, "why": "the log's motor term, held"} for k, v in params.items()
                    if "_MOT" in k or k.endswith(("COMP", "COMP_TYP"))})
    elif motor is None:
        names = [f"COMPASS_MOT_{a}" for a in "XYZ"] if klass.target == "ardupilot" else \
            [f"CAL_MAG0_{a}COMP" for a in "XYZ"]
        out.update({k: {"value": 0.0, "why": "no motor term at this level"} for k in names})
    return out


def _firmware_name(klass: type[FirmwareCompass], name: str) -> str:
    """The firmware's parameter (instance 0) behind an algebra name (``o_x``, ``d_y``, ``A_xz``, ``l``, ``m_z``)."""
    axis = {"x": "X", "y": "Y", "z": "Z", "xx": "X", "yy": "Y", "zz": "Z", "xy": "X", "xz": "Y", "yz": "Z"}
    kind, _, which = name.partition("_")
    a = axis.get(which, "")
    if klass.target == "ardupilot":
        return {"o": f"COMPASS_OFS_{a}", "m": f"COMPASS_MOT_{a}", "l": "COMPASS_SCALE", "d": f"COMPASS_DIA_{a}",
                "A": f"COMPASS_{'DIA' if which in ('xx', 'yy', 'zz') else 'ODI'}_{a}"}[kind]
    return {"o": f"CAL_MAG0_{a}OFF", "m": f"CAL_MAG0_{a}COMP", "l": "CAL_MAG0_XSCALE", "d": f"CAL_MAG0_{a}SCALE",
            "A": f"CAL_MAG0_{a}{'SCALE' if which in ('xx', 'yy', 'zz') else 'ODIAG'}"}[kind]


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
    G = parameter_gradient(values, theta, names)
    cov = G @ cand.covariance @ G.T
    fitted = [i for i, k in enumerate(names) if np.any(G[i] != 0)]
    return [names[i] for i in fitted], cov[np.ix_(fitted, fitted)]


def _result(
    chosen: _Candidate, table: list[dict[str, Any]], klass: type[FirmwareCompass], held: FirmwareCompass,
    fr: _Frame, held_frame: _Frame, orientation: dict[str, Any], vector: bool, raw: NDArray[np.float64],
    target: NDArray[np.float64],
    motors: Mapping[str, NDArray[np.float64]], messages: list[str], same_frame: bool,
    tilt: NDArray[np.float64] | None = None,
) -> FirmwareFit:
    names, cov = _param_covariance(chosen, klass, fr.orientation,
                                   held if same_frame or chosen.held_motor else None)
    status = _parameter_status(chosen, klass, fr.orientation, held if same_frame or chosen.held_motor else None,
                               orientation)
    names, cov = _only_fitted(names, cov, status)
    std = dict(zip(names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist(), strict=True))
    rms_after = float(np.sqrt(np.mean(chosen.solution.residual**2) * chosen.problem.width))
    rms_before = _rms_before(held, raw, target, held_frame, vector, motors, tilt)
    kind = chosen.compass.motor_type
    x = motors.get(kind) if kind else None
    held_values = _held_names(klass, chosen.level, held, chosen.motor, chosen.held_motor)
    fitted = chosen.compass.parameters(0)
    for name in chosen.weak:  # the directions the data do not identify, held at the level below's values
        fw = _firmware_name(klass, name)
        held_values[fw] = {"value": float(fitted.get(fw, 0.0)),
                           "why": "not identified alone: moved only with the identified directions"}
    if chosen.at_limit:
        messages.append(f"warning: the fit holds {', '.join(chosen.at_limit)} at the firmware's limit: the firmware "
                        "cannot represent what the data ask for there")
    out = FirmwareFit(chosen.compass, chosen.level, table, std, cov, names, held_values, orientation,
                      ("heading-free" if tilt is not None else "vector") if vector else "magnitude", rms_before,
                      rms_after, fr.P_u, fr.P_h,
                      float(np.mean(x)) if x is not None else 0.0, chosen.inflation, chosen.noise, len(raw),
                      messages)
    out.param_status = status
    return out


def _parameter_status(chosen: _Candidate, klass: type[FirmwareCompass], orientation: int,
                      held: FirmwareCompass | None, decision: Mapping[str, Any]) -> dict[str, str]:
    """Each written parameter's status (:func:`trimag.vehicle._firmware_trust.parameter_status`): fitted, held,
    not identified; the orientation ``kept`` or ``chosen``; the motor type ``fitted`` with a motor term."""
    problem, sol = chosen.problem, chosen.solution

    def values(t: NDArray[np.float64]) -> dict[str, float]:
        A, o, m = problem.unpack(t)
        moved = dataclasses.replace(sol, A=A, o=o, m=m, theta=t)
        return _compass(klass, moved, chosen.level, orientation, chosen.motor, held, chosen.held_motor).parameters(0)

    n_weak = problem.n_params - chosen.n_identified if chosen.weak else 0
    status = parameter_status(values, sol.theta, sol.jacobian, n_weak,
                              chosen.excitation.scales if chosen.excitation is not None else None)
    for name in status:
        if name.endswith(("ORIENT", "_ROT")):
            status[name] = "chosen" if decision.get("decision") == "chosen" else "kept"
        elif name in ("COMPASS_MOTCT", "CAL_MAG_COMP_TYP"):
            status[name] = "fitted" if chosen.motor else "held"
    return status


def _only_fitted(names: list[str], cov: NDArray[np.float64], status: Mapping[str, str]
                 ) -> tuple[list[str], NDArray[np.float64]]:
    """The covariance of the parameters the data determine: a held or unidentified one has no sigma (issue 38,
    item 4)."""
    keep = [i for i, n in enumerate(names) if status.get(n, "fitted") == "fitted"]
    return [names[i] for i in keep], cov[np.ix_(keep, keep)]


def _rms_before(held: FirmwareCompass, raw: NDArray[np.float64], field: NDArray[np.float64], hf: _Frame,
                vector: bool, motors: Mapping[str, NDArray[np.float64]], tilt: NDArray[np.float64] | None) -> float:
    """RMS of the residual of the firmware's calibration in the log (in its own orientation ``hf``), firmware
    unit; ``field`` the body-frame field (N, 3) or its magnitude (N,); ``tilt`` (body -> level, roll and pitch) for
    the heading-free residual."""
    A, o, m = held.algebra()
    x = motors.get(held.motor_type or "", np.zeros(len(raw)))
    B = (raw @ hf.P_u.T + o) @ A.T + x[:, None] * m
    if tilt is not None:
        L = np.einsum("nij,nj->ni", tilt, B @ hf.P_h)  # B~ -> body -> level
        H = np.einsum("nij,nj->ni", tilt, field)
        d = np.column_stack([np.hypot(L[:, 0], L[:, 1]) - np.hypot(H[:, 0], H[:, 1]), L[:, 2] - H[:, 2]])
        return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
    if vector:
        return float(np.sqrt(np.mean(np.sum((B - field @ hf.P_h.T) ** 2, axis=1))))
    return float(np.sqrt(np.mean((np.linalg.norm(B, axis=1) - field) ** 2)))


def level_table(table: list[dict[str, Any]], unit: str) -> str:
    """The fit report's table of levels: level, parameters, RMS, held-out RMS, identified, limits, chosen."""
    lines = [f"{'level':<10}{'motor':<10}{'params':>7}{'rms':>11}{'held-out':>11}  {'identified':<11}"
             f"{'excited':>8}  {'limits':<9}chosen   [{unit}]"]
    for row in table:
        ident = "all" if row["identified"] else (f"{row['n_identified']} of {row['n_params']}" if row.get(
            "n_identified") else "none")
        limits = "ok" if row["within_limits"] else "outside"
        if row["at_limit"]:
            limits = "at limit"
        excited = f"{row['excitation']:.2f}" if row.get("excitation") is not None else "-"
        lines.append(f"{row['level']:<10}{row['motor'] or '-':<10}{row['n_params']:>7}{row['rms']:>11.4g}"
                     f"{row['heldout_rms']:>11.4g}  {ident:<11}{excited:>8}  {limits:<9}"
                     f"{'<--' if row['chosen'] else ''}")
    lines.append(f"(excited: the weakest direction's excitation by the fitted rows, 1 = a turn through all attitudes; "
                 f"a direction below {DIRECTION_EXCITATION_MIN:g} is not identified, offsets below {EXCITATION_MIN:g} "
                 "are not written, whatever the residual)")
    return "\n".join(lines)


def candidate_field(compass: Mapping[str, Any], raw: ArrayLike, units: str, *,
                    motor_values: ArrayLike | None = None, input_orientation: int | None = None) -> NDArray[np.float64]:
    """The field a level's candidate (a row's ``compass`` of the level table) makes of the raw readings, as the
    calibration of the chosen one does (:func:`firmware_calibration`: ``W (v - b) + m x``).

    Parameters
    ----------
    compass : mapping
        A candidate's parameters (:meth:`~trimag.models.firmware.FirmwareCompass.as_dict`).
    raw : array_like, shape (N, 3)
        The raw readings (the log's calibration undone), in ``units``.
    units : str
        The readings' unit; the field is given in it too.
    motor_values : array_like, shape (N,), optional
        The motor channel of the candidate's ``motor_type`` (A for current, 0..1 for throttle); NaN where missing.
    input_orientation : int, optional
        The rotation already applied to the raw input (the calibration's ``firmware["input_orientation"]``).

    Returns
    -------
    ndarray, shape (N, 3)
        The corrected body field, ``units``.
    """
    from ..models.firmware import FirmwareCompass

    fc = FirmwareCompass.from_dict(compass)
    factor = convert(1.0, fc.unit, units)
    fr = _frame(fc.target, int(fc.orientation), input_orientation)
    A, o, m = fc.algebra()
    v = np.asarray(raw, dtype=np.float64) / factor
    out = (v @ fr.P_u.T + o) @ A.T
    if fc.motor_type is not None:
        if motor_values is None:
            raise TrimagInputError(f"the candidate has a {fc.motor_type} term: give its motor channel")
        out = out + np.asarray(motor_values, dtype=np.float64)[:, None] * m
    return np.asarray(out @ fr.P_h * factor, dtype=np.float64)


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
        "to the firmware's (the compass's own names, firmware unit)", noise_std=fit.noise_std * factor,
        inflation=fit.inflation, unit=compass.unit,
    )
    firmware = {**compass.as_dict(), "level": fit.level, "levels": fit.table, "held": fit.held,
                "orientation_decision": fit.orientation, "residual": fit.residual_kind,
                "input_orientation": input_orientation, "motor_channel": motor_channel if regressors else None,
                "param_std": fit.param_std, "rms_before": fit.rms_before, "rms_after": fit.rms_after,
                "halves": fit.halves, "absent": list(fit.absent), "heading": fit.heading, "instance": fit.instance,
                "verdict": fit.verdict, "param_status": fit.param_status}
    warnings = [m[len("warning: "):] for m in fit.messages if m.startswith("warning: ")]
    diag: dict[str, Any] = {"firmware": jsonable(firmware), **(diagnostics or {})}
    if warnings:
        diag["warnings"] = list(diag.get("warnings", [])) + warnings
    stats = {"n_samples": int(fit.n_samples), "n_used": int(fit.n_samples), "iterations": 1, "converged": True,
             "rms_before": fit.rms_before * factor, "rms_after": fit.rms_after * factor,
             "residual": fit.residual_kind}
    return Calibration.from_matrix_offset(
        W, b_data, units=units, model="affine", method=f"firmware-{compass.target}",
        params=compass.parameters(fit.instance),
        reference=None if reference is None else dict(reference), stats=stats, uncertainty=uncertainty,
        diagnostics=diag, regressors=regressors,
    )
