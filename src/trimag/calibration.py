"""The :class:`Calibration` result: an affine correction with its provenance, statistics and diagnostics.

Every model in trimag reduces, once identified, to the affine correction

    B_corrected = matrix @ (B_raw - offset)                              (docs/conventions.md)

``matrix`` (3x3) removes soft iron, gains and non-orthogonality; ``offset`` (3,) is the hard iron / zero bias,
in the data's unit. The named physical parameters of the model that produced it live in ``params``.

A Calibration is immutable. Build it with ``from_*`` constructors, read it with ``as_*`` / ``to_*``.
Its JSON file is versioned (``format_version``, semver); a file from a newer major version is refused.

Regressor terms (``regressors``, docs/vehicle.md) make the offset depend on logged channels ``u_j`` (current,
temperature, ...): ``B_corrected = matrix @ (B_raw - offset - sum_j k_j (u_j - mean_j))``. A calibration with
them is written with format version :data:`REGRESSORS_FORMAT_VERSION` (2.0.0), so that a trimag that does not
know them refuses the file instead of silently ignoring the terms; every other calibration is written exactly as
before (1.0.0).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, TypedDict

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._core.rowwise import affine
from ._version import __version__
from .errors import CalibrationFormatError, TrimagInputError, UnitMismatchError
from .units import normalise_unit, unit_words

__all__ = ["FORMAT_VERSION", "UNCERTAINTY_FIELDS", "Calibration", "SensorRecord", "Uncertainty", "jsonable",
           "make_uncertainty"]

FORMAT_VERSION = "1.0.0"
_FORMAT_MAJOR = 1
#: The format version of a calibration with regressor terms (a 1.x reader would ignore them: refused there).
REGRESSORS_FORMAT_VERSION = "2.0.0"
#: The minor version of a file with a sensor record (``"sensor"``): 1.1.0, or 2.1.0 with regressor terms. A 1.0
#: reader ignores the record and applies the same correction (only the check of the sensor is lost), so the file
#: stays in its major version; a file without the record is written exactly as before.
SENSOR_MINOR_VERSION = 1


def _format_version(regressors: Any, sensor: Any) -> str:
    major = REGRESSORS_FORMAT_VERSION if regressors is not None else FORMAT_VERSION
    return major if sensor is None else f"{major.split('.')[0]}.{SENSOR_MINOR_VERSION}.0"


@dataclass(frozen=True)
class SensorRecord:
    """Which sensor a calibration belongs to: the ``"sensor"`` object of its file (docs/calibration-file.md).

    Written by ``trimag fit`` (and ``batch``, ``live``) from what it read; ``evaluate``, ``apply``, ``live --replay``
    and ``batch --prior`` read the same sensor by default and refuse a log whose compass is another device. Every
    field is a plain JSON value; a field the source does not know is None.

    Attributes
    ----------
    kind : str
        ``"log"`` (one magnetometer of an autopilot, ROS or phone log), ``"table"`` (three columns of a data file) or
        ``"stream"`` (a live source: standard input, a serial port, MAVLink).
    unit : str
        Unit of the readings the calibration takes (as :attr:`Calibration.units`).
    source : str or None
        The file's name (without its folder) the calibration was fitted to.
    source_sha256 : str or None
        SHA-256 of that file (None for a folder, e.g. a ROS 2 bag, or a stream).
    format : str or None
        ``"ArduPilot DataFlash"``, ``"MAVLink telemetry"``, ``"PX4 ULog"``, ... (a log), or the table's format
        (``"csv"``, ``"mat"``, ``"npz"``, ``"parquet"``, ...).
    compass : int or None
        The log's compass number as the user gives it (``--sensor N``, ``export --instance N``), from 1: the
        firmware slot + 1 (ArduPilot ``COMPASS_OFS2`` = 2; PX4 ``CAL_MAG1`` = 2).
    name : str or None
        The stream's name in the log (``"MAG[1]"``, ``"SCALED_IMU2"``, ``"sensor_mag[1]"``, ``"vehicle_magnetometer"``).
    message : str or None
        The log's message or topic of that stream (``"MAG"``, ``"SCALED_IMU2"``, ``"sensor_mag"``).
    device_id : int or None
        The firmware's device id (ArduPilot ``COMPASS_DEV_IDn``, PX4 ``CAL_MAGn_ID`` / ``sensor_mag.device_id``):
        what identifies the physical compass across logs; None when the log does not say.
    firmware : str or None
        ``"ardupilot"`` or ``"px4"`` for an autopilot log, else None.
    slot : int or None
        The firmware's calibration slot, 0-based (ArduPilot compass index; PX4 ``n`` of ``CAL_MAGn_*``, the first
        ``CAL_MAGn_ID`` holding the device id, as PX4 chooses it).
    offset_parameters : tuple of str or None
        The slot's offset parameters (``("COMPASS_OFS2_X", "COMPASS_OFS2_Y", "COMPASS_OFS2_Z")``,
        ``("CAL_MAG1_XOFF", ...)``): the names the printout, the file and ``export`` use for this sensor.
    stale_slots : tuple of int
        Later PX4 slots that hold the same device id (stale duplicates the firmware never reads).
    absent_parameters : tuple of str
        The slot's (and the shared) firmware parameters the log's firmware lacks (``COMPASS_ORIENT2`` in an
        ArduCopter 3.2 log): ``export`` does not write them.
    columns : tuple of str or None
        The x, y, z columns read (a table; for a log, the table trimag made of it: ``mag_x, mag_y, mag_z``).
    variable : str or None
        The variable of an NPZ or MAT file the columns came from.
    """

    kind: str
    unit: str = "unknown"
    source: str | None = None
    source_sha256: str | None = None
    format: str | None = None
    compass: int | None = None
    name: str | None = None
    message: str | None = None
    device_id: int | None = None
    firmware: str | None = None
    slot: int | None = None
    offset_parameters: tuple[str, ...] | None = None
    stale_slots: tuple[int, ...] = ()
    absent_parameters: tuple[str, ...] = ()
    columns: tuple[str, ...] | None = None
    variable: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON types (every field, None where unknown)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SensorRecord:
        """Rebuild from :meth:`as_dict` (unknown keys, from a newer minor version, are ignored)."""
        if not isinstance(data, Mapping) or not isinstance(data.get("kind"), str):
            raise CalibrationFormatError('calibration file\'s "sensor" entry is not an object with a "kind"')
        known = {f.name for f in fields(cls)}
        values: dict[str, Any] = {}
        for key, value in data.items():
            if key not in known:
                continue
            if key in ("offset_parameters", "columns") and value is not None:
                value = tuple(str(v) for v in value)
            elif key == "stale_slots":
                value = tuple(int(v) for v in value or ())
            elif key == "absent_parameters":
                value = tuple(str(v) for v in value or ())
            elif key in ("compass", "device_id", "slot") and value is not None:
                value = int(value)
            values[key] = value
        return cls(**values)

    def describe(self) -> str:
        """One line for the user: ``compass 2 of ardusub_small.tlog (SCALED_IMU2, device id 1245450, ArduPilot
        COMPASS_OFS2_X..Z), mG``; a table's: ``columns mag_x, mag_y, mag_z of lab.csv, uT``."""
        where = f" of {self.source}" if self.source else ""
        if self.kind == "log":
            what = [x for x in (self.name, f"device id {self.device_id}" if self.device_id else None) if x]
            if self.offset_parameters:
                what.append(f"{self.offset_parameters[0][:-1]}X..Z" if self.firmware == "ardupilot" else
                            f"{self.offset_parameters[0].rsplit('_', 1)[0]}_*")
            number = f"compass {self.compass}" if self.compass is not None else "the magnetometer"
            return f"{number}{where} ({', '.join(what)}), {unit_words(self.unit)}"
        if self.kind == "table":
            cols = f"columns {', '.join(self.columns)}" if self.columns else "the columns"
            var = f" (variable {self.variable})" if self.variable else ""
            return f"{cols}{var}{where}, {unit_words(self.unit)}"
        return f"{self.format or 'a live stream'}{where}, {unit_words(self.unit)}"


