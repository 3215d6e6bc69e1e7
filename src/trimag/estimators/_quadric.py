"""Paper D's linear quadric design and its identifiability analysis, shared by ``quadric``, ``bfgs`` and ``lms``
(not public API; Zhang & Cheng 2009, methods.md paper D)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.chunks import row_blocks
from .._core.normalise import normalisation_stats
from .._core.qr import BlockedQR
from .._core.rowwise import row_dot
from ..errors import IdentifiabilityError, TrimagInputError
from ..fields.reference import ScalarReference
from ..models.zhang_cheng import ZhangCheng
from ..quality.diagnostics import CONDITION_ERROR, CONDITION_WARN, check_condition, design_condition
from ._common import scalar_reference

__all__ = [
    "DESIGN_TERMS", "PARAM_NAMES", "Identifiability", "check_identifiable", "diagnostics_entries",
    "identifiability_report", "physical_jacobian", "quadric_solve", "quadric_terms", "require_magnitude",
]


@dataclass
class _Design:
    """The linear problem ``G h = y`` on ``u = (V - centre) / scale``, as the QR factorisation of ``[G | y]``
    accumulated block by block (:class:`._qr.BlockedQR`: ``G`` (N, 9) is never held whole)."""

    system: BlockedQR
    centre: NDArray[np.float64]
    scale: float


def _linear_design(V: NDArray[np.float64]) -> _Design:
    norm = normalisation_stats(V)
    centre, scale = norm.centre, norm.scale
    system = BlockedQR(9)
    for rows in row_blocks(len(V)):
        P = quadric_terms((V[rows] - centre) / scale)
        system.add(np.column_stack([P[:, 0] - P[:, 2], P[:, 1] - P[:, 2], P[:, 3:]]), -P[:, 2])
    return _Design(system, centre, scale)


def physical_jacobian(V: NDArray[np.float64], model: ZhangCheng) -> NDArray[np.float64]:
    """Jacobian (N, 9) of ``r_i = |M (V_i - b)|^2`` w.r.t. ``(alpha, beta, gamma, kx, ky, kz, bx, by, bz)``.

    ``M = (K A)^-1``, so ``dM = -M dD M`` for ``D = K A``.
    """
    M, b = model.correction()
    e = V - b
    y = e @ M.T
    ca, sa = np.cos(model.alpha), np.sin(model.alpha)
    cb, sb = np.cos(model.beta), np.sin(model.beta)
    cg, sg = np.cos(model.gamma), np.sin(model.gamma)
    kx, ky = model.kx, model.ky
    A = model.a_matrix()
    dD = np.zeros((6, 3, 3))
    dD[0, 0] = [-kx * cg * sa, 0.0, kx * ca]  # alpha
    dD[1, 1] = [0.0, -ky * sb, ky * cb]  # beta
    dD[2, 0] = [-kx * sg * ca, kx * cg, 0.0]  # gamma
    dD[3, 0] = A[0]  # kx
    dD[4, 1] = A[1]  # ky
    dD[5, 2] = A[2]  # kz
    J = np.empty((len(V), 9))
    for j in range(6):
        dM = -M @ dD[j] @ M
        J[:, j] = 2.0 * row_dot(y, e @ dM.T)
    J[:, 6:] = -2.0 * (y @ M)
    return J


@dataclass
class Identifiability:
    """What the samples can determine of the ``zhang-cheng`` model.

    Attributes
    ----------
    rank, n_columns, condition_number : int, int, float
        Of the linear design ``G`` (column-normalised).
    undetermined_terms : list of str
        Columns of ``G`` in its numerically null directions.
    physical_rank, physical_condition_number : int, float
        Of the Jacobian w.r.t. the nine physical parameters (column-normalised).
    undetermined : list of str
        Physical parameters in the Jacobian's null directions (singular value < s_max / CONDITION_ERROR).
    poorly_determined : list of str
        Physical parameters in directions with singular value < s_max / CONDITION_WARN.
    estimate : ZhangCheng or None
        The linear solution when the design has full rank and gives an ellipsoid.
    """

    rank: int
    n_columns: int
    condition_number: float
    undetermined_terms: list[str]
    physical_rank: int
    physical_condition_number: float
    undetermined: list[str]
    poorly_determined: list[str]
    estimate: ZhangCheng | None = None
    singular_values: list[float] = field(default_factory=list)
    estimate_error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary for ``Calibration.diagnostics``."""
        return {
            "design": "quadric, trace-normalised (N, 9): " + ", ".join(DESIGN_TERMS),
            "rank": self.rank,
            "n_columns": self.n_columns,
            "condition_number": self.condition_number,
            "singular_values": self.singular_values,
            "undetermined_terms": self.undetermined_terms,
            "physical_rank": self.physical_rank,
            "physical_condition_number": self.physical_condition_number,
            "undetermined": self.undetermined,
            "poorly_determined": self.poorly_determined,
            "thresholds": {"undetermined": CONDITION_ERROR, "poorly_determined": CONDITION_WARN},
        }

    def message(self) -> str:
        """The sentence an :class:`IdentifiabilityError` carries."""
        names = self.undetermined or self.undetermined_terms
        return (
            f"the data cannot identify the zhang-cheng model: the quadric design has rank {self.rank} of "
            f"{self.n_columns} (condition number {self.condition_number:.3g}); undetermined: "
            f"{', '.join(names) if names else 'none named'}; {_HINT}"
        )


