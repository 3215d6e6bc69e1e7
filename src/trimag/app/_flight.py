"""What the flight review shows of a log and its fits (private; :mod:`trimag.app.review` fits, and the HTML report of
``fit --report report.html`` draws the same): the flight, the compasses, the expected against the measured field,
the field length, the heading, the verdict, the downloads, and the self-contained HTML report.
"""

from __future__ import annotations

import dataclasses
import json
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from .requests import AttitudeSpec, FitRequest, InputSpec, ReferenceSpec

__all__ = ["DISPLAY_POINTS", "LEVELS", "MOTORS", "CompassResult", "FlightLog", "TableInput", "plotly_js",
           "report_html"]

#: At most this many points of a series are drawn (evenly spaced rows; the fit always takes every row).
DISPLAY_POINTS = 3000
#: The levels and motor terms a user chooses among (``fit --level``, ``--motor``).
LEVELS = ("auto", "offsets", "scale", "diagonal", "full")
MOTORS = ("auto", "none", "current", "throttle")
#: The downloads: parameter files (as ``trimag export --to``) and the calibration JSON.
DOWNLOADS = {"ardupilot": ("ardupilot", ".param"), "px4": ("px4", ".txt"), "qgc": ("qgc", ".params")}


def plotly_js() -> bytes:
    """Plotly's own ``plotly.min.js`` from the ``plotly`` package (the ``review`` extra): served to the page and
    written inline into the HTML report; never fetched from the network."""
    from importlib import resources

    from .._core.extras import require

    require("plotly", "trimag review and the HTML report")
    return (resources.files("plotly") / "package_data" / "plotly.min.js").read_bytes()


def _shown(n: int) -> NDArray[np.int64]:
    """The rows drawn of ``n``: all up to :data:`DISPLAY_POINTS`, else evenly spaced ones (first and last kept)."""
    if n <= DISPLAY_POINTS:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, DISPLAY_POINTS).round().astype(np.int64))


def _series(values: Any, digits: int = 5) -> list[float | None]:
    """A series as JSON numbers (NaN and inf as null: a gap in the line)."""
    a = np.asarray(values, dtype=np.float64)
    out = np.round(a, digits).astype(object)
    out[~np.isfinite(a)] = None
    return list(out.tolist())