def file_major_version(data: Any, kind: str, current: str) -> int:
    """The major format version of a trimag ``kind`` file's content (``"calibration"``, ``"compensation"``).

    Raises
    ------
    CalibrationFormatError
        Not such a file, an unreadable version, or a major version newer than ``current``'s.
    """
    if not isinstance(data, Mapping) or data.get("format") != f"trimag-{kind}":
        raise CalibrationFormatError(f'not a trimag {kind} file (no "format": "trimag-{kind}" entry)')
    version = str(data.get("format_version", ""))
    try:
        major = int(version.split(".")[0])
    except ValueError:
        raise CalibrationFormatError(f"{kind} file has an unreadable format_version {version!r}") from None
    if major > int(current.split(".")[0]):
        raise CalibrationFormatError(
            f"{kind} file has format_version {version}, newer than this trimag understands ({current}); "
            "upgrade trimag (pip install -U trimag)"
        )
    return major


#: The fields every ``Calibration.uncertainty`` has, whatever made it (an estimator, a regressor refit, a quick
#: recalibration, a joint fit: :func:`make_uncertainty`); ``None`` where the method does not know the value.
#: ``trimag.quality.honesty`` then adds ``inflation``.
UNCERTAINTY_FIELDS = (
    "basis", "gauge", "param_std", "covariance", "covariance_order", "noise_std", "predicted_field_rms",
    "predicted_magnitude_rms",
)


