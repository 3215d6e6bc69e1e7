"""Typed requests of the application layer (what ``trimag fit`` asks for), built by the CLI and by batch runs.

The command line parses its flags into a :class:`FitRequest`; :func:`trimag.workflow.fit_file` takes one. Each
field is named after the Python argument it becomes (``InputSpec.columns``, ``ReferenceSpec.igrf``); the CLI's
help names the flag of each.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import TrimagInputError

__all__ = ["AttitudeSpec", "FitRequest", "InputSpec", "LiveRequest", "ReferenceSpec"]


@dataclass(frozen=True)
class InputSpec:
    """Which samples to read: the file (or log) and how to read it (:func:`trimag.io.read_samples`)."""

    path: str | Path
    fmt: str | None = None
    columns: str | None = None
    var: str | None = None
    units: str | None = None
    rows: str | None = None
    where: str | None = None
    strict: bool = False
    sensor: str | None = None


@dataclass(frozen=True)
class ReferenceSpec:
    """The field reference: a magnitude (number, or an IGRF site, or a column) for scalar models, a background
    vector (NED, or from an iron-free run) or one per sample (``background_columns``: the N, E, D columns, in the
    data's unit) for vector models. All None: none given."""

    reference: str | float | None = None
    igrf_spec: str | None = None
    reference_column: str | None = None
    background_ned: str | None = None
    background_run: str | None = None
    background_columns: str | None = None
    #: a per-sample background from IGRF-14 at each row's position: ``"LAT,LON,ALT_M,YYYY-MM-DD"`` (three columns
    #: and a date; :func:`trimag.io.background.igrf_along_track`)
    igrf_columns: str | None = None

    @property
    def given(self) -> bool:
        """Whether any reference was given."""
        return any(getattr(self, f.name) is not None for f in dataclasses.fields(self))


@dataclass(frozen=True)
class AttitudeSpec:
    """Where the attitudes are (vector models): Euler angle columns (yaw, pitch, roll, degrees, Z-Y-X, body ->
    NED) or quaternion columns in ``quaternion_order`` (``"wxyz"`` or ``"xyzw"``) for ``quaternion_frame``, in the
    data or in ``attitude_file`` (:mod:`trimag.timesync`)."""

    attitude_columns: str | None = None
    quaternion_columns: str | None = None
    quaternion_order: str = "wxyz"
    quaternion_frame: str = "ned"
    #: attitudes from a second file with its own time column (``attitude_time_column``), interpolated (slerp) to
    #: the magnetometer's time stamps (its ``time_column``); the columns above name that file's columns
    attitude_file: str | Path | None = None
    attitude_time_column: str | None = None
    time_column: str | None = None


@dataclass(frozen=True)
class FitRequest:
    """One fit: read ``input``, take the ``reference`` (and ``attitude``), fit ``model`` by ``method`` with
    ``options`` (and the offset's ``regressors``: column names whose terms ``k_j (u_j - mean_j)`` are fitted
    jointly, docs/vehicle.md), or, with a ``prior`` calibration, refit only its offset (docs/vehicle.md), check
    ``policy`` (a TOML file or ``"default"``) and write ``out`` (calibration JSON) and ``report`` (figure) when
    given. With ``accel_columns`` (``"AX,AY,AZ"``, specific force at rest or moving slowly) the rotation from the
    corrected magnetometer frame to the accelerometer frame and the dip angle are estimated after the calibration
    (:func:`trimag.alignment.fit_alignment`, docs/vehicle.md)."""

    input: InputSpec
    model: str = "ellipsoid"
    method: str | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    reference: ReferenceSpec = field(default_factory=ReferenceSpec)
    attitude: AttitudeSpec = field(default_factory=AttitudeSpec)
    out: str | Path | None = None
    report: str | Path | None = None
    policy: str | None = None
    regressors: tuple[str, ...] | None = None
    #: sample rate (Hz) of the eddy-current terms' derivative (``option eddy``) when there is no ``time_column``
    rate_hz: float | None = None
    #: an earlier calibration (JSON) whose shape is kept while its offset is refitted (:mod:`trimag.prior`)
    prior: str | Path | None = None
    accel_columns: str | None = None

    @classmethod
    def of(cls, path: str | Path, **arguments: Any) -> FitRequest:
        """A request from flat keyword arguments (the fields of the specs and of the request itself), e.g.
        ``FitRequest.of("log.csv", units="uT", igrf_spec="52.5,13.3,40,2021-01-01", out="cal.json")``."""
        groups: dict[type, dict[str, Any]] = {InputSpec: {}, ReferenceSpec: {}, AttitudeSpec: {}, cls: {}}
        specs = (InputSpec, ReferenceSpec, AttitudeSpec)
        owner: dict[str, type] = {f.name: spec for spec in specs for f in dataclasses.fields(spec)}
        owner.update({f.name: cls for f in dataclasses.fields(cls) if f.name not in ("input", "reference", "attitude")})
        for name, value in arguments.items():
            if name not in owner or name == "path":
                raise TrimagInputError(f"unknown fit argument {name!r}; known: {', '.join(sorted(owner))}")
            groups[owner[name]][name] = value
        if groups[cls].get("options") is None:
            groups[cls].pop("options", None)
        return cls(
            input=InputSpec(path, **groups[InputSpec]),
            reference=ReferenceSpec(**groups[ReferenceSpec]),
            attitude=AttitudeSpec(**groups[AttitudeSpec]),
            **groups[cls],
        )


#: The sources of ``trimag live`` (the :class:`LiveRequest` field that names each).
LIVE_SOURCES = ("replay", "stdin", "serial", "mavlink")


@dataclass(frozen=True)
class LiveRequest:
    """One live recording (``trimag live``, :func:`trimag.live.run_live`): exactly one source (``replay`` a log at
    ``rate`` samples/s, ``stdin`` lines, a ``serial`` port at ``baud``, or a ``mavlink`` URL), fitted with ``model``
    (and ``method``, ``options``, the field magnitude ``reference`` in ``units`` when known), served on ``port``
    (127.0.0.1 only; 0 picks a free port), saved to ``out`` (calibration JSON) and ``samples_out`` (CSV; default
    beside ``out``) on the page's save button, on SIGINT, and (``exit_at_end``) when the source ends."""

    replay: str | Path | None = None
    rate: float | None = 2000.0
    stdin: bool = False
    serial: str | None = None
    baud: int = 115200
    mavlink: str | None = None
    fmt: str | None = None
    columns: str | None = None
    sensor: str | None = None
    units: str | None = None
    model: str = "ellipsoid"
    method: str | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    reference: float | None = None
    port: int = 8765
    out: str | Path = "trimag-live-calibration.json"
    samples_out: str | Path | None = None
    open_browser: bool = True
    exit_at_end: bool = False
    interval: float = 0.25

    @property
    def source(self) -> str:
        """The one source given (``"replay"``, ``"stdin"``, ``"serial"`` or ``"mavlink"``)."""
        given = [name for name in LIVE_SOURCES if getattr(self, name) not in (None, False)]
        if len(given) != 1:
            named = ", ".join(f"`{name}`" for name in given) if given else "none"
            raise TrimagInputError(
                f"give exactly one source: `replay`, `stdin`, `serial` or `mavlink` (given: {named})"
            )
        return given[0]
