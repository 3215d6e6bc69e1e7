"""What a firmware-space fit (:mod:`trimag.vehicle.firmware`) may claim (issue 38): which of a level's directions the
data's own excitation identifies, what each written parameter's status is, and whether the parameters beat the
log's own calibration on data they were not fitted to.

**Excitation** (:func:`excitation`). A residual, however small, identifies only the directions of the parameters
that the fitted rows move: a heading-free fit of a log that never turned has two equations per sample (the
horizontal and vertical field) for three offsets, and fits the third to nothing. The level's Jacobian is taken in
*effect units* (a parameter times how much one unit of it moves the field: offsets 1, matrix entries the field
``F``, a motor term the standard deviation of its channel), and its singular values over ``sqrt(N)`` are each
direction's excitation: 1 for an offset of a fit through all attitudes (one unit of it moves every sample's
residual by one unit), ``sin`` of the spread of the field's direction across it for a heading-free offset, near 0
for a direction the rows do not move. A direction below :data:`DIRECTION_EXCITATION_MIN` is not identified
whatever the noise (held at the level below's solution): a reference 0.5 % off or 1 deg of attitude error
(systematic, not averaged away) would move it by fifty times as much as the field it explains. The offsets have no
level below: unless their least excited direction reaches :data:`EXCITATION_MIN` (for a heading-free fit about
6 deg RMS of turning across it) no level is written, and the refusal names ``--heading`` (a vehicle at rest, its
true heading known), ``--level-turn`` and a calibration turn (:class:`NotExcited`, exit 3). A heading-free fit's
offsets are judged from the reference before any level (:func:`heading_free_excitation`): at a poor solution the
Jacobian's horizontal direction is noise and looks excited.

**Status** (:func:`parameter_status`). Each firmware parameter is *fitted* (the data determine it: a sigma is
printed), *held* (the level does not fit it: the log's value) or *not identified* (it moves along a direction the
data do not identify: its value is the level below's, and no sigma is printed).

**Verdict** (:func:`unfitted_verdict`). The parameters and the log's own calibration are put through the
firmware's formula on rows the fit did not see (the rows ``--rows``/``--where`` left out, else each of the
contiguous held-out folds predicted by the fit on the others) with the fit's own residual; the fit either wins, or
is refused (``level="auto"``: keep the log's calibration, exit 3) or warned of (a level asked for).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import IdentifiabilityError
from ..models.firmware import FirmwareCompass, rotation_matrix
from ._firmware_halves import firmware_rms
from ._firmware_levels import LevelProblem, LevelSolution

__all__ = ["DIRECTION_EXCITATION_MIN", "EXCITATION_MIN", "Excitation", "NotExcited", "excitation",
           "heading_free_excitation", "not_excited_message", "parameter_status", "restrict_basis", "unfitted_verdict",
           "verdict_message"]

#: The offsets are identified only when their least excited direction (singular value of their effect-unit Jacobian
#: over sqrt(N)) reaches this (module docstring): below it no level is written.
EXCITATION_MIN = 0.1
#: Any other direction of a level below this excitation is not identified, whatever the residual's noise: held at
#: the level below's solution. Lower than the offsets': a held direction has the level below to fall back on, and a
#: simulated heading-free flight tilted 35 deg recovers its full matrix's weakest direction (0.05) to the noise.
DIRECTION_EXCITATION_MIN = 0.02
#: The rows left out by ``--rows``/``--where`` judge the fit when there are at least this many.
UNFITTED_MIN_ROWS = 12


class NotExcited(IdentifiabilityError):
    """The data's excitation does not identify the offsets: no level is written (exit 3)."""


@dataclass
class Excitation:
    """A level's excitation (module docstring)."""

    #: each direction's excitation, largest first
    values: NDArray[np.float64]
    #: the directions (rows, in effect units: parameter times :attr:`scales`)
    directions: NDArray[np.float64]
    scales: NDArray[np.float64]
    #: the offsets' own excitation (their three columns alone), smallest
    offsets: float
    #: the offsets' least excited direction (unit vector over o_x, o_y, o_z)
    offsets_direction: NDArray[np.float64]
    #: the parameters dominating each direction below :data:`DIRECTION_EXCITATION_MIN`
    unexcited: list[str] = field(default_factory=list)

    @property
    def weakest(self) -> float:
        return float(self.values.min()) if len(self.values) else 0.0

    @property
    def offsets_excited(self) -> bool:
        return self.offsets >= EXCITATION_MIN

    def as_dict(self) -> dict[str, Any]:
        return {"weakest": self.weakest, "offsets": self.offsets, "values": self.values.tolist(),
                "unexcited": list(self.unexcited), "offsets_minimum": EXCITATION_MIN,
                "direction_minimum": DIRECTION_EXCITATION_MIN,
                "offsets_direction": self.offsets_direction.tolist()}