class Uncertainty(TypedDict):
    """``Calibration.uncertainty`` as every estimator fills it (JSON: a plain object with these keys)."""

    basis: str
    gauge: str | None
    param_std: dict[str, float]
    covariance: list[list[float]] | None
    covariance_order: list[str]
    noise_std: float | None
    predicted_field_rms: float | None
    predicted_magnitude_rms: float | None


def make_uncertainty(
    names: Sequence[str], *, basis: str, covariance: NDArray[np.float64] | None = None,
    param_std: Sequence[float] | None = None, gauge: str | None = None, noise_std: float | None = None,
    predicted_field_rms: float | None = None, predicted_magnitude_rms: float | None = None, **extra: Any,
) -> dict[str, Any]:
    """The uncertainty entry of a fit, with the same fields for every estimator (:class:`Uncertainty`).

    Parameters
    ----------
    names : sequence of str
        Parameter names, in the order of ``covariance`` (or ``param_std``).
    basis : str
        How the covariance was obtained (e.g. ``"s^2 (J^T J)^-1 at the solution"``).
    covariance : ndarray, shape (p, p), optional
        Parameter covariance (parameter units squared); its diagonal gives ``param_std``.
    param_std : sequence of float, optional
        Standard deviations when no full covariance is known.
    gauge, noise_std, predicted_field_rms, predicted_magnitude_rms
        As in :class:`Uncertainty` (noise per axis in the data unit; predicted RMS errors of the corrected field
        and magnitude in the data unit).
    **extra
        Method-specific additions (e.g. ``param_std_deg``).
    """
    if covariance is not None:
        cov = np.asarray(covariance, dtype=np.float64)
        std = np.sqrt(np.clip(np.diag(cov), 0, None)).tolist()
    elif param_std is not None:
        cov, std = None, [float(v) for v in param_std]
    else:
        raise TypeError("make_uncertainty needs `covariance` or `param_std`")
    out: dict[str, Any] = {
        "basis": basis,
        "gauge": gauge,
        "param_std": dict(zip(names, std, strict=True)),
        "covariance": None if cov is None else cov.tolist(),
        "covariance_order": list(names),
        "noise_std": None if noise_std is None else float(noise_std),
        "predicted_field_rms": predicted_field_rms,
        "predicted_magnitude_rms": predicted_magnitude_rms,
    }
    out.update(extra)
    return out


def jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays (nested in dicts and lists) to plain JSON types; NaN/inf become None (as in
    calibration files)."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        value = float(obj)
        return value if math.isfinite(value) else None
    return obj


