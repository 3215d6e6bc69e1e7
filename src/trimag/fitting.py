"""The one-call API: :func:`fit` samples to a :class:`~trimag.calibration.Calibration`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .calibration import Calibration
from .estimators import make_estimator

__all__ = ["fit"]


def fit(
    samples: ArrayLike,
    model: str = "ellipsoid",
    method: str | None = None,
    reference: Any = None,
    *,
    units: str | None = "unknown",
    attitude: Any = None,
    regressors: Mapping[str, ArrayLike] | None = None,
    **options: Any,
) -> Calibration:
    """Identify a magnetometer calibration from raw samples.

    Parameters
    ----------
    samples : array_like, shape (N, 3)
        Raw sensor output, one row per sample, in ``units``.
    model : str
        Error model: ``"ellipsoid"`` (hard + soft iron, default), ``"ortho-gain"``, ``"ortho-gain-bias"``,
        ``"scalar9"``, ``"interference12"``, ``"zhang-cheng"``.
    method : str, optional
        Identification method; the model's default when omitted (``trimag.estimators.DEFAULT_METHOD``).
    reference : float, array_like (N,), "mean" or None
        Field magnitude in ``units`` (one value, or one per sample); ``None``/``"mean"`` when unknown.
        For ``interference12``: the background field vector (3,) in the navigation frame (NED).
    units : str
        Unit of ``samples``: ``nT``, ``uT``, ``G``, ``mG``, ``counts`` (recorded in the result).
    attitude : scipy.spatial.transform.Rotation or trimag.fields.gyro.AngularRate, optional
        Per-sample attitudes, for vector methods (``interference12``); the gyroscope for ``method="gyro"``
        (docs/method-gyro.md).
    regressors : mapping str -> array_like, shape (N,), optional
        Channels the offset depends on linearly (motor current, throttle, temperature, ...), in their own units:
        ``b(t) = b0 + sum_j k_j (u_j(t) - mean_j)``, fitted jointly with the model (``ellipsoid`` and
        ``interference12``; :func:`trimag.vehicle.regressors.fit_regressors`, docs/vehicle.md). Apply the result with
        ``cal.apply(B, regressors=...)``.
    **options
        Method options (see each method's class, e.g. ``form="symmetric"`` for ``ml``).

    Returns
    -------
    Calibration
        ``corrected = cal.apply(samples)``; ``cal.matrix @ (raw - cal.offset)``.

    Raises
    ------
    TrimagInputError
        Malformed input (shape, NaN, unknown model, method or unit).
    IdentifiabilityError
        The samples cannot identify the model (too few, coplanar, degenerate attitudes).

    Examples
    --------
    >>> import numpy as np, trimag
    >>> rng = np.random.default_rng(0)
    >>> u = rng.normal(size=(500, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)
    >>> raw = u * [1.1, 0.9, 1.0] * 48000 + [300, -200, 100]
    >>> cal = trimag.fit(raw, reference=48000.0, units="nT")
    >>> cal.apply(raw).shape
    (500, 3)
    """
    estimator = make_estimator(model, method, options)
    estimator.fit(samples, reference, units=units, attitude=attitude)
    if regressors is None:
        return estimator.calibration_
    from .vehicle.regressors import fit_regressors

    return fit_regressors(estimator.calibration_, np.asarray(samples, dtype=np.float64), regressors, reference,
                          attitude=attitude)