def _excitation_scales(problem: LevelProblem, F: float) -> NDArray[np.float64]:
    """How much one unit of each parameter moves the field: offsets 1, matrix entries ``F``, a motor term the
    standard deviation of its channel (its mean is the offsets')."""
    x_std = float(np.std(problem.x)) if problem.x is not None else 1.0
    return np.array([1.0 if n.startswith("o_") else (max(x_std, 1e-300) if n.startswith("m_") else F)
                     for n in problem.names()])


def excitation(problem: LevelProblem, jacobian: NDArray[np.float64], F: float) -> Excitation:
    """The excitation of a level's directions on its rows (module docstring).

    Parameters
    ----------
    problem : LevelProblem
        The level (its parameter names and rows).
    jacobian : ndarray, shape (width N, p)
        The residual's Jacobian at the solution.
    F : float
        The field's magnitude, firmware unit.
    """
    n = max(len(problem.u), 1)
    scales = _excitation_scales(problem, F)
    _, s, vt = np.linalg.svd(jacobian / scales, full_matrices=False)
    values = s / np.sqrt(n)
    names = problem.names()
    k = problem.n_A
    _, so, vto = np.linalg.svd(jacobian[:, k:k + 3], full_matrices=False)
    unexcited: list[str] = []
    for row in vt[values < DIRECTION_EXCITATION_MIN]:
        name = names[int(np.argmax(np.abs(row)))]
        if name not in unexcited:
            unexcited.append(name)
    return Excitation(values, vt, scales, float(so.min() / np.sqrt(n)), vto[-1], unexcited)


def heading_free_excitation(field_body: NDArray[np.float64], tilt: NDArray[np.float64]) -> Excitation:
    """The offsets' excitation of a heading-free fit, from the reference alone (the Jacobian at a fit that matches
    it; at a poor solution, where the corrected horizontal field is near zero, the Jacobian's horizontal direction
    is noise and would look excited).

    A body-frame offset ``o`` moves sample ``i``'s horizontal magnitude by ``e_i . (T_i o)`` (``e_i`` the unit
    horizontal direction of the level-frame field ``T_i h_i``) and its vertical component by ``(T_i o)_z``: two rows
    per sample; the offsets' excitation is the smallest singular value of those rows over ``sqrt(N)``.

    Parameters
    ----------
    field_body : ndarray, shape (N, 3)
        The body-frame reference field.
    tilt : ndarray, shape (N, 3, 3)
        Each sample's roll and pitch (body -> level frame).
    """
    L = np.einsum("nij,nj->ni", tilt, field_body)
    horizontal = L.copy()
    horizontal[:, 2] = 0.0
    e = horizontal / np.maximum(np.linalg.norm(horizontal, axis=1, keepdims=True), 1e-300)
    rows = np.concatenate([np.einsum("ni,nij->nj", e, tilt), tilt[:, 2, :]])
    _, s, vt = np.linalg.svd(rows, full_matrices=False)
    values = s / np.sqrt(max(len(field_body), 1))
    return Excitation(values, vt, np.ones(3), float(values.min()), vt[-1],
                      [f"o_{'xyz'[int(np.argmax(np.abs(r)))]}" for r in vt[values < DIRECTION_EXCITATION_MIN]])


def restrict_basis(basis: NDArray[np.float64], scales: NDArray[np.float64], exc: Excitation) -> NDArray[np.float64]:
    """The identified directions ``basis`` (columns, in parameters over ``scales``, as
    :func:`trimag.vehicle.firmware._identified` gives them) without the directions below
    :data:`DIRECTION_EXCITATION_MIN`."""
    low = exc.directions[exc.values < DIRECTION_EXCITATION_MIN]
    if not len(low) or not basis.shape[1]:
        return basis
    D = (low / exc.scales / scales).T  # effect units -> parameters -> parameters over scales
    Q, _ = np.linalg.qr(D)
    rest = basis - Q @ (Q.T @ basis)
    u, s, _ = np.linalg.svd(rest, full_matrices=False)
    return np.asarray(u[:, s > 1e-6 * max(float(s.max(initial=0.0)), 1e-300)], dtype=np.float64)


