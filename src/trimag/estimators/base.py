"""The estimator contract (style guide: scikit-learn) and the shared finishing step of every fit.

* ``__init__`` only stores keyword arguments under their own names; validation waits for ``fit``.
* ``fit(B, reference=None, *, units=..., attitude=None)`` validates, identifies, and returns ``self``.
* Fitted state ends in ``_``: ``calibration_``, ``residuals_``, ``cond_``, ``n_samples_``.
* ``transform(B)`` applies the fit; before ``fit`` it raises :class:`~trimag.errors.NotFittedError`.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any, ClassVar, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.threads import one_blas_thread
from ..calibration import Calibration
from ..errors import NotFittedError, TrimagInputError
from ..fields.reference import ScalarReference
from ..models import get_model
from ..quality.diagnostics import data_coverage
from ..quality.honesty import honest_uncertainty
from ..quality.metrics import before_after_stats, row_norms
from ..units import normalise_unit
from ..validation import check_field

__all__ = ["Estimator", "build_calibration"]


_INIT_PARAMETERS: dict[type, tuple[str, ...]] = {}


def _init_parameters(cls: type) -> tuple[str, ...]:
    """The keyword parameters of ``cls.__init__`` (looked up once per class: ``inspect.signature`` costs ~40 us)."""
    if cls in _INIT_PARAMETERS:
        return _INIT_PARAMETERS[cls]
    names = []
    for p in inspect.signature(cls.__init__).parameters.values():  # type: ignore[misc]
        if p.name == "self":
            continue
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            raise TypeError(f"{cls.__name__}.__init__ must not take *args or **kwargs")
        names.append(p.name)
    _INIT_PARAMETERS[cls] = tuple(names)
    return _INIT_PARAMETERS[cls]


class Estimator:
    """Base class of all identification methods.

    Class attributes
    ----------------
    name : str
        The ``--method`` name.
    models : tuple of str
        Models this method can identify; the first is the default.
    reference_kind : str
        ``"scalar"`` (magnitude optional or required, see ``requires_reference``), ``"none"`` (reference-free),
        ``"vector"`` (background vector + attitudes, paper C) or ``"gyro"`` (magnitude optional + the gyroscope).
    requires_reference : bool
        True when a known magnitude (or background vector) is mandatory.
    """

    name: ClassVar[str] = ""
    models: ClassVar[tuple[str, ...]] = ()
    reference_kind: ClassVar[str] = "scalar"
    requires_reference: ClassVar[bool] = False

    # ---- parameters (scikit-learn style, no dependency on it)
    @classmethod
    def _param_names(cls) -> tuple[str, ...]:
        return _init_parameters(cls)

    def get_params(self) -> dict[str, Any]:
        """The constructor's keyword arguments and their current values."""
        return {n: getattr(self, n) for n in self._param_names()}

    def set_params(self, **params: Any) -> Self:
        """Set constructor parameters; unknown names raise ``TrimagInputError``."""
        valid = set(self._param_names())
        for key, value in params.items():
            if key not in valid:
                raise TrimagInputError(
                    f"method {self.name!r} has no option {key!r}; its options are {sorted(valid)}"
                )
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    # ---- fitting
    def _resolve_model(self) -> str:
        model = getattr(self, "model", None) or self.models[0]
        if model not in self.models:
            raise TrimagInputError(
                f"method {self.name!r} identifies the model(s) {', '.join(self.models)}; got model {model!r}"
            )
        return str(model)

    def _min_samples(self, model: str) -> int:
        return int(get_model(model).n_identifiable) + 1

    def fit(
        self,
        B: ArrayLike,
        reference: Any = None,
        *,
        units: str | None = "unknown",
        attitude: Any = None,
    ) -> Self:
        """Identify the model from raw samples.

        Parameters
        ----------
        B : array_like, shape (N, 3)
            Raw sensor output in ``units``.
        reference : float, array_like (N,), "mean", ScalarReference, or None
            Field magnitude reference in ``units`` (scalar methods); for ``reference_kind == "vector"``
            the background field vector in the navigation frame, shape (3,).
        units : str
            Unit of ``B`` (and of a numeric reference); recorded in the Calibration.
        attitude : scipy.spatial.transform.Rotation or AngularRate, optional
            Per-sample attitude: N rotations body -> navigation frame (NED), so that a navigation-frame
            field is seen in the body frame as ``attitude.inv().apply(H_n)`` (docs/conventions.md); only for
            methods with ``reference_kind == "vector"``. For ``reference_kind == "gyro"`` the gyroscope
            (:class:`trimag.fields.gyro.AngularRate`: the samples' time stamps and the angular rate).

        Returns
        -------
        self
        """
        model = self._resolve_model()
        X = check_field(B, min_samples=self._min_samples(model), model=model)
        unit = normalise_unit(units)
        with one_blas_thread():  # small BLAS calls only: a second thread would just spin-wait (trimag._core.threads)
            cal = self._fit(X, reference, model=model, units=unit, attitude=attitude)
            cal = honest_uncertainty(cal, X, reference)  # repeated rows, correlated residuals, few samples
        self.calibration_ = cal
        self.n_samples_ = int(X.shape[0])
        # residuals_ is computed on first access (trimag.fit never needs it: one pass less over the data)
        self._residual_inputs: tuple[NDArray[np.float64], Any] | None = (X, reference)
        self._residuals: NDArray[np.float64] | None = None
        self.cond_ = float(cal.diagnostics.get("condition_number", np.nan))
        return self

    @property
    def residuals_(self) -> NDArray[np.float64]:
        """``|corrected_i| - F_i`` (N,) on the fitted samples, in their unit.

        Computed on first access from the samples given to :meth:`fit`. A C-ordered float64 array is not copied
        by ``fit`` (:func:`~trimag.validation.check_field`), so if you modify it in place in between, read
        ``residuals_`` before you do.
        """
        if not hasattr(self, "calibration_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet; call fit(B, reference) first")
        if self._residuals is None:
            assert self._residual_inputs is not None
            X, reference = self._residual_inputs
            cal = self.calibration_
            corrected = cal.apply(X)
            target = self._residual_target(corrected, reference, (cal.reference or {}).get("value"))
            self._residuals = row_norms(corrected) - target
            self._residual_inputs = None
        return self._residuals

    def _residual_target(self, corrected: NDArray[np.float64], reference: Any, ref_value: Any) -> Any:
        if isinstance(reference, ScalarReference) and reference.values is not None:
            return reference.values
        if reference is not None and np.ndim(reference) == 1 and len(reference) == len(corrected):
            return np.asarray(reference, dtype=np.float64)
        if ref_value is not None:
            return float(ref_value)
        return float(row_norms(corrected).mean())

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        raise NotImplementedError

    def transform(self, B: ArrayLike) -> NDArray[np.float64]:
        """Apply the fitted calibration to raw samples (N, 3)."""
        if not hasattr(self, "calibration_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet; call fit(B, reference) first")
        return self.calibration_.apply(B)