def _finite_or_none(value: Any) -> Any:
    """JSON-safe numbers, recursively (NaN and inf as null)."""
    if isinstance(value, dict):
        return {str(k): _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _unwrapped_breaks(deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """A wrapped angle (deg, [-180, 180)) with a gap (NaN) where it jumps across the wrap, so no line is drawn
    across the plot."""
    out = np.array(deg, dtype=np.float64)
    jump = np.abs(np.diff(out)) > 180.0
    out[1:][jump] = np.nan
    return out


def _figure(traces: list[dict[str, Any]], title: str, **layout: Any) -> dict[str, Any]:
    return {"data": traces, "layout": {"title": {"text": title, "font": {"size": 14}, "y": 0.99, "yanchor": "top"},
                                       "height": 340,
                                       "margin": {"l": 60, "r": 60, "t": 60, "b": 40},
                                       "legend": {"orientation": "h", "x": 0, "y": 1.0, "yanchor": "bottom"},
                                       **layout}}


def _line(x: Any, y: Any, name: str, **more: Any) -> dict[str, Any]:
    return {"type": "scatter", "mode": "lines", "x": _series(x, 3), "y": _series(y), "name": name,
            "line": {"width": 1}, **more}


@dataclass
class CompassResult:
    """One compass's fit of the chosen range (or its refusal) and what is judged of it."""

    number: int
    calibration: Calibration | None
    summary: dict[str, Any] = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)
    error: str | None = None
    exit_code: int = 0
    rows: str = ""
    command: str = ""


class FlightLog:
    """An autopilot log under review, read once: what is shown of it and of the fits in :attr:`results`
    (:class:`trimag.app.review.FlightReview` fits).

    Parameters
    ----------
    path : str or Path
        A log ``trimag fit`` reads (DataFlash ``.bin``/``.log``, ``.tlog``, ULog, ``.px4log``), or a table with its
        attitude columns (one compass).
    fmt : str, optional
        The log's format when its extension does not say.
    target : str, optional
        ``"ardupilot"`` or ``"px4"``; default: the log's own firmware.
    igrf_spec : str, optional
        ``LAT,LON,ALT_M,DATE`` for a log without a GPS fix.
    units, columns, attitude_columns, time_column : str, optional
        A table's unit and columns (:func:`_read_table`).
    progress : callable, optional
        ``progress(fraction, what)`` while the log is read (:func:`trimag.io.logs.read_log`).
    """

    def __init__(self, path: str | Path, *, fmt: str | None = None, target: str | None = None,
                 igrf_spec: str | None = None, units: str | None = None, columns: str | None = None,
                 attitude_columns: str | None = None, time_column: str | None = None,
                 progress: Callable[[float, str], None] | None = None) -> None:
        from ..io.logs import log_format, read_log

        self.path = Path(path)
        if not self.path.is_file():
            raise TrimagInputError(f"{path}: no such file")
        self.fmt = fmt
        self.table_input: TableInput | None = None
        if log_format(self.path, fmt) is None:  # a table (CSV, ...): its columns as a one-compass flight
            if progress is not None:
                progress(0.0, f"reading the table {self.path.name}")
            self.table_input = _read_table(self.path, fmt, units, columns, attitude_columns, time_column)
            self.log = self.table_input.log
            if progress is not None:
                progress(1.0, f"read the table {self.path.name}: {len(self.log.magnetometers[0].time_s)} rows")
        else:
            self.log = read_log(self.path, fmt, progress=progress)
        if not self.log.magnetometers:
            raise TrimagInputError(f"{path}: the log has no magnetometer readings")
        fw = self.log.format
        own = "ardupilot" if fw.startswith(("ArduPilot", "MAVLink")) else "px4" if fw.startswith("PX4") else None
        #: the firmware whose parameters are fitted; "" when neither the log nor the user says (nothing is fitted:
        #: every compass says why, the rest is shown)
        self.target: str = str(target or own or "")
        self.igrf_spec = igrf_spec
        self.results: dict[int, CompassResult] = {}
        self.choice: dict[str, Any] = {}
        self._tables: dict[int, Any] = {}
        self._lock = threading.Lock()

    def unavailable(self) -> list[str]:
        """What this log cannot show or fit, one line each (the page and the report say it)."""
        out = []
        if not self.target:
            out.append(f"no parameters are fitted: a {self.log.format} names no firmware; give --target ardupilot or "
                       "--target px4")
        if self.log.attitude is None:
            out.append("no attitude: the expected field, the heading and a vector fit need one (a table's yaw, pitch "
                       "and roll columns: --attitude-columns YAW,PITCH,ROLL); a fit uses the field's magnitude")
        if self.log.gps is None and self.igrf_spec is None:
            out.append("no GPS fix: the expected field and a fit need the Earth's field (--igrf LAT,LON,ALT_M,DATE)")
        if self.table_input is not None:
            out += self.table_input.notes
        return out

    # ------------------------------------------------------------------ the log as it is
    @property
    def span_s(self) -> tuple[float, float]:
        """First and last magnetometer time stamp of the log, seconds."""
        t = np.concatenate([m.time_s for m in self.log.magnetometers])
        return float(np.min(t)), float(np.max(t))

    def compasses(self) -> list[dict[str, Any]]:
        """Every compass of the log, as the firmware numbers it, with its device id, rate, gaps, the log's own
        calibration (the parameters undone) and its health (readings' spread, non-finite rows)."""
        out = []
        for m in self.log.magnetometers:
            dt = np.diff(m.time_s)
            rate = m.rate_hz
            gap_s = 10.0 / rate if rate > 0 else np.inf
            norm = np.linalg.norm(m.logged, axis=1)
            finite = np.isfinite(norm)
            mean = float(np.mean(norm[finite])) if finite.any() else float("nan")
            out.append(_finite_or_none({
                "number": m.number, "name": m.name, "device_id": m.device_id, "n_samples": len(m.time_s),
                "rate_hz": round(rate, 3), "span_s": float(m.time_s[-1] - m.time_s[0]) if len(m.time_s) else 0.0,
                "n_gaps": int(np.sum(dt > gap_s)) if len(dt) else 0,
                "longest_gap_s": float(np.max(dt)) if len(dt) else 0.0,
                "unit": m.unit, "undone": list(m.undone), "onboard": dict(m.onboard),
                "health": {"mean_norm": mean, "std_norm_percent": float(100 * np.std(norm[finite]) / mean)
                           if finite.any() and mean > 0 else None, "non_finite_rows": int(np.sum(~finite))},
                "describe": m.describe(),
            }))
        return out

    def flight_figure(self, start_s: float | None = None, stop_s: float | None = None) -> dict[str, Any]:
        """Attitude, altitude, throttle and current against time (stacked panels, one time axis), the fit range
        shaded."""
        log = self.log
        panels: list[tuple[str, list[dict[str, Any]]]] = []
        if log.attitude is not None:
            t, v = log.attitude.time_s, log.attitude.values
            k = _shown(len(t))
            colours = ("#1f77b4", "#ff7f0e", "#2ca02c")
            lines = [_line(t[k], v[k, j], f"{name} ({log.attitude.source})", legendgroup=name,
                           line={"width": 1, "color": colours[j]})
                     for j, name in enumerate(("yaw", "pitch", "roll"))]
            for other in log.attitudes.values():  # DCM (AHR2): dotted, beside the EKF's
                t2, v2 = other.time_s, other.values
                k2 = _shown(len(t2))
                lines += [_line(t2[k2], np.mod(v2[k2, j], 360.0) if j == 0 else v2[k2, j], f"{name} ({other.source})",
                                legendgroup=name, line={"width": 1, "color": colours[j], "dash": "dot"})
                          for j, name in enumerate(("yaw", "pitch", "roll"))]
            panels.append(("attitude (deg)", lines))
        if log.altitude is not None and len(log.altitude.time_s):
            k = _shown(len(log.altitude.time_s))
            panels.append(("altitude (m)", [_line(log.altitude.time_s[k], log.altitude.values[k],
                                                  f"altitude ({log.altitude.source})")]))
        for name, label in (("throttle", "throttle"), ("current_A", "current (A)")):
            ch = log.channels.get(name)
            if ch is not None and len(ch.time_s):
                k = _shown(len(ch.time_s))
                values = np.asarray(ch.values, dtype=float).reshape(len(ch.time_s), -1)[:, 0]
                panels.append((label, [_line(ch.time_s[k], values[k], f"{name} ({ch.source})")]))
        n = max(len(panels), 1)
        gap = 0.04
        height = (1.0 - gap * (n - 1)) / n
        traces: list[dict[str, Any]] = []
        axes: dict[str, Any] = {}
        for i, (label, lines) in enumerate(panels):
            ref = "y" if i == 0 else f"y{i + 1}"
            top = 1.0 - i * (height + gap)
            axes["yaxis" if i == 0 else f"yaxis{i + 1}"] = {"title": {"text": label}, "domain": [top - height, top],
                                                            "fixedrange": True}
            traces += [{**line, "yaxis": ref} for line in lines]
        lo, hi = self.span_s
        shapes = []
        if start_s is not None and stop_s is not None:
            shapes.append({"type": "rect", "xref": "x", "yref": "paper", "x0": start_s, "x1": stop_s, "y0": 0,
                           "y1": 1, "fillcolor": "rgba(40,120,220,0.12)", "line": {"width": 0}, "layer": "below"})
        return _figure(traces, "the flight: drag across it to choose the rows to fit (the rest are held out); "
                       "double-click: the whole flight", height=140 + 110 * n, dragmode="zoom", shapes=shapes,
                       xaxis={"title": {"text": "time (s)"}, "range": [lo, hi], "anchor": f"y{n}" if n > 1 else "y"},
                       **axes)

    def overview(self) -> dict[str, Any]:
        """What the page shows before any fit: the log, its compasses, the flight, the choices."""
        lo, hi = self.span_s
        return _finite_or_none({
            "path": self.path.name, "format": self.log.format, "vehicle": self.log.vehicle, "target": self.target,
            "gps": self.log.gps, "span_s": [lo, hi], "compasses": self.compasses(),
            "attitude_source": None if self.log.attitude is None else self.log.attitude.source,
            "attitude_sources": {name: ch.source for name, ch in self.log.attitudes.items()},
            "altitude_source": None if self.log.altitude is None else self.log.altitude.source,
            "yaw_sources": sorted(self.log.yaw_sources), "channels": sorted(self.log.channels),
            "levels": list(LEVELS), "motors": list(MOTORS), "yaw_choices": self.yaw_sources(),
            "flight": self.flight_figure(),
            "messages": list(self.log.messages), "unavailable": self.unavailable(),
            "table": self.table_input is not None,
        })

    def yaw_sources(self) -> list[str]:
        """The yaw sources this log offers a firmware fit (``fit --yaw-source``; a table: its columns only)."""
        if self.table_input is not None:
            return ["auto"]
        out = ["auto", "attitude"] if self.log.attitude is not None else ["auto"]
        out += ["dcm"] if "AHR2" in self.log.attitudes else []
        return out + [name for name, key in (("gsf", "XKY0.YC"), ("gps", "GPS.Yaw")) if key in self.log.yaw_sources]

    # ------------------------------------------------------------------ the fit
    def _table(self, number: int) -> Any:
        """The compass's full table (every row, the calibration undone; other streams aligned), read once."""
        from ..io import read_samples

        if number not in self._tables:
            if self.table_input is not None:
                self._tables[number] = self.table_input.samples
            else:
                self._tables[number] = read_samples(self.path, fmt=self.fmt, sensor=str(number))
        return self._tables[number]

    def rows_of(self, number: int, start_s: float, stop_s: float) -> tuple[int, int]:
        """The compass's rows in ``[start_s, stop_s]``: ``(START, STOP)`` of ``fit --rows START:STOP``."""
        t = self.log.choose(number).time_s
        a, b = int(np.searchsorted(t, start_s, "left")), int(np.searchsorted(t, stop_s, "right"))
        if self.table_input is not None:  # the kept rows' numbers in the file (`--rows` counts the file's data rows)
            index = self.table_input.rows
            return (int(index[a]) if a < len(index) else int(index[-1]) + 1), (int(index[b - 1]) + 1 if b > 0 else 0)
        return a, b

    def request(self, number: int, start_s: float, stop_s: float, level: str = "auto", motor: str = "auto",
                yaw_source: str = "auto", out: str | Path | None = None,
                report: str | Path | None = None) -> FitRequest:
        """The :class:`FitRequest` of one compass over the time range: exactly what the command line fits."""
        a, b = self.rows_of(number, start_s, stop_s)
        ti = self.table_input
        if ti is not None:
            inp = InputSpec(self.path, fmt=self.fmt, columns=ti.columns, units=ti.units, rows=f"{a}:{b}")
            attitude = AttitudeSpec(attitude_columns=ti.attitude_columns)
        else:
            inp, attitude = InputSpec(self.path, fmt=self.fmt, rows=f"{a}:{b}", sensor=str(number)), AttitudeSpec()
        return FitRequest(input=inp, attitude=attitude,
                          reference=ReferenceSpec(igrf_spec=self.igrf_spec), target=self.target or None,
                          level=None if level == "auto" else level, motor=None if motor == "auto" else motor,
                          yaw_source=None if yaw_source == "auto" else yaw_source, out=out, report=report)

    def command(self, req: FitRequest) -> str:
        """The command line of ``req`` (what the page shows beside the result)."""
        words = ["trimag", "fit", str(self.path)]
        for flag, value in (("--format", req.input.fmt), ("--columns", req.input.columns), ("--units", req.input.units),
                            ("--attitude-columns", req.attitude.attitude_columns), ("--target", req.target),
                            ("--sensor", req.input.sensor)):
            if value:
                words += [flag, str(value)]
        words += ["--rows", str(req.input.rows)]
        if req.level:
            words += ["--level", req.level]
        if req.motor:
            words += ["--motor", req.motor]
        if req.yaw_source:
            words += ["--yaw-source", req.yaw_source]
        if req.reference.igrf_spec:
            words += ["--igrf", req.reference.igrf_spec]
        return " ".join([*words, "-o", f"compass{req.input.sensor or 1}.json"])

    # ------------------------------------------------------------------ what is judged and drawn
    def figure_yaw_source(self, cal: Calibration | None) -> str:
        """The yaw source the figures take: the one the fit took (recorded in its calibration, ``auto`` resolved on
        the fitted rows), else the user's choice."""
        fw = (cal.diagnostics.get("firmware") or {}) if cal is not None else {}
        return str((fw.get("attitude") or {}).get("yaw_source") or self.choice.get("yaw_source") or "auto")

    def _ned(self, unit: str) -> NDArray[np.float64] | None:
        """The Earth's field (NED) at the log's GPS fix (or ``igrf_spec``), in ``unit``; None without either."""
        from ..fields.reference import igrf, parse_igrf_spec
        from ..units import convert

        spec = self.igrf_spec
        gps = self.log.gps
        if spec is None and gps and gps.get("date"):
            spec = f"{gps['lat_deg']:.6f},{gps['lon_deg']:.6f},{gps['alt_m']:.1f},{gps['date']}"
        if spec is None:
            return None
        return np.asarray(igrf(*parse_igrf_spec(spec)).ned_nT, dtype=np.float64) * convert(1.0, "nT", unit)

    def judged(self, number: int) -> dict[str, Any]:
        """One compass's series over the whole log and their statistics on the fitted and the held-out rows:
        expected body field, the log's calibration, the candidate; field length; heading."""
        from ..fields.attitude import body_field
        from ..vehicle.heading import heading_difference, tilt_compensated_heading
        from ._firmware import flight_attitude

        samples = self._table(number)
        table = samples.table
        unit = samples.log_info["unit"]
        t = table["time_s"].to_numpy(dtype=float)
        logged = table[["mag_logged_x", "mag_logged_y", "mag_logged_z"]].to_numpy(dtype=float)
        result = self.results.get(number)
        cal = result.calibration if result is not None else None
        out: dict[str, Any] = {"t": t, "logged": logged, "unit": unit}
        if cal is not None:
            regressors = None
            if cal.regressors is not None:
                name = cal.regressors["names"][0]
                regressors = {name: table[name].to_numpy(dtype=float)}
            out["candidate"] = cal.apply(samples.field, regressors=regressors)
            if regressors:
                out["motor"] = (name, regressors[name])
            out["levels"] = _level_candidates(cal, samples.field, table)
        for name in ("current_A", "throttle"):
            if "motor" not in out and name in table.columns:
                out["motor"] = (name, table[name].to_numpy(dtype=float))
        ned = self._ned(unit)
        yaw_source = self.figure_yaw_source(cal)
        if ned is not None and (samples.log_info.get("has_attitude") or yaw_source == "dcm"):
            try:  # the attitude the fit took (its yaw source, ``auto`` resolved), over the whole log
                chosen = flight_attitude(dataclasses.replace(samples, table=table.reset_index(drop=True)),
                                         AttitudeSpec(attitude_columns="yaw_deg,pitch_deg,roll_deg"), yaw_source)
            except TrimagInputError as exc:
                out["attitude_note"] = f"no expected field: {exc}"
            else:
                rows = chosen.samples.table.index.to_numpy()  # the rows with the chosen attitude
                expected = np.full_like(logged, np.nan)
                expected[rows] = body_field(chosen.rotation, ned)
                out["expected"] = expected
                down = np.full_like(logged, np.nan)
                down[rows] = body_field(chosen.rotation, np.array([0.0, 0.0, -1.0]))  # the specific force at rest
                yaw = np.full(len(t), np.nan)
                yaw[rows] = chosen.rotation.as_euler("ZYX", degrees=True)[:, 0]  # the attitude's yaw, as rotated
                decl = float(np.degrees(np.arctan2(ned[1], ned[0])))

                def heading_of(field_body: NDArray[np.float64]) -> NDArray[np.float64]:
                    heading = np.full(len(t), np.nan)
                    heading[rows] = tilt_compensated_heading(field_body[rows], down[rows], declination_deg=decl)
                    return np.asarray(heading_difference(heading, yaw), dtype=np.float64)

                for key in ("logged", "candidate"):
                    if key in out:
                        out[f"heading_{key}"] = heading_of(out[key])
                for level in out.get("levels", []):
                    level["heading"] = heading_of(level["field"])
                out["yaw_source"] = chosen.source
        if result is not None and result.rows:
            a, b = (int(x) for x in result.rows.split(":"))
            if self.table_input is not None:  # `--rows` counts the file's data rows: the kept rows' positions
                a, b = (int(v) for v in np.searchsorted(self.table_input.rows, [a, b]))
            fitted = np.zeros(len(t), dtype=bool)
            fitted[a:b] = True
            out["fitted_rows"] = fitted
        return out

    def statistics(self, judged: dict[str, Any]) -> dict[str, Any]:
        """Vector RMS against the expected field, on the fitted rows and on the held-out ones, of the log's
        calibration and the candidate."""
        stats: dict[str, Any] = {}
        if "expected" not in judged:
            return stats
        fitted = judged.get("fitted_rows", np.ones(len(judged["t"]), dtype=bool))
        for key in ("logged", "candidate"):
            if key not in judged:
                continue
            err = np.linalg.norm(judged[key] - judged["expected"], axis=1)
            for part, mask in (("fitted", fitted), ("held_out", ~fitted)):
                e = err[mask & np.isfinite(err)]
                stats[f"{key}_{part}_rms"] = float(np.sqrt(np.mean(e ** 2))) if len(e) else None
                stats[f"{part}_rows"] = len(e)
        levels = []
        for level in judged.get("levels", []):
            err = np.linalg.norm(level["field"] - judged["expected"], axis=1)
            row = {"label": level["label"], "chosen": level["chosen"]}
            for part, mask in (("fitted", fitted), ("held_out", ~fitted)):
                e = err[mask & np.isfinite(err)]
                row[f"{part}_rms"] = float(np.sqrt(np.mean(e ** 2))) if len(e) else None
            levels.append(row)
        if levels:
            stats["levels"] = levels
        return stats

    def compass_figures(self, number: int) -> dict[str, dict[str, Any]]:
        """The figures of one compass: ``field`` (X/Y/Z, expected against measured), ``magnitude`` (|B| with the
        motor channel beside), ``heading`` (the heading change against the attitude)."""
        j = self.judged(number)
        t, unit = j["t"], j["unit"]
        k = _shown(len(t))
        colours = {"expected": "#444444", "logged": "#d62728", "candidate": "#1f77b4"}
        names = {"expected": "expected (IGRF rotated by the attitude)", "logged": "the log's calibration"
                 if self.table_input is None else "the readings as recorded", "candidate": "this fit"}
        levels = j.get("levels", [])
        chosen = next((lv["label"] for lv in levels if lv["chosen"]), None)
        if chosen is not None:
            names["candidate"] = f"this fit: {chosen} (chosen)"
        others = [lv for lv in levels if not lv["chosen"]]  # each other candidate: in the legend, drawn on a click
        field_traces = []
        for axis, _letter in enumerate("XYZ"):
            for key in ("expected", "logged", "candidate"):
                if key in j:
                    field_traces.append(_line(t[k], j[key][k, axis], f"{names[key]}", xaxis="x",
                                              yaxis=f"y{axis + 1 if axis else ''}", legendgroup=key,
                                              showlegend=axis == 0, line={"width": 1, "color": colours[key]}))
            for i, lv in enumerate(others):
                field_traces.append(_line(t[k], lv["field"][k, axis], f"candidate: {lv['label']}", xaxis="x",
                                          yaxis=f"y{axis + 1 if axis else ''}", legendgroup=f"level{i}",
                                          showlegend=axis == 0, visible="legendonly",
                                          line={"width": 1, "color": _LEVEL_COLOURS[i % len(_LEVEL_COLOURS)]}))
        said = f"<br>expected: IGRF rotated by {j['yaw_source']}" if "yaw_source" in j else ""
        field_fig = _figure(field_traces, f"compass {number}: body field X / Y / Z ({unit}){said}", height=520,
                            grid={"rows": 3, "columns": 1, "pattern": "coupled"},
                            yaxis={"title": {"text": f"X ({unit})"}}, yaxis2={"title": {"text": f"Y ({unit})"}},
                            yaxis3={"title": {"text": f"Z ({unit})"}}, xaxis={"title": {"text": "time (s)"}})
        mag_traces = []
        for key in ("expected", "logged", "candidate"):
            if key in j:
                mag_traces.append(_line(t[k], np.linalg.norm(j[key][k], axis=1), f"|B| {names[key]}",
                                        line={"width": 1, "color": colours[key]}))
        for i, lv in enumerate(others):
            mag_traces.append(_line(t[k], np.linalg.norm(lv["field"][k], axis=1), f"|B| candidate: {lv['label']}",
                                    visible="legendonly",
                                    line={"width": 1, "color": _LEVEL_COLOURS[i % len(_LEVEL_COLOURS)]}))
        if "motor" in j:
            name, values = j["motor"]
            mag_traces.append(_line(t[k], values[k], name, yaxis="y2", line={"width": 1, "color": "#2ca02c"}))
        mag_fig = _figure(mag_traces, f"compass {number}: field length and the motor channel",
                          xaxis={"title": {"text": "time (s)"}}, yaxis={"title": {"text": f"|B| ({unit})"}},
                          yaxis2={"title": {"text": j["motor"][0] if "motor" in j else ""}, "overlaying": "y",
                                  "side": "right", "showgrid": False})
        head_traces = []
        for key in ("logged", "candidate"):
            if f"heading_{key}" in j:
                head_traces.append(_line(t[k], _unwrapped_breaks(j[f"heading_{key}"][k]),
                                         f"{names[key]} - logged yaw",
                                         line={"width": 1, "color": colours[key]}))
        if "heading_logged" in j and "heading_candidate" in j:
            from ..vehicle.heading import heading_difference

            change = heading_difference(j["heading_candidate"], j["heading_logged"])
            head_traces.append(_line(t[k], _unwrapped_breaks(change[k]),
                                     "heading change: this fit - the log's calibration",
                                     line={"width": 1, "color": "#9467bd", "dash": "dot"}))
            for i, lv in enumerate(others):
                if "heading" in lv:
                    change = heading_difference(lv["heading"], j["heading_logged"])
                    head_traces.append(_line(t[k], _unwrapped_breaks(change[k]),
                                             f"heading change: candidate {lv['label']} - the log's calibration",
                                             visible="legendonly", line={"width": 1, "dash": "dot",
                                                                         "color": _LEVEL_COLOURS[i % len(
                                                                             _LEVEL_COLOURS)]}))
        head_fig = _figure(head_traces, f"compass {number}: tilt-compensated heading against the attitude's yaw "
                           f"({j.get('yaw_source') or 'no attitude'})", xaxis={"title": {"text": "time (s)"}},
                           yaxis={"title": {"text": "deg"}})
        return {"field": field_fig, "magnitude": mag_fig, "heading": head_fig}

    def compass_result(self, number: int) -> dict[str, Any]:
        """One compass's verdict for the page: the level table, halves and heading checks, statistics, messages,
        the command line, and the figures."""
        result = self.results.get(number)
        out: dict[str, Any] = {"number": number}
        if result is not None:
            out.update(rows=result.rows, command=result.command, error=result.error, exit_code=result.exit_code,
                       messages=result.messages)
            cal = result.calibration
            if cal is not None:
                fw = cal.diagnostics.get("firmware") or {}
                out.update(level=fw.get("level"), levels=fw.get("levels"), halves=fw.get("halves"),
                           heading=fw.get("heading"), orientation=fw.get("orientation_decision"),
                           held=fw.get("held"), unit=fw.get("unit"), rms_before=fw.get("rms_before"),
                           rms_after=fw.get("rms_after"), warnings=cal.diagnostics.get("warnings", []),
                           parameters=_parameters(cal, self.target, number))
        judged = self.judged(number)
        out["attitude"] = judged.get("yaw_source") or judged.get("attitude_note")
        out["statistics"] = self.statistics(judged)
        out["verdict"] = _verdict(result, out["statistics"])
        out["figures"] = self.compass_figures(number)
        return _finite_or_none(out)

    # ------------------------------------------------------------------ downloads
    def download(self, what: str, compass: str = "all") -> tuple[str, str]:
        """``(file name, text)``: the parameter file (``what`` ``"ardupilot"``, ``"px4"`` or ``"qgc"``) of
        ``compass`` (a number, or ``"all"``: every compass fitted) exactly as ``trimag export`` writes it, or
        (``what="json"``) one compass's calibration JSON as ``trimag fit -o`` writes it."""
        from ..io.export_instances import export_instances

        fitted = {n: r.calibration for n, r in self.results.items() if r.calibration is not None
                  and (what == "json" or not isinstance(_parameters(r.calibration, self.target, n), str))}
        if not fitted:
            raise TrimagInputError("no compass has a calibration yet: fit first (or the data refused every compass)")
        if compass == "all":
            numbers = sorted(fitted)
        else:
            try:
                numbers = [int(compass)]
            except ValueError:
                raise TrimagInputError(f"`compass` is a compass number or 'all'; got {compass!r}") from None
            if numbers[0] not in fitted:
                raise TrimagInputError(f"compass {compass} has no calibration (not fitted, or refused)")
        stem = Path(self.path.name).stem
        if what == "json":
            if len(numbers) != 1:
                raise TrimagInputError("a calibration JSON holds one compass: give its number")
            return f"{stem}-compass{numbers[0]}.json", fitted[numbers[0]].to_json() + "\n"
        if what not in DOWNLOADS:
            raise TrimagInputError(f"download one of {', '.join([*DOWNLOADS, 'json'])}; got {what!r}")
        target, suffix = DOWNLOADS[what]
        exp = export_instances([(fitted[n], n) for n in numbers], target)
        which = "all" if len(numbers) > 1 else f"compass{numbers[0]}"
        return f"{stem}-{which}{suffix}", exp.text


#: The usual names of a table's attitude columns (yaw, pitch, roll in degrees) and time column (s), compared in
#: lower case with a unit in brackets dropped (``Yaw (deg)`` is ``yaw``).
ATTITUDE_NAMES = (("yaw_deg", "pitch_deg", "roll_deg"), ("yaw", "pitch", "roll"), ("heading", "pitch", "roll"))
TIME_NAMES = ("time_s", "time", "t", "timestamp_s", "seconds", "time_sec")


@dataclass
class TableInput:
    """A table reviewed as a one-compass flight: how it is read (the ``trimag fit`` flags), the rows kept, the
    flight built of its columns, and what it cannot give."""

    log: Any
    samples: Any
    rows: NDArray[np.int64]
    units: str | None
    columns: str | None
    attitude_columns: str | None
    notes: list[str] = field(default_factory=list)


def _read_table(path: Path, fmt: str | None, units: str | None, columns: str | None, attitude_columns: str | None,
                time_column: str | None) -> TableInput:
    """A table ``trimag fit`` reads, with its attitude (``attitude_columns`` or the usual names), time (``time_column``
    or the usual names; else the row number) and motor columns, as a :class:`~trimag.io.logs.VehicleLog` of one
    compass (the readings as recorded: no calibration undone) and the :class:`~trimag.io.Samples` the figures use."""
    from ..io import read_samples
    from ..io.logs.base import Channel, MagnetometerStream, VehicleLog
    from ..units import normalise_unit
    from ._firmware import MOTOR_COLUMN_NAMES, _plain_name

    samples = read_samples(path, fmt=fmt, columns=columns)
    table = samples.table
    plain = {_plain_name(c): str(c) for c in reversed(list(table.columns))}
    notes: list[str] = []

    def given(names: str, flag: str) -> list[str]:
        out = [n.strip() for n in names.split(",")]
        missing = [n for n in out if n not in table.columns]
        if missing:
            raise TrimagInputError(f"{path}: no column {missing[0]!r} (named by {flag}); the columns are "
                                   f"{', '.join(map(str, table.columns))}")
        return out

    if attitude_columns:
        att = given(attitude_columns, "--attitude-columns")
        if len(att) != 3:
            raise TrimagInputError(f"--attitude-columns takes YAW,PITCH,ROLL; got {attitude_columns!r}")
    else:
        att = next(([plain[n] for n in names] for names in ATTITUDE_NAMES if all(n in plain for n in names)), [])
    if time_column:
        time_name: str | None = given(time_column, "--time-column")[0]
    else:
        time_name = next((plain[n] for n in TIME_NAMES if n in plain), None)
    unit = normalise_unit(units) if units else "unknown"
    if unit == "unknown":
        notes.append("the table's unit is not given: the firmware's parameters need it (--units mG, G, uT or nT)")
    n = len(table)
    if time_name is not None:
        t = table[time_name].to_numpy(dtype=float)
        if not (np.isfinite(t).all() and np.all(np.diff(t) >= 0)):
            raise TrimagInputError(f"{path}: the time column {time_name!r} must be finite and not go back (seconds); "
                                   "name another with --time-column")
    else:
        t = np.arange(n, dtype=float)
        notes.append("no time column (time_s, time, t, ...; --time-column NAME): the time axis is the row number")
    field_ = np.asarray(samples.field, dtype=np.float64)
    name = ",".join(map(str, samples.columns))
    mag = MagnetometerStream(name, 0, t, field_, field_, unit,
                             ["a table: no onboard calibration to undo (the readings as recorded)"])
    log = VehicleLog(str(path), "table", [mag])
    extra: dict[str, Any] = {"time_s": t}
    extra.update({f"mag_logged_{a}": field_[:, k] for k, a in enumerate("xyz")})
    if att:
        angles = table[att].to_numpy(dtype=float)
        log.attitude = Channel(t, angles, "deg", f"the table's {','.join(att)}")
        extra.update({"yaw_deg": np.mod(angles[:, 0], 360.0), "pitch_deg": angles[:, 1], "roll_deg": angles[:, 2]})
    for kind, own in (("current", "current_A"), ("throttle", "throttle")):
        col = next((plain[n] for n in MOTOR_COLUMN_NAMES[kind] if n in plain), None)
        if col is not None:
            log.channels[own] = Channel(t, table[col].to_numpy(dtype=float), "A" if kind == "current" else "", col)
            extra.setdefault(own, table[col].to_numpy(dtype=float))
    shown = table.drop(columns=[c for c in extra if c in table.columns]).assign(**extra)
    info: dict[str, Any] = {"unit": unit, "has_attitude": bool(att),
                            "attitude_source": log.attitude.source if log.attitude is not None else None,
            "parameters": {}, "format": "table"}
    kept = dataclasses.replace(samples, table=shown, log_info=info)
    return TableInput(log, kept, np.asarray(table.index, dtype=np.int64), units, columns,
                      ",".join(att) if att else None, notes)


#: The colours of the candidates the fit did not choose (the chosen one is "this fit", blue).
_LEVEL_COLOURS = ("#ff7f0e", "#17becf", "#bcbd22", "#8c564b", "#e377c2", "#7f7f7f", "#2ca02c", "#9467bd")


def _level_candidates(cal: Calibration, raw: NDArray[np.float64], table: Any) -> list[dict[str, Any]]:
    """Each level's candidate of the fit (a row of ``diagnostics["firmware"]["levels"]``): its label (level and
    motor term), whether it was chosen, and the field it makes of ``raw`` (:func:`trimag.vehicle.firmware.
    candidate_field`); a candidate whose motor channel the table lacks is left out."""
    from ..vehicle.firmware import candidate_field

    fw = cal.diagnostics.get("firmware") or {}
    chosen_channel = fw.get("motor_channel")
    out = []
    for row in fw.get("levels") or []:
        spec = row.get("compass")
        if not spec:  # a calibration written before the level table held each candidate's parameters
            continue
        kind = spec.get("motor_type")
        column = None
        if kind is not None:
            column = chosen_channel if chosen_channel and spec.get("motor_type") == fw.get("motor_type") else \
                {"current": "current_A", "throttle": "throttle"}.get(kind)
            if column not in table.columns:
                continue
        values = None if column is None else table[column].to_numpy(dtype=float)
        label = str(row["level"]) + (f" + {row['motor']}" if row.get("motor") else "")
        out.append({"label": label, "chosen": bool(row.get("chosen")),
                    "field": candidate_field(spec, raw, cal.units, motor_values=values,
                                             input_orientation=fw.get("input_orientation"))})
    return out


def _parameters(cal: Calibration, target: str, number: int) -> dict[str, float] | str:
    """The parameters ``trimag export`` writes for ``cal`` (or why it will not)."""
    from ..io.export import export_calibration

    try:
        return export_calibration(cal, target, instance=number - 1).parameters
    except TrimagInputError as exc:
        return f"not exportable: {exc}"


def _verdict(result: CompassResult | None, stats: dict[str, Any]) -> str:
    """One line: what to do with this compass."""
    if result is None:
        return "not fitted yet"
    if result.calibration is None:  # exit 2: something the user gives is missing; else the data refused one
        return f"not fitted: {result.error}" if result.exit_code == 2 else f"keep the log's calibration: {result.error}"
    cal = result.calibration
    fw = cal.diagnostics.get("firmware") or {}
    unit = fw.get("unit", cal.units)
    held = [stats.get("candidate_held_out_rms"), stats.get("logged_held_out_rms")]
    text = f"level {fw.get('level')}: field RMS {fw.get('rms_before', float('nan')):.4g} -> " \
           f"{fw.get('rms_after', float('nan')):.4g} {unit} on the fitted rows"
    if held[0] is not None and held[1] is not None:
        better = "better" if held[0] < held[1] else "WORSE"
        text += f"; held-out rows: {held[1]:.4g} (log) -> {held[0]:.4g} ({better})"
    warnings = cal.diagnostics.get("warnings") or []
    return text + (f"; {len(warnings)} warning(s)" if warnings else "; no warnings")


def report_html(review: FlightLog, numbers: Sequence[int] | None = None, title: str | None = None) -> str:
    """The review's figures and tables as one self-contained HTML file (Plotly inline; nothing fetched)."""
    import html as _html

    js = plotly_js().decode("utf-8")
    numbers = sorted(review.results) if numbers is None else list(numbers)
    choice = review.choice
    overview = review.overview()
    figures: list[tuple[str, dict[str, Any]]] = [("flight", review.flight_figure(choice.get("start_s"),
                                                                                  choice.get("stop_s")))]
    sections = []
    for n in numbers:
        r = review.compass_result(n)
        for name, fig in r["figures"].items():
            figures.append((f"compass{n}-{name}", fig))
        vector = {v["label"]: v for v in r["statistics"].get("levels") or []}

        def rms(row: dict[str, Any], part: str, vector: dict[str, Any] = vector) -> str:
            value = vector.get(str(row["level"]) + (f" + {row['motor']}" if row.get("motor") else ""), {}).get(part)
            return "-" if value is None else f"{value:.4g}"

        rows = "".join(
            f"<tr><td>{row['level']}</td><td>{row['motor'] or '-'}</td><td>{row['n_params']}</td>"
            f"<td>{row['rms']:.4g}</td><td>{row['heldout_rms']:.4g}</td>"
            f"<td>{'all' if row['identified'] else row.get('n_identified')}</td>"
            f"<td>{'ok' if row['within_limits'] else 'outside'}</td><td>{rms(row, 'fitted_rms')}</td>"
            f"<td>{rms(row, 'held_out_rms')}</td><td>{'&larr;' if row['chosen'] else ''}</td></tr>"
            for row in r.get("levels") or [])
        table = (f"<table><tr><th>level</th><th>motor</th><th>params</th><th>rms</th><th>held-out</th>"
                 f"<th>identified</th><th>limits</th><th>vector RMS, fitted rows</th><th>held-out rows</th>"
                 f"<th>chosen</th></tr>{rows}</table>" if rows else "")
        sections.append(
            f"<h2>compass {n}</h2><p class='verdict'>{_html.escape(str(r['verdict']))}</p>"
            + (f"<p class='attitude'>attitude of the figures (the fit's): {_html.escape(str(r['attitude']))}</p>"
               if r.get("attitude") else "") + f"{table}"
            f"<pre>{_html.escape(chr(10).join(r.get('messages') or []))}</pre>"
            + "".join(f"<div class='fig' id='compass{n}-{name}'></div>" for name in r["figures"]))
    specs = json.dumps({name: _finite_or_none(fig) for name, fig in figures}, allow_nan=False).replace("</", "<\\/")
    compass_rows = "".join(
        f"<tr><td>{c['number']}</td><td>{_html.escape(str(c['name']))}</td><td>{c['device_id'] or '-'}</td>"
        f"<td>{c['n_samples']}</td><td>{c['rate_hz']}</td><td>{c['n_gaps']}</td><td>{c['unit']}</td></tr>"
        for c in overview["compasses"])
    heading = _html.escape(title or f"trimag review of {review.path.name}")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{heading}</title>
<style>body{{font-family:sans-serif;margin:1em 2em}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}} .fig{{width:100%;min-height:320px}}
pre{{white-space:pre-wrap;font-size:85%}}</style>
<script>{js}</script></head><body data-figures="{len(figures)}">
<h1>{heading}</h1>
<p>{_html.escape(str(overview['format']))} {_html.escape(str(overview['vehicle'] or ''))}; target {review.target};
fitted {choice.get('start_s', 0):.1f}..{choice.get('stop_s', 0):.1f} s, level {choice.get('level')}, motor
{choice.get('motor')}, yaw source {choice.get('yaw_source') or 'auto'}</p>
{''.join(f"<p class='unavailable'>{_html.escape(line)}</p>" for line in overview['unavailable'])}
<table><tr><th>compass</th><th>name</th><th>device id</th><th>samples</th><th>rate (Hz)</th><th>gaps</th>
<th>unit</th></tr>{compass_rows}</table>
<div class='fig' id='flight'></div>
{''.join(sections)}
<script id="figures" type="application/json">{specs}</script>
<script>
const figs = JSON.parse(document.getElementById('figures').textContent);
let drawn = 0;
for (const [id, fig] of Object.entries(figs)) {{
  const el = document.getElementById(id);
  if (el) {{ Plotly.newPlot(el, fig.data, fig.layout, {{displaylogo: false}}); drawn += 1; }}
}}
document.body.dataset.drawn = String(drawn);
</script></body></html>
"""