def _rank(s: NDArray[np.float64], threshold: float) -> int:
    return int(np.sum(s > s[0] / threshold)) if s[0] > 0 else 0


def _in_subspace(
    vt: NDArray[np.float64], s: NDArray[np.float64], names: tuple[str, ...], *, threshold: float, share: float
) -> list[str]:
    """Names whose unit vector has a component larger than ``share`` in the span of the right singular
    vectors with singular value below ``s[0] / threshold`` (independent of how that span's basis is chosen)."""
    weak = vt[s <= s[0] / threshold] if s[0] > 0 else vt
    if len(weak) == 0:
        return []
    proj = np.linalg.norm(weak, axis=0)
    return [n for n, p in zip(names, proj, strict=True) if p > share]


def identifiability_report(V: NDArray[np.float64], F2: float) -> Identifiability:
    """Rank, condition number and undetermined parameters of ``zhang-cheng`` for samples ``V`` (N, 3).

    The physical Jacobian is evaluated at the linear solution when there is one, otherwise at the nominal
    sensor (no angles, equal gains matching the mean magnitude, zero offsets).
    """
    design = _linear_design(V)
    cond, s, vt = design_condition(design.system.R)  # R: the singular values and vectors of G
    rank = _rank(s, CONDITION_ERROR)
    terms = _in_subspace(vt, s, DESIGN_TERMS, threshold=CONDITION_ERROR, share=0.05)
    estimate: ZhangCheng | None = None
    error: str | None = None
    if rank == len(s):
        try:
            estimate, _ = quadric_solve(V, F2, design)
        except IdentifiabilityError as exc:
            error = str(exc)
    at = estimate
    if at is None:
        k0 = float(np.sqrt(np.einsum("ij,ij->", V, V) / len(V) / F2))
        at = ZhangCheng(kx=k0, ky=k0, kz=k0)
    physical = BlockedQR(9)  # the physical Jacobian block by block: its triangular factor has J's singular values
    for rows in row_blocks(len(V)):
        physical.add(physical_jacobian(V[rows], at))
    pcond, ps, pvt = design_condition(physical.R)
    prank = _rank(ps, CONDITION_ERROR)
    undetermined = _in_subspace(pvt, ps, PARAM_NAMES, threshold=CONDITION_ERROR, share=0.05)
    poorly = _in_subspace(pvt, ps, PARAM_NAMES, threshold=CONDITION_WARN, share=0.3)
    return Identifiability(
        rank=rank,
        n_columns=len(s),
        condition_number=cond,
        undetermined_terms=terms,
        physical_rank=prank,
        physical_condition_number=pcond,
        undetermined=undetermined,
        poorly_determined=[p for p in poorly if p not in undetermined],
        estimate=estimate,
        singular_values=s.tolist(),
        estimate_error=error,
    )


def check_identifiable(report: Identifiability, *, linear: bool) -> None:
    """Raise :class:`IdentifiabilityError` (exit 3) when the data cannot identify the model; warn when weak.

    ``linear=True`` (the ``quadric`` method) needs the linear design at full rank; the iterative methods need
    the physical Jacobian at full rank.
    """
    if report.physical_rank < 9 or (linear and report.rank < report.n_columns):
        raise IdentifiabilityError(report.message())
    cond = report.condition_number if linear else report.physical_condition_number
    check_condition(
        cond,
        what="the zhang-cheng model",
        hint=_HINT,
        weak=report.poorly_determined,
        error=np.inf,
    )


