"""The :class:`ScalarCompensation` result: a Tolles–Lawson compensation of a scalar magnetometer.

A :class:`~trimag.calibration.Calibration` is an affine map of a vector reading; a Tolles–Lawson (TL)
compensation is not: it subtracts from a *scalar* magnetometer the aircraft's field predicted from a vector
magnetometer's direction cosines and their time derivatives (docs/method-tolles-lawson.md):

    S_compensated = S - A(vector) @ coefficients

so it has its own immutable result type and its own versioned JSON file (``"format":
"trimag-compensation"``), which records the terms, coefficients, filter, scale, derivative scheme, sample rate
and the sensors (columns) it was fitted on. ``trimag apply`` and ``trimag evaluate`` recognise both files.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.chunks import row_blocks
from .._version import __version__
from ..calibration import file_major_version, jsonable
from ..errors import CalibrationFormatError, TrimagInputError
from ..io.atomic import atomic_write_text
from ..models.tolles_lawson import TollesLawsonTerms
from .filtering import BandPass, finite_runs

__all__ = ["COMPENSATION_FORMAT_VERSION", "ScalarCompensation"]

COMPENSATION_FORMAT_VERSION = "1.0.0"


@dataclass(frozen=True, eq=False)
class ScalarCompensation:
    """A fitted Tolles–Lawson compensation (build it with :func:`trimag.fit_tolles_lawson`).

    Attributes
    ----------
    terms : TollesLawsonTerms
        Term groups, ``Bt_scale`` (nT), derivative scheme and the source of ``Bt``.
    coefficients : ndarray, shape (p,)
        TL coefficients, in MagNav.jl's order and scale (nT per unit of each design column).
    bandpass : BandPass
        The filter the fit used (its ``rate_hz`` is the sample rate of the data).
    ridge : float
        Ridge parameter lambda of the fit (0 = ordinary least squares).
    sensors : dict
        ``vector_columns``, ``scalar_column``, ``time_column``, ``source`` (file) of the fit data.
    uncertainty : dict
        ``formal_std`` (from the residual variance), ``bootstrap_std`` (block bootstrap over time blocks),
        ``std`` (the larger of the two, the one to use) and how they were computed.
    stats, diagnostics : dict
        Per-segment band-passed std before/after, improvement ratio, collinear terms, manoeuvre content.
    """

    terms: TollesLawsonTerms
    coefficients: NDArray[np.float64]
    bandpass: BandPass
    ridge: float = 0.0
    units: str = "nT"
    sensors: Mapping[str, Any] = field(default_factory=dict)
    uncertainty: Mapping[str, Any] = field(default_factory=dict)
    stats: Mapping[str, Any] = field(default_factory=dict)
    diagnostics: Mapping[str, Any] = field(default_factory=dict)
    created: str = ""
    trimag_version: str = __version__
    model: str = "tolles-lawson"
    method: str = "ridge-least-squares"

    def __post_init__(self) -> None:
        coef = np.array(self.coefficients, dtype=np.float64, copy=True)
        if coef.shape != (len(self.terms.names),):
            raise TrimagInputError(
                f"{len(self.terms.names)} coefficients expected for terms {', '.join(self.terms.terms)}; "
                f"got shape {coef.shape}"
            )
        if not np.isfinite(coef).all():
            raise TrimagInputError("Tolles–Lawson coefficients must be finite")
        coef.setflags(write=False)
        object.__setattr__(self, "coefficients", coef)
        if not self.created:
            object.__setattr__(self, "created", _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))

    # ------------------------------------------------------------------ algebra
    @property
    def names(self) -> list[str]:
        """Names of the coefficients (design columns)."""
        return self.terms.names

    def interference(
        self,
        vector_nT: ArrayLike,
        scalar_nT: ArrayLike | None = None,
        segments: Sequence[tuple[int, int]] | None = None,
    ) -> NDArray[np.float64]:
        """The aircraft field ``A @ c`` seen by the scalar magnetometer (nT), NaN outside ``segments``.

        Parameters
        ----------
        vector_nT : array_like, shape (N, 3)
            Vector magnetometer, nT, in time order.
        scalar_nT : array_like, shape (N,), optional
            Scalar magnetometer (needed when ``Bt`` comes from it).
        segments : sequence of (start, stop), optional
            Contiguous row ranges; default: the runs of finite rows (derivatives never cross a gap).
        """
        B = np.asarray(vector_nT, dtype=np.float64)
        if B.ndim != 2 or B.shape[1] != 3:
            raise TrimagInputError(f"the vector magnetometer must have shape (N, 3); got {B.shape}")
        S = None if scalar_nT is None else np.asarray(scalar_nT, dtype=np.float64)
        if self.terms.Bt_source == "scalar" and S is None:
            raise TrimagInputError("this compensation takes Bt from the scalar magnetometer: give its values")
        if segments is None:
            ok: NDArray[np.bool_] = np.asarray(np.isfinite(B).all(axis=1))
            if S is not None and self.terms.Bt_source == "scalar":
                ok &= np.isfinite(S)
            segments = finite_runs(ok)
        out = np.full(len(B), np.nan)
        for start, stop in segments:
            if stop - start < 2:
                continue
            # in blocks of rows, each with one neighbour on either side so that the finite differences at a
            # block's edges are those of the whole segment: memory does not grow with the segment's length
            for rows in row_blocks(stop - start, len(self.coefficients) + 3):  # the design's columns, the field
                c0, c1 = start + rows.start, start + rows.stop
                a, b = max(c0 - 1, start), min(c1 + 1, stop)
                A = self.terms.design(B[a:b], None if S is None else S[a:b])
                out[c0:c1] = A[c0 - a : c0 - a + (c1 - c0)] @ self.coefficients
        return out

    def apply(
        self,
        vector_nT: ArrayLike,
        scalar_nT: ArrayLike,
        segments: Sequence[tuple[int, int]] | None = None,
    ) -> NDArray[np.float64]:
        """Compensated scalar ``S - A @ c`` (nT), shape (N,); NaN where a row cannot be compensated."""
        S = np.asarray(scalar_nT, dtype=np.float64)
        return S - self.interference(vector_nT, S, segments)

    # ------------------------------------------------------------------ file
    def as_dict(self) -> dict[str, Any]:
        """All content as plain JSON types (the compensation file)."""
        return jsonable(
            {
                "format": "trimag-compensation",
                "format_version": COMPENSATION_FORMAT_VERSION,
                "trimag_version": self.trimag_version,
                "created": self.created,
                "model": self.model,
                "method": self.method,
                "units": self.units,
                "convention": "S_compensated = S - A(vector) @ coefficients (MagNav.jl create_TL_A order)",
                "terms": list(self.terms.terms),
                "term_names": self.names,
                "Bt_scale": self.terms.Bt_scale,
                "Bt_source": self.terms.Bt_source,
                "derivative_scheme": self.terms.derivative_scheme,
                "derivative_unit": "per sample",
                "coefficients": dict(zip(self.names, self.coefficients.tolist(), strict=True)),
                "filter": self.bandpass.as_dict(),
                "ridge": self.ridge,
                "sensors": dict(self.sensors),
                "uncertainty": dict(self.uncertainty),
                "stats": dict(self.stats),
                "diagnostics": dict(self.diagnostics),
            }
        )

    def to_json(self, indent: int | None = 2) -> str:
        """JSON text (full float precision: a round trip is exact)."""
        return json.dumps(self.as_dict(), indent=indent, allow_nan=False)

    def to_file(self, path: str | os.PathLike[str]) -> Path:
        """Write the JSON file atomically."""
        return atomic_write_text(path, self.to_json() + "\n")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ScalarCompensation:
        """Rebuild from :meth:`as_dict` output; checks the format and its version."""
        file_major_version(data, "compensation", COMPENSATION_FORMAT_VERSION)
        try:
            terms = TollesLawsonTerms(
                terms=tuple(data["terms"]),
                Bt_scale=float(data["Bt_scale"]),
                derivative_scheme=str(data["derivative_scheme"]),
                Bt_source=str(data.get("Bt_source", "vector")),
            )
            coef_map = data["coefficients"]
            names = terms.names
            if not isinstance(coef_map, Mapping) or sorted(coef_map) != sorted(names):
                raise CalibrationFormatError(
                    f"compensation file: coefficients must name exactly the terms {', '.join(names)}"
                )
            coefficients = np.array([float(coef_map[n]) for n in names])
            f = data["filter"]
            bandpass = BandPass(float(f["low_hz"]), float(f["high_hz"]), float(f["rate_hz"]), int(f["poles"]),
                                int(f["trim"]))
        except KeyError as exc:
            raise CalibrationFormatError(f"compensation file lacks the entry {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise CalibrationFormatError(f"compensation file has an unreadable entry: {exc}") from None
        return cls(
            terms=terms, coefficients=coefficients, bandpass=bandpass, ridge=float(data.get("ridge", 0.0)),
            units=str(data.get("units", "nT")), sensors=dict(data.get("sensors") or {}),
            uncertainty=dict(data.get("uncertainty") or {}), stats=dict(data.get("stats") or {}),
            diagnostics=dict(data.get("diagnostics") or {}), created=str(data.get("created", "")),
            trimag_version=str(data.get("trimag_version", "")), method=str(data.get("method", "ridge-least-squares")),
        )

    @classmethod
    def from_json(cls, text: str) -> ScalarCompensation:
        """Parse JSON text written by :meth:`to_json`."""
        from ..validation import check_nesting

        check_nesting(text, "compensation file", CalibrationFormatError)
        try:
            return cls.from_dict(json.loads(text))
        except json.JSONDecodeError as exc:
            raise CalibrationFormatError(f"compensation file is not valid JSON: {exc}") from None

    @classmethod
    def from_file(cls, path: str | os.PathLike[str]) -> ScalarCompensation:
        """Read a compensation JSON file."""
        p = Path(path)
        if not p.is_file():
            raise TrimagInputError(f"compensation file {str(p)!r} does not exist")
        return cls.from_json(p.read_text(encoding="utf-8"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ScalarCompensation):
            return NotImplemented
        return self.as_dict() == other.as_dict()

    __hash__ = None  # type: ignore[assignment]