def not_excited_message(exc: Excitation, offset_names: list[str], heading_free: bool, cone_deg: float) -> str:
    """The refusal of a fit whose offsets the data's excitation does not identify (one line)."""
    d = np.abs(exc.offsets_direction)
    along = " and ".join(offset_names[int(i)] for i in np.argsort(-d) if d[i] >= 0.3 * d.max())
    what = ("a heading-free fit sees two components of the field (horizontal and vertical) per sample: with the "
            "field's direction in the compass fixed, that is two equations for three offsets, whatever the residual"
            if heading_free else "the rows do not move the field's direction across them")
    return (f"the data do not identify the offsets: the field's direction in the compass stayed within "
            f"{cone_deg:.0f} deg, so the fitted rows excite the offsets along {along} to {exc.offsets:.2g} of what a "
            f"turn through all headings would ({EXCITATION_MIN:g} needed); {what}, and the values would come from "
            "the reference (the site typed or the log's GPS) rather than from the data: give a vehicle at rest its "
            "true heading (`--heading DEG` without --target, as ArduPilot's MAG_CAL_YAW), fit one that turned "
            "level with `--level-turn`, or record a calibration turn through all headings, pitched and rolled")


def parameter_gradient(values: Callable[[NDArray[np.float64]], Mapping[str, float]], theta: NDArray[np.float64],
                       names: list[str]) -> NDArray[np.float64]:
    """d(parameter)/d(theta), shape (len(names), len(theta)): forward differences of the firmware parameters
    ``values(theta)`` (name -> value) named in ``names`` (a step of 1e-6 relative, at least 1e-6)."""
    base = values(theta)
    G = np.zeros((len(names), len(theta)))
    for j in range(len(theta)):  # one step per fitted parameter (at most ~16), not per sample
        step = 1e-6 * max(1.0, abs(theta[j]))
        t = theta.copy()
        t[j] += step
        moved = values(t)
        G[:, j] = [(moved[k] - base[k]) / step for k in names]
    return G


def parameter_status(values: Callable[[NDArray[np.float64]], Mapping[str, float]], theta: NDArray[np.float64],
                     jacobian: NDArray[np.float64], n_unidentified: int,
                     effect: NDArray[np.float64] | None = None) -> dict[str, str]:
    """``{firmware parameter: "fitted" | "held" | "not identified"}`` of a level's solution.

    ``values`` maps a parameter vector to the firmware's parameters. A parameter no parameter of the level moves is
    *held*. The directions the data do not identify are the ``n_unidentified`` least excited directions of the
    level's ``jacobian`` in *effect units* (parameters times ``effect``, :func:`excitation`'s scales, where an offset
    and a matrix entry are commensurate; near-null directions of the Jacobian, whatever the metric); a parameter
    whose gradient there has more than 10 % of its length along them moves with what the data do not see: *not
    identified*."""
    theta = np.asarray(theta, dtype=np.float64)
    names = list(values(theta))
    G = parameter_gradient(values, theta, names)
    es = np.ones(len(theta)) if effect is None else np.asarray(effect, dtype=np.float64)
    weak = np.zeros((0, len(theta)))
    if n_unidentified > 0:
        _, _, vt = np.linalg.svd(jacobian / es, full_matrices=False)
        weak = vt[-n_unidentified:]  # rows: the least excited directions, in effect units
    out: dict[str, str] = {}
    for i, name in enumerate(names):
        g = G[i] / es  # d parameter / d effect
        total = float(np.linalg.norm(g))
        if total == 0.0:
            out[name] = "held"
        else:
            out[name] = "not identified" if np.linalg.norm(weak @ g) > 0.1 * total else "fitted"
    return out