def build_calibration(
    B: NDArray[np.float64],
    matrix: ArrayLike,
    offset: ArrayLike,
    *,
    model: str,
    method: str,
    units: str,
    reference: ScalarReference,
    params: Mapping[str, float] | None = None,
    iterations: int = 0,
    converged: bool = True,
    fitted_magnitude: float | None = None,
    uncertainty: Mapping[str, Any] | None = None,
    diagnostics: Mapping[str, Any] | None = None,
    extra_stats: Mapping[str, Any] | None = None,
    coverage: Mapping[str, Any] | None = None,
) -> Calibration:
    """Assemble a :class:`Calibration` with before/after statistics and sphere coverage.

    Statistics use ``F`` = the reference magnitude(s), or, when the magnitude is unknown, the mean corrected
    magnitude: ``rms_* = RMS(|B_i| - F)``, ``max_abs_*`` = max ``||B_i| - F|``. ``fitted_magnitude`` (the radius
    implied by the method's scale gauge, e.g. det(W) = 1) is recorded as ``reference["fitted_radius"]``.
    The statistics take one pass over the samples in blocks (:func:`~trimag.quality.metrics.before_after_stats`);
    ``coverage`` (:func:`~trimag.quality.diagnostics.data_coverage` of ``B``: a property of the data, the same
    whatever the method) may be passed when the caller has it already, otherwise it is computed here.
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    offset = np.asarray(offset, dtype=np.float64)
    before, after, F = before_after_stats(B, matrix, offset, reference.values)
    if reference.values is not None:
        ref_info = reference.info()
    else:
        # no reference: the statistics use the mean corrected magnitude (docs/cli.md, "rms_*")
        ref_info = reference.info(fitted_value=F)
        if fitted_magnitude is not None:
            ref_info["fitted_radius"] = float(fitted_magnitude)
    stats: dict[str, Any] = {
        "n_samples": int(B.shape[0]),
        "n_used": int(B.shape[0]),
        "iterations": int(iterations),
        "converged": bool(converged),
        "rms_before": before["rms"],
        "rms_after": after["rms"],
        "max_abs_before": before["max_abs"],
        "max_abs_after": after["max_abs"],
        "p2p_before": before["peak_to_peak"],
        "p2p_after": after["peak_to_peak"],
        "mean_norm_before": before["mean_norm"],
        "mean_norm_after": after["mean_norm"],
        "std_norm_before": before["std_norm"],
        "std_norm_after": after["std_norm"],
    }
    stats.update(extra_stats or {})
    if coverage is None:
        coverage = data_coverage(B)
    cov = coverage
    diag = {"coverage": {k: v for k, v in cov.items() if k != "cell_counts"}}
    diag.update(diagnostics or {})
    return Calibration.from_matrix_offset(
        matrix,
        offset,
        units=units,
        model=model,
        method=method,
        params=params,
        reference=ref_info,
        stats=stats,
        uncertainty=uncertainty,
        diagnostics=diag,
    )
