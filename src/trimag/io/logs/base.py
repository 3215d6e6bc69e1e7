"""The types every log reader returns, and the helpers they share (imported by the readers and the package)."""

from __future__ import annotations

import contextlib
import dataclasses
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ...calibration import SensorRecord
from ...errors import TrimagInputError

__all__ = ["Channel", "MagnetometerStream", "SensorChoice", "VehicleLog", "compass_labels", "forward_in_time",
           "mavlink_messages", "require"]

#: How a caller names the magnetometer of a log: its compass number, name or device id (text or a number), a
#: calibration's :class:`~trimag.calibration.SensorRecord` (the same physical compass: :meth:`VehicleLog.choose`),
#: or None (the one with the most samples).
SensorChoice = str | int | SensorRecord | None


def require(module: str) -> Any:
    """Import an optional dependency of the log readers, or raise a one-line error naming the extra."""
    from ..._core.extras import require as require_extra

    return require_extra(module, "reading autopilot logs")


@contextlib.contextmanager
def native_output_discarded() -> Any:
    """The process's own standard output and error (file descriptors 1 and 2) sent to the null device meanwhile:
    pymavlink's compiled log indexer prints "bad header ..." there for each damaged byte it skips, past Python's
    ``sys.stderr`` (issue 41, item 11: 128 054 lines for a random 20 MB ``.px4log``). Python's own streams are
    flushed first, so nothing of theirs is lost."""
    import os
    import sys

    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    try:
        saved = [(fd, os.dup(fd)) for fd in (1, 2)]
    except OSError:  # no such descriptors (an embedding without them): nothing to discard
        yield
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd, _ in saved:
            os.dup2(null, fd)
        yield
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)
        os.close(null)


def mavlink_messages(path: Path, types: list[str]) -> Any:
    """The messages of ``types`` in a pymavlink-readable log, in order; damage gives one clear error.

    pymavlink prints a line for each damaged byte it skips ("bad header ..."): its output goes to a buffer while
    the log is read, so the callers (which collect the messages and print nothing) run with it redirected too.
    """
    mavutil = require("pymavlink.mavutil")
    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
        try:
            with native_output_discarded():  # the compiled indexer's line per damaged byte
                conn = mavutil.mavlink_connection(str(path))
        except Exception as exc:  # pymavlink raises many kinds on a damaged file
            raise TrimagInputError(f"{path}: not a readable log ({type(exc).__name__}: {exc})") from None
        try:
            while True:
                try:
                    msg = conn.recv_match(type=types)
                except Exception as exc:
                    raise TrimagInputError(f"{path}: the log is damaged ({type(exc).__name__}: {exc})") from None
                if msg is None:
                    return
                if quiet.tell() > 1 << 16:  # a long damaged stretch: the buffer is not kept
                    quiet.seek(0)
                    quiet.truncate()
                yield msg
        finally:  # the file pymavlink opened (an unclosed file otherwise: ResourceWarning)
            close = getattr(conn, "close", None)
            if callable(close):
                close()


def forward_in_time(time_s: NDArray[np.float64], *, strictly: bool = False) -> NDArray[np.bool_]:
    """The rows whose time stamp is finite and does not go back: not earlier than any row before it (``strictly``:
    later), shape (N,). Of the two readings of a stamp that jumps, the one keeping more rows wins: rows stamped too
    early are dropped, or a row stamped too late (then the rows after it are kept and it is dropped)."""
    t = np.asarray(time_s, dtype=np.float64)
    finite = np.isfinite(t)
    if len(t) == 0:
        return finite
    before = np.maximum.accumulate(np.concatenate([[-np.inf], np.where(finite, t, -np.inf)[:-1]]))
    after = np.minimum.accumulate(np.concatenate([np.where(finite, t, np.inf)[1:], [np.inf]])[::-1])[::-1]
    if strictly:
        forward, backward = finite & (t > before), finite & (t < after)
    else:
        forward, backward = finite & (t >= before), finite & (t <= after)
    return forward if forward.sum() >= backward.sum() else backward


@dataclass
class Channel:
    """A logged time series: ``time_s`` (N,) and ``values`` (N,) or (N, k), with a unit."""

    time_s: NDArray[np.float64]
    values: NDArray[np.float64]
    unit: str = ""
    source: str = ""