def require_magnitude(reference: Any, n: int, units: str, method: str) -> ScalarReference:
    """The scalar reference, which paper D's methods require (a known field magnitude)."""
    ref = scalar_reference(reference, n, units)
    if ref.values is None:
        raise TrimagInputError(
            f"method {method!r} needs the field magnitude: give `reference=F` in the data's unit (or "
            "`igrf_spec=LAT,LON,ALT_M,DATE`, or `reference_column=NAME`)"
        )
    return ref


def diagnostics_entries(report: Identifiability, model: ZhangCheng) -> dict[str, Any]:
    """The identifiability entries every paper-D fit puts in ``Calibration.diagnostics``."""
    return {
        "rank": report.rank,
        "condition_number": report.condition_number,
        "undetermined": list(report.undetermined),
        "identifiability": report.as_dict(),
        "params_display": model.as_report(),
        "w": model.w_vector().tolist(),
    }


#: Columns of the trace-normalised linear design ``G``.
DESIGN_TERMS: tuple[str, ...] = ("xx-zz", "yy-zz", "xy", "xz", "yz", "x", "y", "z", "1")


#: Physical parameters of the ``zhang-cheng`` model, in model order.
PARAM_NAMES: tuple[str, ...] = ZhangCheng.param_names()


_HINT = (
    "record the sensor in more attitudes: a turn about a single axis cannot separate that axis' gain from "
    "its offset, nor the tilt angles of the other axes from their offsets; add a turn about a second axis"
)


def quadric_solve(
    V: NDArray[np.float64], F2: float, design: _Design | None = None
) -> tuple[ZhangCheng, NDArray[np.float64]]:
    """The linear solve (steps 1-4 of the module docstring).

    Parameters
    ----------
    V : ndarray, shape (N, 3)
        Sensor output, data unit.
    F2 : float
        Squared field magnitude, data unit squared.

    Returns
    -------
    model : ZhangCheng
        Physical parameters.
    h : ndarray, shape (9,)
        The least-squares solution of ``G h = -u_z^2`` (normalised coordinates, trace gauge).

    Raises
    ------
    IdentifiabilityError
        The fitted quadric is not an ellipsoid (noise too large for the attitude coverage).
    """
    d = design if design is not None else _linear_design(V)
    # G = Q R: the problem G h = y is R h = Q^T y, with G's column norms (those of R) as the scaling
    R = d.system.R
    norms = np.linalg.norm(R, axis=0)
    norms[norms == 0] = 1.0
    h = np.linalg.lstsq(R / norms, d.system.qtb, rcond=None)[0] / norms
    Wu = np.array([h[0], h[1], 1.0 - h[0] - h[1], *h[2:]])
    Q = np.array(
        [[Wu[0], Wu[3] / 2, Wu[4] / 2], [Wu[3] / 2, Wu[1], Wu[5] / 2], [Wu[4] / 2, Wu[5] / 2, Wu[2]]]
    )
    try:
        b_u = np.linalg.solve(Q, -0.5 * Wu[6:9])
    except np.linalg.LinAlgError:
        raise IdentifiabilityError(
            "the fitted quadric is degenerate (not an ellipsoid); " + _HINT
        ) from None
    level = float(b_u @ Q @ b_u - Wu[9])
    if not level > 0 or np.any(np.linalg.eigvalsh(Q) <= 0):
        raise IdentifiabilityError(
            "the fitted quadric is not an ellipsoid (noise too large for the attitudes covered); " + _HINT
        )
    Q = Q * (F2 / d.scale**2) / level
    b = d.centre + d.scale * b_u
    try:
        model = ZhangCheng.from_quadric(Q, b)
    except TrimagInputError as exc:
        raise IdentifiabilityError(f"the fitted ellipsoid is outside the zhang-cheng model ({exc}); {_HINT}") from None
    return model, h


def quadric_terms(V: ArrayLike) -> NDArray[np.float64]:
    """The monomials ``phi(V)`` of the quadratic form, shape (N, 10), so that ``phi(V) @ W == |B|^2``.

    Parameters
    ----------
    V : array_like, shape (N, 3)
        Sensor output (any unit).
    """
    v = np.asarray(V, dtype=np.float64)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z, np.ones_like(x)], axis=-1)
