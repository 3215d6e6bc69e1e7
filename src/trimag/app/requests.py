"""Typed requests of the application layer (what each ``trimag`` command asks for), built by the CLI and by batch
runs.

The command line parses its flags into one request per command (:class:`FitRequest`, :class:`EvaluateRequest`,
:class:`ApplyRequest`, :class:`ExportRequest`, :class:`SimulateRequest`, :class:`LiveRequest`); each entry point of
:mod:`trimag.app` takes one. The shared parts are :class:`InputSpec` (which samples), :class:`ReferenceSpec` (the
field reference) and :class:`AttitudeSpec` (the attitudes). Each field is named after the Python argument it
becomes (``InputSpec.columns``, ``ReferenceSpec.igrf_spec``) and after the CLI flag's destination; the CLI's help
names the flag of each.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from .._core.chunks import DEFAULT_CHUNK_ROWS
from ..errors import TrimagInputError

__all__ = [
    "ApplyRequest", "AttitudeSpec", "EvaluateRequest", "ExportRequest", "FitRequest", "InputSpec", "LiveRequest",
    "ReferenceSpec", "ReviewRequest", "SimulateRequest",
]

_R = TypeVar("_R")


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
    data or in ``attitude_file`` (:mod:`trimag.vehicle.timesync`)."""

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
    (:func:`trimag.vehicle.alignment.fit_alignment`, docs/vehicle.md)."""

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
    #: an earlier calibration (JSON) whose shape is kept while its offset is refitted (:mod:`trimag.vehicle.prior`)
    prior: str | Path | None = None
    accel_columns: str | None = None
    #: a firmware-space fit (``"ardupilot"``, ``"px4"``): exactly the parameters it loads, at ``level`` (``"auto"``,
    #: ``"offsets"``, ``"scale"``, ``"diagonal"``, ``"full"``) with the ``motor`` term (``"auto"``, ``"none"``,
    #: ``"current"``, ``"throttle"``; :mod:`trimag.vehicle.firmware`)
    target: str | None = None
    level: str | None = None
    motor: str | None = None
    #: the yaw of a firmware fit of a log: ``"auto"`` (None: a GPS heading, else the EKF-GSF yaw, else the log's
    #: attitude), ``"attitude"`` (the log's attitude: heading-free where its EKF used this compass), ``"gsf"``
    #: (ArduPilot's ``XKY0``), ``"gps"`` (a moving-baseline GPS heading)
    yaw_source: str | None = None
    #: a vehicle that turns but cannot tilt: :func:`trimag.vehicle.level_turn.fit_level_turn` (docs/autopilot.md)
    level_turn: bool = False
    #: the vehicle's known true heading (degrees), or a column of it: the offsets from the field's vector
    #: (:func:`trimag.vehicle.fixed_yaw.fit_fixed_heading`, as ArduPilot's MAG_CAL_YAW)
    heading: float | None = None
    heading_column: str | None = None
    #: the deviation card's figure (PNG) of a ``level_turn`` or ``heading`` fit
    deviation_card: str | Path | None = None
    #: with ``input.sensor="all"`` (:func:`trimag.app.fit_all_sensors`): one parameter file (``export_out``) of
    #: ``export_to`` (``"ardupilot"`` or ``"px4"``) with every compass fitted
    export_to: str | None = None
    export_out: str | Path | None = None
    #: with ``export_to``: write the parameters even of a compass the policy rejected or whose unit its fit doubted
    force: bool = False
    #: the gyro-aided fit (``method=gyro``, docs/method-gyro.md): the gyroscope's columns ``"GX,GY,GZ"`` in the same
    #: rows (with ``attitude.time_column`` or ``rate_hz``) or in ``gyro_file`` (its own clock: ``gyro_time_column``,
    #: default ``attitude.time_column``), in ``gyro_unit`` (``"rad/s"``, ``"deg/s"``; default from the column names,
    #: else rad/s)
    gyro_columns: str | None = None
    gyro_unit: str | None = None
    gyro_file: str | Path | None = None
    gyro_time_column: str | None = None
    #: the sensor's positions ``"X,Y,Z"`` (m, the attitudes' frame; in the data or in ``attitude.attitude_file``):
    #: ``interference12`` fits the background's gradient across the room (:mod:`trimag.vehicle.gradient`)
    position_columns: str | None = None

    @classmethod
    def of(cls, path: str | Path, **arguments: Any) -> FitRequest:
        """A request from flat keyword arguments (the fields of the specs and of the request itself), e.g.
        ``FitRequest.of("log.csv", units="uT", igrf_spec="52.5,13.3,40,2021-01-01", out="cal.json")``."""
        if arguments.get("options", {}) is None:
            arguments = {k: v for k, v in arguments.items() if k != "options"}
        return _from_flat(cls, "fit", path, {}, arguments)


#: The parts of a request that group several arguments, by the request's field name.
_SPECS: dict[str, type] = {"input": InputSpec, "reference": ReferenceSpec, "attitude": AttitudeSpec}


def _from_flat(cls: type[_R], what: str, path: str | Path, fixed: dict[str, Any], arguments: Mapping[str, Any]) -> _R:
    """A request ``cls`` from flat keyword ``arguments``: each goes to the spec that has a field of its name
    (:data:`_SPECS`), else to the request itself; ``path`` is the input's path and ``fixed`` the request's own
    positional fields. An unknown name is refused, naming the known ones (``what`` names the command)."""
    types = {f.name: f.type for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    own = list(types)
    specs = {name: spec for name, spec in _SPECS.items() if types.get(name) in (spec, spec.__name__)}
    owner: dict[str, str] = {f.name: name for name, spec in specs.items() for f in dataclasses.fields(spec)}
    owner.update({name: "" for name in own if name not in specs and name not in fixed})
    groups: dict[str, dict[str, Any]] = {name: {} for name in ["", *specs]}
    for name, value in arguments.items():
        if name not in owner or name == "path":
            raise TrimagInputError(f"unknown {what} argument {name!r}; known: {', '.join(sorted(owner))}")
        groups[owner[name]][name] = value
    parts = {name: spec(**({"path": path} if spec is InputSpec else {}), **groups[name])
             for name, spec in specs.items()}
    return cls(**fixed, **parts, **groups[""])


def as_request(cls: type[_R], request: Any, positional: tuple[Any, ...], arguments: dict[str, Any]) -> _R:
    """``request`` when it is a ``cls`` (and nothing else is given), else ``cls.of(request, *positional,
    **arguments)``: the entry points of :mod:`trimag.app` take a request or its flat arguments."""
    if isinstance(request, cls):
        if positional or arguments:
            raise TrimagInputError(f"give either a {cls.__name__} or its arguments, not both")
        return request
    return cls.of(request, *positional, **arguments)  # type: ignore[attr-defined]


@dataclass(frozen=True)
class EvaluateRequest:
    """One evaluation (``trimag evaluate``) of the ``calibration`` (JSON) on the samples of ``input``.

    Which evaluation runs follows what is given: with ``accel_columns`` the tilt-compensated heading against
    ``heading_column`` or the yaw of ``attitude.attitude_columns`` (with the declination from ``reference.igrf_spec``
    or ``declination``, degrees east); with attitude columns the vector errors against ``reference.background_ned``,
    ``reference.igrf_spec`` or ``reference.background_columns``; otherwise the magnitude errors against
    ``reference`` (``reference``, ``igrf_spec`` or ``reference_column``; the mean corrected magnitude when none),
    streamed in ``chunk_rows`` rows. ``input.units``, when given, must match the calibration's; ``input.sensor``
    picks the magnetometer of an autopilot log; with ``input.strict`` a row with a bad field value is refused."""

    calibration: str | Path
    input: InputSpec
    reference: ReferenceSpec = field(default_factory=ReferenceSpec)
    attitude: AttitudeSpec = field(default_factory=AttitudeSpec)
    accel_columns: str | None = None
    heading_column: str | None = None
    declination: float | str | None = None
    chunk_rows: int = DEFAULT_CHUNK_ROWS
    #: sample rate (Hz) of the data for a calibration's eddy-current terms when there is no ``attitude.time_column``
    #: (checked against the calibration's)
    rate_hz: float | None = None
    #: the sensor's positions ``"X,Y,Z"`` (m) for a calibration with a background gradient (default: the columns it
    #: was fitted with)
    position_columns: str | None = None

    @classmethod
    def of(cls, calibration: str | Path, data: str | Path, **arguments: Any) -> EvaluateRequest:
        """A request from flat keyword arguments (the fields of the specs and of the request itself), e.g.
        ``EvaluateRequest.of("cal.json", "log.csv", reference=48000.0)``."""
        return _from_flat(cls, "evaluate", data, {"calibration": calibration}, arguments)


@dataclass(frozen=True)
class ApplyRequest:
    """One correction (``trimag apply``): every row of ``input`` corrected by ``calibration`` (JSON) and written to
    ``out`` (``.csv``, ``.txt``, ``.parquet`` or ``.npz``), streamed in ``chunk_rows`` rows. ``input.units``, when
    given, must match the calibration's; ``input.sensor`` picks the magnetometer of an autopilot log; with
    ``input.strict`` a row that cannot be corrected is refused (nothing written); ``input.rows`` and ``where`` are
    not used (every row is kept).
    ``scalar_column`` is for Tolles-Lawson compensation files only."""

    calibration: str | Path
    input: InputSpec
    out: str | Path
    chunk_rows: int = DEFAULT_CHUNK_ROWS
    scalar_column: str | None = None

    @classmethod
    def of(cls, calibration: str | Path, data: str | Path, out: str | Path, **arguments: Any) -> ApplyRequest:
        """A request from flat keyword arguments, e.g. ``ApplyRequest.of("cal.json", "log.csv", "out.csv")``."""
        return _from_flat(cls, "apply", data, {"calibration": calibration, "out": out}, arguments)


@dataclass(frozen=True)
class ExportRequest:
    """One export (``trimag export``): the ``calibration`` (JSON) in ``target``'s convention (``"ardupilot"``,
    ``"px4"``, ``"c-header"``, ``"json"``, ``"ros-yaml"``, ``"matlab"``) for magnetometer ``instance`` (1-based;
    None: the compass of the log the calibration was fitted to, else 1), written to ``out``."""

    calibration: str | Path
    target: str
    out: str | Path
    instance: int | None = None
    #: write the parameters even of a calibration its fit rejected (the policy) or whose unit it doubted
    force: bool = False


@dataclass(frozen=True)
class SimulateRequest:
    """One simulated log (``trimag simulate``): ``n`` samples of a ``model`` sensor with the parameters in
    ``params_path`` (JSON ``{name: value}``), per-axis noise ``noise`` (standard deviation, field units), field
    magnitude ``field`` along north, ``attitudes`` (``"random"`` or ``"axes"``) drawn with ``seed``; written to
    ``out`` (CSV) and, with ``truth``, the true parameters (JSON, recording ``units``)."""

    model: str
    params_path: str | Path
    n: int
    out: str | Path
    noise: float = 0.0
    attitudes: str = "random"
    seed: int = 0
    field: float = 1.0
    units: str | None = None
    truth: str | Path | None = None


@dataclass(frozen=True)
class ReviewRequest:
    """One flight review (``trimag review``, :func:`trimag.live.review.run_review`): the autopilot ``log`` or table (its
    format ``fmt`` when the extension does not say), fitted for ``target`` (default: the log's own firmware) with
    the field at ``igrf_spec`` when the log has no GPS fix, served on ``port`` (127.0.0.1 only; 0 picks a free one),
    the browser opened unless ``open_browser`` is false."""

    log: str | Path
    fmt: str | None = None
    target: str | None = None
    igrf_spec: str | None = None
    port: int = 8765
    open_browser: bool = True
    #: a table's unit and columns (``fit``'s ``--units``, ``--columns``, ``--attitude-columns``) and time column (s)
    units: str | None = None
    columns: str | None = None
    attitude_columns: str | None = None
    time_column: str | None = None


#: The sources of ``trimag live`` (the :class:`LiveRequest` field that names each).
LIVE_SOURCES = ("replay", "stdin", "serial", "mavlink")


@dataclass(frozen=True)
class LiveRequest:
    """One live recording (``trimag live``, :func:`trimag.live.run_live`): exactly one source (``replay`` a log at
    ``rate`` samples/s, ``stdin`` lines, a ``serial`` port at ``baud``, or a ``mavlink`` URL), fitted with ``model``
    (and ``method``, ``options``, the field magnitude ``reference`` in ``units`` when known), served on ``port``
    (127.0.0.1 only; 0 picks a free port), saved to ``out`` (calibration JSON) and ``samples_out`` (CSV; default
    beside ``out``) on the page's save button, on SIGINT or SIGTERM, and (``exit_at_end``) when the source ends;
    what cannot work (a non-finite ``rate``, ``interval`` or ``reference``, a ``port`` outside 0-65535, an unknown
    unit, an output that cannot be written or would replace the replayed log) is refused before it starts."""

    replay: str | Path | None = None
    rate: float | None = 2000.0
    stdin: bool = False
    serial: str | None = None
    baud: int = 115200
    mavlink: str | None = None
    fmt: str | None = None
    columns: str | None = None
    var: str | None = None
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