@dataclass
class MagnetometerStream:
    """One magnetometer of a log.

    Attributes
    ----------
    name : str
        How the log names it (``MAG[0]``, ``MAG2``, ``sensor_mag device 592905``, ``IMU1.Mag``).
    instance : int
        0-based instance (ArduPilot compass number, PX4 calibration slot).
    time_s : ndarray, shape (N,)
    field : ndarray, shape (N, 3)
        The reading with the onboard calibration undone (the raw reading in the autopilot's body frame), ``unit``.
    logged : ndarray, shape (N, 3)
        The reading as logged.
    unit : str
    undone : list of str
        What was undone, for the user (empty when the log holds raw readings).
    device_id : int or None
    onboard : dict
        The onboard calibration parameters that were undone.
    """

    name: str
    instance: int
    time_s: NDArray[np.float64]
    field: NDArray[np.float64]
    logged: NDArray[np.float64]
    unit: str
    undone: list[str] = dataclasses.field(default_factory=list)
    device_id: int | None = None
    onboard: dict[str, float] = dataclasses.field(default_factory=dict)

    @property
    def number(self) -> int:
        """The compass number the user gives (``sensor``, ``export --instance``): ``instance + 1``, as the firmware's
        parameter names count (``COMPASS_OFS`` = 1, ``COMPASS_OFS2`` = 2; PX4 ``CAL_MAG0`` = 1)."""
        return self.instance + 1

    @property
    def rate_hz(self) -> float:
        """Median sample rate, Hz (0 for fewer than 2 samples)."""
        dt = np.diff(self.time_s)
        dt = dt[dt > 0]
        return float(1.0 / np.median(dt)) if len(dt) else 0.0

    def describe(self) -> str:
        """One line for the user: name, samples, rate, unit."""
        dev = f", device id {self.device_id}" if self.device_id else ""
        gaps = ""
        if len(self.time_s) > 2 and self.rate_hz > 0:
            span = float(self.time_s[-1] - self.time_s[0])
            longest = float(np.max(np.diff(self.time_s)))
            if span > 1.5 * (len(self.time_s) - 1) / self.rate_hz and longest > 10.0 / self.rate_hz:
                gaps = f" over {span:.0f} s (with gaps: the longest {longest:.0f} s without a reading)"
        return f"{self.name}: {len(self.time_s)} samples at {self.rate_hz:.3g} Hz{gaps}, {self.unit}{dev}"