def _frozen_array(a: ArrayLike, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    arr = np.array(a, dtype=np.float64, copy=True)
    if arr.shape != shape:
        raise TrimagInputError(f"`{name}` must have shape {shape}; got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).sum())
        raise TrimagInputError(f"`{name}` must be finite; got {bad} non-finite value(s) of {arr.size}")
    arr.setflags(write=False)
    return arr


#: the largest offset component a calibration file may hold, nT: 10 mT (100 G), beyond the range of any magnetometer
#: of the Earth's field (a MEMS compass saturates near 1.6 mT, a fluxgate near 0.1 mT)
MAX_OFFSET_NT = 1e7
#: the same for data without a physical unit (``counts``, ``unknown``): beyond a 32-bit reading
MAX_OFFSET_COUNTS = 1e10
#: the gains (singular values) a calibration's matrix may have: from a counts-to-unit-sphere scale to its inverse
GAIN_RANGE = (1e-9, 1e9)
#: the largest condition number of a calibration's matrix: no soft iron compresses one axis a million times
MAX_CONDITION = 1e6


def check_physical_range(matrix: NDArray[np.float64], offset: NDArray[np.float64], units: str) -> None:
    """Refuse a calibration file's numbers that no magnetometer's calibration has (issue 41, item 8: an offset of
    1e308 or a matrix of 1e300 I was applied and exported with overflow warnings).

    ``matrix`` (3, 3) and ``offset`` (3,) in ``units`` (finite already): the offset within :data:`MAX_OFFSET_NT`
    (:data:`MAX_OFFSET_COUNTS` without a physical unit), the matrix's gains within :data:`GAIN_RANGE` and its
    condition number at most :data:`MAX_CONDITION`.

    Raises
    ------
    CalibrationFormatError
        Naming the entry, its value and the range.
    """
    from .units import UNITS

    per_nT = UNITS.get(units)
    limit = MAX_OFFSET_COUNTS if per_nT is None else MAX_OFFSET_NT / per_nT
    worst = float(np.abs(offset).max())
    edited = "it was edited or corrupted, or not written by trimag"
    if worst > limit:
        where = "a 32-bit reading" if per_nT is None else "10 mT, beyond any Earth-field magnetometer's range"
        raise CalibrationFormatError(f"calibration file's offset has a component of {worst:.3g} {units}, beyond "
                                     f"{limit:.3g} {units} ({where}): {edited}")
    gains = np.linalg.svd(matrix, compute_uv=False)
    lo, hi = GAIN_RANGE
    if gains[0] > hi or gains[-1] < lo:
        gain = gains[0] if gains[0] > hi else gains[-1]
        raise CalibrationFormatError(f"calibration file's matrix has a gain of {gain:.3g}, outside {lo:g} to {hi:g}: "
                                     f"{edited}")
    if gains[0] > MAX_CONDITION * gains[-1]:
        raise CalibrationFormatError(f"calibration file's matrix stretches one direction {gains[0] / gains[-1]:.3g} "
                                     f"times more than another (at most {MAX_CONDITION:g} in a calibration): {edited}")


def check_regressor_terms(terms: Mapping[str, Any]) -> dict[str, Any]:
    """The ``regressors`` entry of a calibration, checked and as plain lists.

    ``terms``: ``names`` (m str), ``means`` (m,) in each regressor's unit, ``coefficients`` (m, 3) in data unit
    per regressor unit (row ``j`` is ``k_j``), and optionally ``units`` (m str, free text) and ``note``.
    """
    try:
        names = [str(n) for n in terms["names"]]
        means = np.asarray(terms["means"], dtype=np.float64)
        coef = np.asarray(terms["coefficients"], dtype=np.float64)
    except KeyError as exc:
        raise TrimagInputError(f"`regressors` lacks the entry {exc.args[0]!r}") from None
    m = len(names)
    if m == 0 or len(set(names)) != m:
        raise TrimagInputError(f"`regressors` must name at least one regressor, each once; got {names}")
    if means.shape != (m,) or coef.shape != (m, 3):
        raise TrimagInputError(
            f"`regressors` of {m} names needs means of shape ({m},) and coefficients ({m}, 3); got {means.shape} "
            f"and {coef.shape}"
        )
    if not (np.isfinite(means).all() and np.isfinite(coef).all()):
        raise TrimagInputError("`regressors` means and coefficients must be finite")
    out: dict[str, Any] = {**dict(terms), "names": names, "means": means.tolist(), "coefficients": coef.tolist()}
    return out


def _regressor_values(terms: Mapping[str, Any], values: Any, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """The regressor values ``values`` (mapping name -> (N,), or (N, m) / (m,) array) as an (N, m) or (m,)
    array in the order of ``terms["names"]``, for samples of ``shape`` ((N, 3) or (3,))."""
    names = list(terms["names"])
    if isinstance(values, Mapping):
        missing = [n for n in names if n not in values]
        if missing:
            raise TrimagInputError(
                f"`regressors` lacks {', '.join(map(repr, missing))}; this calibration needs {', '.join(names)}"
            )
        arr = np.stack([np.asarray(values[n], dtype=np.float64) for n in names], axis=-1)
    else:
        arr = np.asarray(values, dtype=np.float64)
    expected = (*shape[:-1], len(names))
    if arr.shape != expected:
        raise TrimagInputError(
            f"`regressors` must have shape {expected} (one value of {', '.join(names)} per sample); got {arr.shape}"
        )
    return arr


@dataclass(frozen=True, eq=False)
class Calibration:
    """An identified magnetometer calibration: ``B_corrected = matrix @ (B_raw - offset)``.

    Do not call the constructor directly; use :meth:`from_matrix_offset`, :meth:`from_params`,
    :meth:`from_json` or :meth:`from_file` (estimators build it for you).

    Attributes
    ----------
    matrix : ndarray, shape (3, 3)
        Correction matrix (dimensionless when input and output share a unit).
    offset : ndarray, shape (3,)
        Hard-iron / zero-bias offset, in ``units``.
    units : str
        Unit of the raw data this calibration accepts; corrected output is in the same unit.
    model, method : str
        Error model and identification method that produced it.
    params : dict[str, float]
        Named physical parameters of ``model`` (angles in radians).
    reference : dict or None
        Field reference used: ``{"value": float or None, "source": str, "unit": str}``.
    stats : dict
        Fit statistics: ``n_samples``, ``n_used``, ``iterations``, ``converged``, ``rms_before``,
        ``rms_after``, ``max_abs_before``, ``max_abs_after`` and method-specific entries.
    uncertainty : dict or None
        Standard deviations (``param_std``), covariance and predicted error when the method gives them.
    diagnostics : dict
        Condition number, sphere coverage, warnings, iteration history.
    regressors : dict or None
        Regressor terms of the offset (docs/vehicle.md): ``names`` (m), ``means`` (m,), ``coefficients`` (m, 3)
        in ``units`` per regressor unit; :meth:`apply` subtracts ``sum_j k_j (u_j - mean_j)`` from the raw
        samples first. None: the offset is constant.
    sensor : SensorRecord or None
        The sensor the calibration belongs to (:class:`SensorRecord`); None when not known (a calibration built
        from arrays, or a file written before the record existed).
    """

    matrix: NDArray[np.float64]
    offset: NDArray[np.float64]
    units: str = "unknown"
    model: str = "affine"
    method: str = "given"
    params: Mapping[str, float] = field(default_factory=dict)
    reference: Mapping[str, Any] | None = None
    stats: Mapping[str, Any] = field(default_factory=dict)
    uncertainty: Mapping[str, Any] | None = None
    diagnostics: Mapping[str, Any] = field(default_factory=dict)
    created: str = ""
    trimag_version: str = __version__
    format_version: str = FORMAT_VERSION
    regressors: Mapping[str, Any] | None = None
    sensor: SensorRecord | None = None

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_matrix_offset(
        cls,
        matrix: ArrayLike,
        offset: ArrayLike = (0.0, 0.0, 0.0),
        *,
        units: str | None = "unknown",
        model: str = "affine",
        method: str = "given",
        params: Mapping[str, float] | None = None,
        reference: Mapping[str, Any] | None = None,
        stats: Mapping[str, Any] | None = None,
        uncertainty: Mapping[str, Any] | None = None,
        diagnostics: Mapping[str, Any] | None = None,
        created: str | None = None,
        regressors: Mapping[str, Any] | None = None,
        sensor: SensorRecord | None = None,
    ) -> Calibration:
        """Build a calibration from its correction matrix (3, 3) and offset (3,) in ``units``; ``regressors``:
        the offset's regressor terms (see the class docstring), None for a constant offset; ``sensor``: the sensor
        it belongs to."""
        m = _frozen_array(matrix, (3, 3), "matrix")
        if abs(np.linalg.det(m)) < 1e-300 or np.linalg.cond(m) > 1e12:
            raise TrimagInputError("`matrix` is singular: a calibration must be invertible")
        return cls(
            matrix=m,
            offset=_frozen_array(offset, (3,), "offset"),
            units=normalise_unit(units),
            model=model,
            method=method,
            params=dict(params or {}),
            reference=None if reference is None else dict(reference),
            stats=dict(stats or {}),
            uncertainty=None if uncertainty is None else dict(uncertainty),
            diagnostics=dict(diagnostics or {}),
            created=created or _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            regressors=None if regressors is None else check_regressor_terms(regressors),
            format_version=_format_version(regressors, sensor),
            sensor=sensor,
        )

    @classmethod
    def from_params(
        cls, model: str, params: Mapping[str, float], *, units: str | None = "unknown", **kwargs: Any
    ) -> Calibration:
        """Build a calibration from a model name and its named physical parameters.

        Examples
        --------
        >>> cal = Calibration.from_params("ellipsoid", {"hard_iron_x": 1.0, "hard_iron_y": 0.0,
        ...     "hard_iron_z": 0.0, "w11": 1.0, "w12": 0.0, "w13": 0.0, "w21": 0.0, "w22": 1.0,
        ...     "w23": 0.0, "w31": 0.0, "w32": 0.0, "w33": 1.0})
        >>> cal.apply([1.0, 0.0, 0.0]).shape
        (3,)
        """
        from .models import get_model

        instance = get_model(model).from_dict(params)
        matrix, offset = instance.correction()
        return cls.from_matrix_offset(
            matrix, offset, units=units, model=model, params=instance.as_dict(), **kwargs
        )

    # ------------------------------------------------------------------ algebra
    def check_units(self, units: str) -> None:
        """Raise :class:`UnitMismatchError` when data in ``units`` are not in this calibration's unit (an unknown
        unit on either side passes)."""
        given = normalise_unit(units)
        if given != self.units and "unknown" not in (given, self.units):
            raise UnitMismatchError(
                f"this calibration is for data in {self.units!r}; got data in {given!r}. "
                "Convert the data, or fit a calibration in that unit"
            )

    def apply(
        self, B: ArrayLike, *, inverse: bool = False, units: str | None = None, regressors: Any = None
    ) -> NDArray[np.float64]:
        """Correct raw samples (or, with ``inverse=True``, distort corrected ones back to raw).

        Parameters
        ----------
        B : array_like, shape (3,) or (N, 3)
            Samples in :attr:`units`. Non-finite rows stay non-finite (one row never affects another).
        inverse : bool
            Apply the inverse map ``B_raw = inv(matrix) @ B + offset`` (plus the regressor terms).
        units : str, optional
            Unit of ``B``; if given and different from :attr:`units`, :class:`UnitMismatchError` is raised.
        regressors : mapping or array_like, optional
            Values of the calibration's regressors (:attr:`regressors`) at each sample: a mapping name -> shape
            (N,) (or a number for one sample), or an array of shape (N, m) (or (m,)) in the order of
            ``regressors["names"]``, in the units they were fitted in. Required when the calibration has
            regressor terms (``sum_j k_j (u_j - mean_j)`` is subtracted from ``B`` before the affine correction),
            refused when it has none.

        Returns
        -------
        ndarray, shape like ``B``
        """
        if units is not None:
            self.check_units(units)
        arr = np.asarray(B, dtype=np.float64)
        if arr.shape[-1:] != (3,) or arr.ndim > 2:
            raise TrimagInputError(f"`B` must have shape (3,) or (N, 3); got {arr.shape}")
        if self.regressors is not None or regressors is not None:
            return self._apply_regressors(arr, inverse, regressors)
        if inverse:
            return np.linalg.solve(self.matrix, arr.T).T + self.offset
        if arr.ndim == 2 and len(arr) > 1000:
            return affine(arr, self.matrix, self.offset)  # blocked, component-major: ~3x faster on long arrays
        return (arr - self.offset) @ self.matrix.T

    def regressor_shift(self, regressors: Any, shape: tuple[int, ...] = (1, 3)) -> NDArray[np.float64]:
        """The offset change ``sum_j k_j (u_j - mean_j)`` at each sample, shape ``shape`` ((N, 3) or (3,)),
        for regressor values given as in :meth:`apply`."""
        terms = self.regressors
        if terms is None:
            raise TrimagInputError("this calibration has no regressor terms; drop `regressors`")
        if regressors is None:
            raise TrimagInputError(
                f"this calibration has regressor terms ({', '.join(terms['names'])}); give their values at every "
                "sample: apply(B, regressors={name: values}) (on the command line the data need those columns)"
            )
        u = _regressor_values(terms, regressors, shape)
        shift = (u - np.asarray(terms["means"])) @ np.asarray(terms["coefficients"])
        return np.asarray(shift, dtype=np.float64)

    def _apply_regressors(self, arr: NDArray[np.float64], inverse: bool, regressors: Any) -> NDArray[np.float64]:
        shift = self.regressor_shift(regressors, arr.shape)
        if inverse:
            return np.linalg.solve(self.matrix, arr.T).T + self.offset + shift
        return np.asarray((arr - shift - self.offset) @ self.matrix.T, dtype=np.float64)

    def _refuse_regressors(self, what: str) -> None:
        if self.regressors is not None:
            raise TrimagInputError(
                f"{what} of a calibration with regressor terms ({', '.join(self.regressors['names'])}) is not "
                "defined (the offset depends on the regressors)"
            )

    def inv(self) -> Calibration:
        """The inverse map as a Calibration: ``c.inv().apply(c.apply(B)) == B`` (to rounding)."""
        self._refuse_regressors("the inverse")
        inv_matrix = np.linalg.inv(self.matrix)
        return Calibration.from_matrix_offset(
            inv_matrix, -self.matrix @ self.offset, units=self.units, model="affine",
            method=f"inverse of {self.method}",
        )

    def __mul__(self, other: object) -> Calibration:
        """Composition: ``(a * b).apply(B) == a.apply(b.apply(B))`` (``b`` first, as in scipy's Rotation)."""
        if not isinstance(other, Calibration):
            return NotImplemented
        self._refuse_regressors("a composition")
        other._refuse_regressors("a composition")
        matrix = self.matrix @ other.matrix
        offset = other.offset + np.linalg.solve(other.matrix, self.offset)
        return Calibration.from_matrix_offset(
            matrix, offset, units=other.units, model="affine", method=f"{self.method} * {other.method}",
            sensor=other.sensor,
        )

    def approx_equal(self, other: Calibration, atol: float = 1e-9) -> bool:
        """True when matrix, offset (and regressor coefficients) agree within ``atol`` and the units match."""
        mine, theirs = self.regressors, other.regressors
        if (mine is None) != (theirs is None):
            return False
        if mine is not None and theirs is not None and not (
            list(mine["names"]) == list(theirs["names"])
            and bool(np.allclose(mine["coefficients"], theirs["coefficients"], rtol=0, atol=atol))
            and bool(np.allclose(mine["means"], theirs["means"], rtol=0, atol=atol))
        ):
            return False
        return (
            self.units == other.units
            and bool(np.allclose(self.matrix, other.matrix, rtol=0, atol=atol))
            and bool(np.allclose(self.offset, other.offset, rtol=0, atol=atol))
        )

    def with_diagnostics(self, **entries: Any) -> Calibration:
        """A copy with ``entries`` merged into :attr:`diagnostics`."""
        return replace(self, diagnostics={**self.diagnostics, **entries})

    def with_stats(self, **entries: Any) -> Calibration:
        """A copy with ``entries`` merged into :attr:`stats`."""
        return replace(self, stats={**self.stats, **entries})

    def with_sensor(self, sensor: SensorRecord | None) -> Calibration:
        """A copy that belongs to ``sensor`` (:class:`SensorRecord`; None: to no known sensor)."""
        return replace(self, sensor=sensor, format_version=_format_version(self.regressors, sensor))

    # ------------------------------------------------------------------ export
    def as_dict(self) -> dict[str, Any]:
        """All content as plain JSON types (the file format; see ``docs/calibration-file.md``). A calibration
        without regressor terms has no ``regressors`` key (format 1.0.0, as before they existed), one without a
        sensor record no ``sensor`` key."""
        out = jsonable(
            {
                "format": "trimag-calibration",
                "format_version": self.format_version,
                "trimag_version": self.trimag_version,
                "created": self.created,
                "model": self.model,
                "method": self.method,
                "units": self.units,
                "input_unit": self.units,
                "output_unit": self.units,
                "convention": "B_corrected = matrix @ (B_raw - offset)",
                "matrix": self.matrix,
                "offset": self.offset,
                "params": dict(self.params),
                "reference": self.reference,
                "stats": dict(self.stats),
                "uncertainty": self.uncertainty,
                "diagnostics": dict(self.diagnostics),
            }
        )
        if self.regressors is not None:
            out["format_version"] = REGRESSORS_FORMAT_VERSION
            out["convention"] = "B_corrected = matrix @ (B_raw - offset - sum_j k_j (u_j - mean_j))"
            out["regressors"] = jsonable(dict(self.regressors))
        if self.sensor is not None:
            out["sensor"] = jsonable(self.sensor.as_dict())
        out["format_version"] = _format_version(self.regressors, self.sensor)
        return dict(out)

    def to_json(self, indent: int | None = 2) -> str:
        """Serialise to JSON text; floats are written with full precision, so apply() round-trips exactly."""
        return json.dumps(self.as_dict(), indent=indent, allow_nan=False)

    def to_file(self, path: str | os.PathLike[str]) -> Path:
        """Write the JSON file atomically (temporary file, then rename)."""
        from .io.atomic import atomic_write_text

        return atomic_write_text(path, self.to_json() + "\n")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Calibration:
        """Rebuild from :meth:`as_dict` output; checks the format and its version."""
        major = file_major_version(data, "calibration", REGRESSORS_FORMAT_VERSION)
        if major < _FORMAT_MAJOR:
            from .io.legacy import migrate

            data = migrate(data)
        from .models import MODELS

        model = str(data.get("model", "affine"))
        if model not in MODELS and model != "affine":
            raise CalibrationFormatError(
                f"calibration file names an unknown model {model!r} (known: affine, {', '.join(MODELS)}); "
                "it was not written by this trimag or was edited"
            )
        try:
            terms = data.get("regressors")
            if major >= 2 and terms is None:
                raise CalibrationFormatError(
                    f"calibration file has format_version {data.get('format_version')} but no regressor terms"
                )
            matrix = _frozen_array(data["matrix"], (3, 3), "matrix")
            with np.errstate(all="ignore"):
                singular = not abs(np.linalg.det(matrix)) >= 1e-300 or not np.linalg.cond(matrix) <= 1e12
            if singular:
                raise CalibrationFormatError(
                    "calibration file's matrix is singular: it maps every field onto a plane or a line, which no "
                    "calibration does (it was edited, or not written by trimag)"
                )
            offset = _frozen_array(data["offset"], (3,), "offset")
            units = normalise_unit(data.get("units", "unknown"))
            with np.errstate(all="ignore"):
                check_physical_range(matrix, offset, units)
            return cls(
                matrix=matrix,
                offset=offset,
                units=units,
                model=str(data.get("model", "affine")),
                method=str(data.get("method", "given")),
                params=dict(data.get("params") or {}),
                reference=data.get("reference"),
                stats=dict(data.get("stats") or {}),
                uncertainty=data.get("uncertainty"),
                diagnostics=dict(data.get("diagnostics") or {}),
                created=str(data.get("created", "")),
                trimag_version=str(data.get("trimag_version", "")),
                format_version=_format_version(terms, data.get("sensor")),
                regressors=None if terms is None else check_regressor_terms(terms),
                sensor=None if data.get("sensor") is None else SensorRecord.from_dict(data["sensor"]),
            )
        except KeyError as exc:
            raise CalibrationFormatError(f"calibration file lacks the entry {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise CalibrationFormatError(f"calibration file has a non-numeric or misshapen entry: {exc}") from None

    @classmethod
    def from_json(cls, text: str) -> Calibration:
        """Parse JSON text written by :meth:`to_json`."""
        from .validation import check_nesting

        check_nesting(text, "calibration file", CalibrationFormatError)
        from .validation import json_error

        try:
            data = json.loads(text)
        except ValueError as exc:  # JSONDecodeError, or an integer of more than 4300 digits
            raise CalibrationFormatError(f"calibration file is not valid JSON: {json_error(exc)}") from None
        return cls.from_dict(data)

    @classmethod
    def from_file(cls, path: str | os.PathLike[str]) -> Calibration:
        """Read a calibration JSON file."""
        p = Path(path)
        if p.is_dir():
            raise TrimagInputError(f"{p} is a folder; give a calibration file (.json)")
        if not p.is_file():
            raise TrimagInputError(f"calibration file {str(p)!r} does not exist")
        text = p.read_text(encoding="utf-8")
        try:
            return cls.from_json(text)
        except CalibrationFormatError as exc:  # named: a command may read two calibrations, or a calibration and a log
            raise CalibrationFormatError(f"{p}: {exc}") from None

    # ------------------------------------------------------------------ display
    def __repr__(self) -> str:
        terms = "" if self.regressors is None else f", regressors={dict(self.regressors)!r}"
        return (
            f"Calibration.from_matrix_offset(matrix={self.matrix.tolist()!r}, offset={self.offset.tolist()!r}, "
            f"units={self.units!r}, model={self.model!r}, method={self.method!r}{terms})"
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        return self.as_dict() == other.as_dict()

    __hash__ = None  # type: ignore[assignment]
