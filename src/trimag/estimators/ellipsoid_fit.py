"""``ellipsoid-fit``: the algebraic ellipsoid fit of Li & Griffiths (2004), one pass over the data.

The quadric ``a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z + d = 0`` is fitted by
minimising ``v^T S v`` (``S = D^T D``, the 10x10 scatter of the design ``D``) under the constraint
``4J - I^2 = 1`` (``k = 4``), which guarantees an ellipsoid: Q. Li, J. G. Griffiths, "Least squares ellipsoid
specific fitting", Proc. Geometric Modeling and Processing, 2004. The scatter matrix is accumulated in chunks,
so memory does not grow with N.

The centre of the quadric is the hard-iron offset; the upper Cholesky factor of its normalised shape matrix is
the soft-iron correction ``W`` (upper triangular). This fit is fast and needs no start, but it is biased under
noise (the scale shrinks by about (sigma/F)^2); ``ml`` refines it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..quality.diagnostics import check_not_degenerate
from ._common import algebraic_ellipsoid, gauge_scale, normalisation_of, scalar_reference
from ._finish import ellipsoid_result
from .base import Estimator

__all__ = ["EllipsoidFit"]


class EllipsoidFit(Estimator):
    """Algebraic ellipsoid fit (Li & Griffiths 2004), no iterations.

    Parameters
    ----------
    model : str
        ``"ellipsoid"``.
    form : {"upper", "symmetric"}
        Gauge of the returned soft-iron matrix.
    """

    name = "ellipsoid-fit"
    models = ("ellipsoid",)

    def __init__(self, model: str = "ellipsoid", form: str = "upper") -> None:
        self.model = model
        self.form = form

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        principal = check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        # the fit is invariant to translation and scale: normalise chunk by chunk, no copy of B
        norm = normalisation_of(B)
        W_u, c_u, cond = algebraic_ellipsoid(B, norm)
        W = W_u / norm.scale
        offset = norm.centre + norm.scale * c_u
        W, F_hat = gauge_scale(W, ref.values)
        return ellipsoid_result(
            B, W, offset, ref=ref, F_hat=F_hat, sigma=None, model=model, method=self.name, units=units,
            form=self.form, diagnostics={"condition_number": cond},
            uncertainty_note="Fisher information at the estimate: a lower bound; this algebraic fit is biased "
            "under strong noise (use ml)",
            principal=principal,
        )