@dataclass
class VehicleLog:
    """What trimag reads of an autopilot log."""

    path: str
    format: str
    magnetometers: list[MagnetometerStream]
    attitude: Channel | None = None  # yaw, pitch, roll in degrees (Z-Y-X, body -> NED)
    gyro: Channel | None = None  # angular rate (N, 3), rad/s, in the IMU's own frame (the gyro-aided fit)
    channels: dict[str, Channel] = field(default_factory=dict)  # current_A, throttle, temperature_C, ...
    gps: dict[str, Any] | None = None  # lat_deg, lon_deg, alt_m, date (YYYY-MM-DD)
    parameters: dict[str, float] = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)
    #: the firmware and vehicle that wrote the log, where it says (``"ArduCopter V4.3.6"``, ``"PX4 v1.12.3"``)
    vehicle: str | None = None
    #: other yaw sources than the attitude's (``"XKY0.YC"``: EKF-GSF yaw; ``"GPS.Yaw"``: a GPS heading), degrees
    yaw_sources: dict[str, Channel] = field(default_factory=dict)
    #: other whole attitude estimates than :attr:`attitude` (``"AHR2"``: ArduPilot's DCM), yaw, pitch, roll in
    #: degrees; :meth:`table` gives each as columns (:data:`ATTITUDE_COLUMNS`)
    attitudes: dict[str, Channel] = field(default_factory=dict)
    #: the vehicle's altitude, m (shown with the flight; not a regressor): its ``source`` says above what
    altitude: Channel | None = None
    #: the device ids of the magnetometers the log's EKF instances fused (PX4 ``estimator_status.mag_device_id``,
    #: v1.12+), or None where the log does not say: a compass not among them gives a yaw independent of it
    ekf_mag_device_ids: tuple[int, ...] | None = None

    def choose(self, sensor: SensorChoice = None) -> MagnetometerStream:
        """The magnetometer named by ``sensor`` (compass number, name or device id), or the best one.

        Compasses are numbered from 1, as the firmware's parameter names count them (ArduPilot ``COMPASS_OFS``,
        ``COMPASS_OFS2``, ``COMPASS_OFS3`` = 1, 2, 3; PX4 ``CAL_MAG0`` = 1) and as ``export --instance`` does:
        :attr:`MagnetometerStream.number`. Without ``sensor``: the magnetometer with the most samples (the first on
        a tie).
        """
        if not self.magnetometers:
            raise TrimagInputError(f"{self.path}: the log has no magnetometer readings")
        if sensor is None:
            return max(self.magnetometers, key=lambda m: len(m.time_s))
        if isinstance(sensor, SensorRecord):
            return self._recorded(sensor)
        text = str(sensor).strip()
        for m in self.magnetometers:
            if text in (str(m.number), m.name, str(m.device_id)):
                return m
        if text == "0":
            raise TrimagInputError(
                f"{self.path}: compasses are numbered from 1, as the firmware's parameters (COMPASS_OFS = 1, "
                f"COMPASS_OFS2 = 2; CAL_MAG0 = 1): `sensor=1` is {self.magnetometers[0].name}; the log has "
                f"{self.compass_list()}"
            )
        raise TrimagInputError(f"{self.path}: no magnetometer {text!r}; the log has {self.compass_list()} (choose "
                               "with `sensor`)")

    def _recorded(self, record: SensorRecord) -> MagnetometerStream:
        """The stream of a calibration's sensor: the compass with the record's device id (wherever the log numbers
        it; of several streams of it, the one of the same name, else of the same number), or, for a record or a log
        without device ids, the stream of the same name, else of the same number. A log without that device is
        refused: its compasses are other sensors."""
        mags = self.magnetometers
        if record.device_id and any(m.device_id for m in mags):
            same = [m for m in mags if m.device_id == record.device_id]
            if not same:
                listed = ", ".join(f"{m.number} ({m.name}, device id {m.device_id})" for m in mags)
                raise TrimagInputError(
                    f"{self.path}: no compass with device id {record.device_id}, the calibration's sensor "
                    f"({record.describe()}); this log has {listed}: another sensor. Give --sensor N to use this "
                    "calibration on one of them anyway")
            return next((m for m in same if m.name == record.name), next(
                (m for m in same if m.number == record.compass), same[0]))
        found = next((m for m in mags if m.name == record.name), None) or next(
            (m for m in mags if m.number == record.compass), None)
        if found is None:
            raise TrimagInputError(f"{self.path}: no magnetometer {record.name!r} or compass {record.compass} (the "
                                   f"calibration's sensor: {record.describe()}); the log has {self.compass_list()}: "
                                   "choose one with --sensor N")
        return found

    def compass_list(self) -> str:
        """The compasses as the user numbers them: ``"1 (MAG[0]), 2 (MAG[1])"``."""
        return ", ".join(compass_labels([(m.number, m.name) for m in self.magnetometers]))

    def table(self, sensor: SensorChoice = None) -> tuple[pd.DataFrame, list[str]]:
        """One row per sample of the chosen magnetometer, with every other stream aligned to its time stamps.

        Columns: ``time_s``, ``mag_x``, ``mag_y``, ``mag_z`` (calibration undone), ``mag_logged_x..z``, then
        ``yaw_deg``, ``pitch_deg``, ``roll_deg`` (slerp) and the channels (linear interpolation). A channel
        sample outside its stream's time span is left empty (NaN) and counted.

        Returns
        -------
        table, messages
        """
        from scipy.spatial.transform import Rotation, Slerp

        mag = self.choose(sensor)
        messages: list[str] = []
        ahead = forward_in_time(mag.time_s)
        if not ahead.all():  # a clock that jumped back, a damaged stamp: the sample's attitude would be another's
            messages.append(f"warning: dropped {int((~ahead).sum())} of {len(ahead)} {mag.name} samples whose time "
                            "stamp is missing or goes back (earlier than a sample before it: a damaged log or a "
                            "clock reset)")
            mag = dataclasses.replace(mag, time_s=mag.time_s[ahead], field=mag.field[ahead],
                                      logged=mag.logged[ahead])
        t = mag.time_s
        cols: dict[str, NDArray[np.float64]] = {"time_s": t}
        for k, a in enumerate("xyz"):
            cols[f"mag_{a}"] = mag.field[:, k]
        for k, a in enumerate("xyz"):
            cols[f"mag_logged_{a}"] = mag.logged[:, k]
        outside: dict[str, int] = {}
        estimates = [("attitude", self.attitude, ("yaw_deg", "pitch_deg", "roll_deg"))]
        estimates += [(name, ch, ATTITUDE_COLUMNS[name]) for name, ch in self.attitudes.items()
                      if name in ATTITUDE_COLUMNS]
        for label, at, names in estimates:
            if at is None:
                continue
            good = np.isfinite(at.time_s) & np.isfinite(at.values).all(axis=1)
            order = np.argsort(at.time_s[good], kind="stable")
            ta, keep = np.unique(at.time_s[good][order], return_index=True)
            if len(ta) < 2:
                continue
            rot = Rotation.from_euler("ZYX", at.values[good][order][keep], degrees=True)
            inside = (t >= ta[0]) & (t <= ta[-1])
            ypr = np.full((len(t), 3), np.nan)
            if inside.any():
                ypr[inside] = Slerp(ta, rot)(t[inside]).as_euler("ZYX", degrees=True)
            ypr[:, 0] = np.mod(ypr[:, 0], 360.0)
            for k, name in enumerate(names):
                cols[name] = ypr[:, k]
            if (~inside).sum():
                outside[label] = int((~inside).sum())
        outside.update(_yaw_columns(self.yaw_sources, t, cols))
        for name, ch in self.channels.items():
            if len(ch.time_s) < 2:
                continue
            order = np.argsort(ch.time_s, kind="stable")
            tc = ch.time_s[order]
            vals = ch.values[order]
            inside = (t >= tc[0]) & (t <= tc[-1])
            v = np.interp(t, tc, vals)
            v[~inside] = np.nan
            cols[name] = v
            if (~inside).sum():
                outside[name] = int((~inside).sum())
        if outside:
            messages.append(
                f"aligned to {mag.name}'s {len(t)} time stamps; left empty where outside the stream's logged span: "
                + ", ".join(f"{name} {n}" for name, n in outside.items())
            )
        df = pd.DataFrame(cols)
        return df, messages

    def summary_lines(self, sensor: SensorChoice = None) -> list[str]:
        """What the user should know: the magnetometers, what was undone, what else the log offers."""
        chosen = self.choose(sensor)
        lines = [f"{self.format} log with {len(self.magnetometers)} magnetometer(s): "
                 + "; ".join(("* " if m is chosen else "") + f"{m.number}: {m.describe()}" for m in self.magnetometers)
                 + " (* = used; choose another with `sensor`)"]
        lines += [f"{chosen.name}: {u}" for u in chosen.undone]
        offered = list(self.channels)
        if offered:
            lines.append(f"channels for regressors: {', '.join(offered)}")
        if self.gyro is not None:
            lines.append(f"gyroscope: {self.gyro.source}, {len(self.gyro.time_s)} samples (the gyro-aided fit, "
                         "docs/method-gyro.md)")
        lines += self.messages
        return lines


