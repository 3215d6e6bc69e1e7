"""``quadric``: paper D's simple linear method (Zhang & Cheng 2009) and the identifiability report it shares.

With a known field magnitude ``F`` every sample satisfies (methods.md, paper D)::

    |B|^2 = (V - b)^T Q (V - b) = phi(V) . W = F^2,        Q = (KA)^-T (KA)^-1

(``phi`` and ``W`` as in :mod:`trimag.models.zhang_cheng`). Written as ``phi(V) . (W - F^2 e10) = 0`` the
equation is homogeneous: the data fix the ellipsoid (9 numbers) but a free constant term makes ``W`` itself
determined only up to scale, so a plain least-squares solve ``phi(V) W = F^2`` with ten unknowns is always
rank deficient (the null vector is ``W - F^2 e10``). The paper's own equation (5) is lost in the OCR; trimag
makes the solve linear and well posed the standard way:

1. normalise ``u = (V - c) / s`` (centroid ``c``, RMS radius ``s``) so the design is unit-free;
2. fix the scale by the trace, ``Q11 + Q22 + Q33 = 1``: nine unknowns
   ``h = (Q11, Q22, 2Q12, 2Q13, 2Q23, l_x, l_y, l_z, c0)`` from the linear least-squares problem
   ``G h = -u_z^2``, ``G = [u_x^2 - u_z^2, u_y^2 - u_z^2, u_x u_y, u_x u_z, u_y u_z, u_x, u_y, u_z, 1]`` (N, 9);
3. ``b_u = -Q^-1 l / 2``; the known magnitude sets the scale: ``Q <- Q (F/s)^2 / (b_u^T Q b_u - c0)``;
4. back to data units, ``b = c + s b_u`` and ``Q`` unchanged; ``M = cholesky(Q)^T`` (upper triangular) and the
   physical parameters follow in closed form (:meth:`ZhangCheng.from_quadric`).

With noise-free data this returns the true ``W`` to rounding; its ``rank`` and ``condition_number`` are those of
``G`` (column-normalised). When ``rank(G) < 9`` the samples lie on more than one quadric and no linear solve can
pick the ellipsoid: :class:`~trimag.errors.IdentifiabilityError` (exit 3) names the parameters concerned.

Which *physical* parameters the data cannot determine comes from the Jacobian of
``r_i = |M(theta) (V_i - b)|^2 - F^2`` with respect to the nine parameters ``theta``
(:func:`identifiability_report`); e.g. a turn about the sensor's Z axis alone leaves ``kz`` and ``bz``
(and ``alpha``/``bx``, ``beta``/``by``) inseparable.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import IdentifiabilityError
from ._quadric import (
    check_identifiable,
    diagnostics_entries,
    identifiability_report,
    require_magnitude,
)
from .base import Estimator, build_calibration

__all__ = ["Quadric"]


class Quadric(Estimator):
    """Paper D's linear least-squares method: ``W`` from one linear solve, then ``K``, the angles and ``b``.

    Needs a known field magnitude (``reference``). No options.

    Examples
    --------
    >>> import numpy as np
    >>> from trimag.models.zhang_cheng import ZhangCheng
    >>> truth = ZhangCheng(*np.radians([0.8, 0.5, 1.1]), 1.02, 0.99, 1.01, 0.03, 0.02, 0.01)
    >>> rng = np.random.default_rng(0)
    >>> B = rng.normal(size=(50, 3)); B /= np.linalg.norm(B, axis=1, keepdims=True)
    >>> est = Quadric().fit(truth.distort(B), 1.0)
    >>> round(est.calibration_.params["kx"], 9)
    1.02
    """

    name = "quadric"
    models = ("zhang-cheng",)
    requires_reference = True

    def __init__(self, model: str = "zhang-cheng") -> None:
        self.model = model

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        ref = require_magnitude(reference, len(B), units, self.name)
        assert ref.values is not None
        F2 = float(np.mean(ref.values**2))
        report = identifiability_report(B, F2)
        check_identifiable(report, linear=True)
        if report.estimate is None:
            raise IdentifiabilityError(report.estimate_error or report.message())
        est = report.estimate
        M, offset = est.correction()
        return build_calibration(
            B, M, offset, model=model, method=self.name, units=units, reference=ref,
            params=est.as_dict(), iterations=0, converged=True,
            diagnostics=diagnostics_entries(report, est),
        )