def unfitted_verdict(
    fitted: FirmwareCompass, held: FirmwareCompass, applied: int | None, *,
    unfitted: Mapping[str, Any] | None = None,
    folds: Callable[[], tuple[float, int]] | None = None,
    raw: NDArray[np.float64] | None = None, field_body: NDArray[np.float64] | None = None,
    motors: Mapping[str, NDArray[np.float64]] | None = None, tilt: NDArray[np.float64] | None = None,
) -> dict[str, Any]:
    """The fit against the log's calibration on data it was not fitted to, through the firmware's formula.

    Parameters
    ----------
    fitted, held : FirmwareCompass
        The parameters to be written and the calibration in force in the log.
    applied : int or None
        The rotation already applied to the raw readings (the firmware's enum value).
    unfitted : mapping, optional
        The rows left out of the fit: ``raw`` (n, 3, rotated by ``applied``, firmware unit), ``field`` (n, 3 body
        frame, or (n,) magnitude), ``motors`` and ``tilt`` (or None), ``what`` (how they were left out).
    folds : callable, optional
        Without ``unfitted``: ``() -> (RMS of the held-out folds predicted by the fit on the others, n)``, judged
        against the log's calibration on all the fitted rows ``raw``, ``field_body``, ``motors``, ``tilt``.

    Returns
    -------
    dict
        ``judged_on`` (``"rows left out"`` / ``"held-out folds"``), ``what``, ``n_rows``, ``rms_log``, ``rms_fit``,
        ``ratio`` (fit over log), ``better`` (bool).
    """
    def sensor(v: NDArray[np.float64]) -> NDArray[np.float64]:
        R0 = np.eye(3) if applied is None else rotation_matrix(held.target, applied)
        return np.asarray(v @ R0, dtype=np.float64)  # the readings in the sensor's own frame

    if unfitted is not None:
        v = sensor(np.asarray(unfitted["raw"], dtype=np.float64))
        f, m, t = unfitted["field"], unfitted.get("motors") or {}, unfitted.get("tilt")
        rms_log = firmware_rms(held, v, f, m, t)
        rms_fit = firmware_rms(fitted, v, f, m, t)
        out = {"judged_on": "rows left out", "what": str(unfitted.get("what", "")), "n_rows": len(v)}
    else:
        assert folds is not None and raw is not None and field_body is not None
        rms_fit, n = folds()
        rms_log = firmware_rms(held, sensor(raw), field_body, motors or {}, tilt)
        out = {"judged_on": "held-out folds", "what": "each contiguous fold predicted by the fit on the others",
               "n_rows": n}
    out.update(rms_log=float(rms_log), rms_fit=float(rms_fit),
               ratio=float(rms_fit / rms_log) if rms_log > 0 else float("inf"),
               better=bool(np.isfinite(rms_fit) and rms_fit < rms_log))
    return out


def verdict_message(verdict: Mapping[str, Any], unit: str) -> str:
    """One line: the fit and the log's calibration on data the fit did not see, and what that means."""
    where = (f"the {verdict['n_rows']} rows the fit did not see ({verdict['what']})" if verdict["judged_on"] ==
             "rows left out" else f"held-out data ({verdict['what']}, {verdict['n_rows']} rows)")
    figures = (f"this fit leaves {verdict['rms_fit']:.4g} {unit} RMS against the log's calibration's "
               f"{verdict['rms_log']:.4g}")
    if verdict["better"]:
        return f"on {where}, through the firmware's formula: {figures}: the fit improves on the log's calibration"
    return (f"on {where}, through the firmware's formula, {figures} ({verdict['ratio']:.2f}x): the parameters would "
            "make the vehicle's compass worse than the calibration it has; keep the log's calibration, or record a "
            "calibration flight turning through all headings, pitched and rolled, away from metal")


def fold_rms(problem: LevelProblem, sol: LevelSolution, bounds: Any, n_folds: int,
             to_compass: Callable[[LevelSolution], FirmwareCompass], raw_sensor: NDArray[np.float64],
             field_body: NDArray[np.float64], motors: Mapping[str, NDArray[np.float64]],
             tilt: NDArray[np.float64] | None) -> tuple[float, int]:
    """RMS over every row of the residual, through the firmware's formula, of the parameters fitted on the other
    contiguous folds (``n_folds`` of them); the rows as :func:`firmware_rms` takes them."""
    n = len(raw_sensor)
    edges = np.linspace(0, n, n_folds + 1).astype(int)
    total, count = 0.0, 0
    refit = problem.fold_refitter(sol) if bounds is None else None  # Gauss-Newton from the whole log's solution
    for k in range(n_folds):
        fold = np.arange(edges[k], edges[k + 1])
        train = np.setdiff1d(np.arange(n), fold)
        theta = refit(int(edges[k]), int(edges[k + 1])) if refit is not None and len(fold) else None
        if theta is not None:
            A_k, o_k, m_k = problem.unpack(theta)
            part = dataclasses.replace(sol, A=A_k, o=o_k.copy(), m=m_k.copy(), theta=theta)
        elif sol.basis is not None and sol.theta_ref is not None and sol.scales is not None:
            part = problem.solve_in(sol.theta_ref, sol.basis, sol.scales, rows=train)
        else:
            part = problem.solve(sol.theta, rows=train, bounds=bounds)
        m = {kind: v[fold] for kind, v in motors.items()}
        rms = firmware_rms(to_compass(part), raw_sensor[fold], field_body[fold], m,
                           None if tilt is None else tilt[fold])
        total += rms**2 * len(fold)
        count += len(fold)
    return float(np.sqrt(total / max(count, 1))), count