#: The table's columns (yaw, pitch, roll) of each attitude estimate of :attr:`VehicleLog.attitudes`.
ATTITUDE_COLUMNS = {"AHR2": ("yaw_dcm_deg", "pitch_dcm_deg", "roll_dcm_deg")}
#: The table's column of each yaw source of :attr:`VehicleLog.yaw_sources` (a second value column: its sigma).
YAW_COLUMNS = {"XKY0.YC": ("yaw_gsf_deg", "yaw_gsf_sigma_deg"), "GPS.Yaw": ("yaw_gps_deg", None)}


def _yaw_columns(sources: dict[str, Channel], t: NDArray[np.float64],
                 cols: dict[str, NDArray[np.float64]]) -> dict[str, int]:
    """The yaw sources aligned to the time stamps ``t`` (the yaw unwrapped, interpolated, wrapped to 0..360) into
    ``cols``; returns the samples outside each source's span."""
    outside: dict[str, int] = {}
    for name, ch in sources.items():
        if name not in YAW_COLUMNS or len(ch.time_s) < 2:
            continue
        order = np.argsort(ch.time_s, kind="stable")
        tc = ch.time_s[order]
        values = ch.values[order].reshape(len(tc), -1)
        inside = (t >= tc[0]) & (t <= tc[-1])
        yaw_col, sigma_col = YAW_COLUMNS[name]
        yaw = np.mod(np.interp(t, tc, np.degrees(np.unwrap(np.radians(values[:, 0])))), 360.0)
        yaw[~inside] = np.nan
        cols[yaw_col] = yaw
        if sigma_col is not None and values.shape[1] > 1:
            sigma = np.interp(t, tc, values[:, 1])
            sigma[~inside] = np.nan
            cols[sigma_col] = sigma
        if (~inside).sum():
            outside[yaw_col] = int((~inside).sum())
    return outside


def compass_labels(compasses: list[tuple[int, str]]) -> list[str]:
    """Each compass as the user chooses it: ``"2 (MAG[1])"``; a stream whose number an earlier one has (PX4's
    ``vehicle_magnetometer``, the prime compass's calibrated output) by its name: ``"vehicle_magnetometer (also
    compass 2; `sensor=vehicle_magnetometer`)"``, since `sensor=2` chooses the first."""
    seen: set[int] = set()
    labels = []
    for number, name in compasses:
        labels.append(f"{name} (also compass {number}; `sensor={name}`)" if number in seen else f"{number} ({name})")
        seen.add(number)
    return labels
