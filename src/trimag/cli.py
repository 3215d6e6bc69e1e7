"""The ``trimag`` command: parsing and printing only; the work is done in :mod:`trimag.app`.

Exit codes (docs/cli.md): 0 success; 2 bad input or usage; 3 the data cannot identify the requested model;
1 internal error. Errors are one line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import itertools
import json
import re
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from ._core.chunks import DEFAULT_CHUNK_ROWS
from ._version import __version__
from .errors import IdentifiabilityError, TrimagError, TrimagInputError
from .units import unit_words

if TYPE_CHECKING:
    from .app.requests import EvaluateRequest

_R = TypeVar("_R")

__all__ = ["build_parser", "main"]

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_IDENTIFIABILITY, EXIT_POLICY = 0, 1, 2, 3, 4


class _Terminated(BaseException):
    """Raised by the SIGTERM handler so that ``finally`` and cleanup code run (no stray temporary files)."""


#: A word that is a number (or a list of numbers, a place, a range) with a leading minus sign: ``-33.9,151.2,0,...``,
#: ``-.5``, ``-1e3``, ``-20:30``. argparse takes such a word for an option unless it is one plain number.
_NEGATIVE_VALUE = re.compile(r"^-\.?\d")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # one line, exit 2
        sys.stderr.write(f"trimag: error: {_printable(message, lines=False)} (see `{self.prog} --help`)\n")
        raise SystemExit(EXIT_INPUT)

    def parse_known_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                         namespace: argparse.Namespace | None = None) -> tuple[argparse.Namespace, list[str]]:
        """argparse's parse, with every option that takes one value accepting a value with a leading minus sign
        given as the next word (``--igrf -33.9,151.2,0,2024-01-01``, ``--background-ned -200,10,-430``)."""
        words = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(self._joined_negative_values(words), namespace)

    def _joined_negative_values(self, words: list[str]) -> list[str]:
        """``words`` with ``--option -NUMBER...`` joined into ``--option=-NUMBER...`` where ``--option`` (or an
        unambiguous prefix of it) is one of this parser's options taking exactly one value; words after ``--`` and
        after a subcommand's name (its own parser does the same) are left as they are."""
        takes_one = {s: a for a in self._actions for s in a.option_strings if a.nargs is None}
        out: list[str] = []
        k = 0
        while k < len(words):
            word = words[k]
            if word == "--" or word in self._subcommand_names():
                return out + words[k:]
            option = takes_one.get(word) or self._unique_prefix(word, takes_one)
            if option is not None and k + 1 < len(words) and _NEGATIVE_VALUE.match(words[k + 1]):
                out.append(f"{word}={words[k + 1]}")
                k += 2
                continue
            out.append(word)
            k += 1
        return out

    def _subcommand_names(self) -> set[str]:
        return {name for a in self._actions if isinstance(a, argparse._SubParsersAction) for name in a.choices}

    def _unique_prefix(self, word: str, options: dict[str, argparse.Action]) -> argparse.Action | None:
        """The option that ``word`` abbreviates (argparse's ``allow_abbrev``), when exactly one does."""
        if not (word.startswith("--") and len(word) > 2 and self.allow_abbrev):
            return None
        matches = {a for s, a in options.items() if s.startswith(word)}
        return matches.pop() if len(matches) == 1 else None


#: Python argument name -> the command line's flag (filled from the parser by :func:`main`): the library's messages
#: name Python arguments in backticks (`` `columns` ``, `` `units=uT` ``, `` `option balance=never` ``) and the
#: command line says them as flags (``--columns``, ``--units uT``, ``--option balance=never``).
_FLAGS: dict[str, str] = {"options": "--option", "rate_hz": "--rate"}
_ARGUMENT = re.compile(r"`([a-z_]+)(?:([= ])([^`]*))?`")


def _as_flags(msg: str) -> str:
    """``msg`` with every `` `argument` `` (or `` `argument=value` ``) the command line has a flag for said as that
    flag (``--flag`` or ``--flag value``); other backticked text is left as it is."""

    def flag(m: re.Match[str]) -> str:
        name, value = m.group(1), m.group(3)
        if name not in _FLAGS:
            return m.group(0)
        return _FLAGS[name] if value is None else f"{_FLAGS[name]} {value}"

    return _ARGUMENT.sub(flag, msg)


def _register_flags(parser: argparse.ArgumentParser) -> None:
    """Fill :data:`_FLAGS` from every (sub)command's options: dest -> its long flag."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _register_flags(sub)
        longs = [o for o in action.option_strings if o.startswith("--")]
        if longs and action.dest not in ("help", "version"):
            _FLAGS.setdefault(action.dest, longs[0])


#: what a terminal obeys rather than shows: C0 controls but tab and newline, DEL, C1 controls (``\x9b`` is CSI),
#: and the bidirectional overrides that reorder what is shown
_CONTROL = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]")


def _printable(text: str, *, lines: bool = True) -> str:
    """``text`` with every control character escaped (``\\x1b``; issue 41, item 13: escape sequences in a CSV
    header or a calibration file reached the terminal raw); ``lines=False`` escapes newlines too (one line)."""
    text = _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}" if ord(m.group()) < 0x100 else
                        f"\\u{ord(m.group()):04x}", text)
    return text if lines else text.replace("\n", "\\n")


#: the longest line trimag prints for one message (two compasses' refusals take ~1 700 characters); a longer one (a list
#: of 100 000 names) is cut in its middle
MAX_MESSAGE_CHARS = 4000


def _short(text: str) -> str:
    """``text`` within :data:`MAX_MESSAGE_CHARS`, its middle cut and counted (issue 41, item 14: 100 000 regressors
    made a 1.58 MB error line); the start (what is wrong) and the end (what to do) are kept."""
    if len(text) <= MAX_MESSAGE_CHARS:
        return text
    head, tail = MAX_MESSAGE_CHARS * 2 // 3, MAX_MESSAGE_CHARS // 4
    return f"{text[:head]} ... [{len(text) - head - tail} more characters] ... {text[-tail:]}"


#: the longest line of a refusal's detail (docs/cli.md, "Errors"); a longer one is wrapped
MAX_DETAIL_CHARS = 120


def _err(msg: str, details: Sequence[str] = ()) -> None:
    """``msg`` as one line (``trimag: ...``), then each of ``details`` indented by two spaces, wrapped within
    :data:`MAX_DETAIL_CHARS` (its continuation lines by four)."""
    import textwrap

    lines = [f"trimag: {_short(_printable(_as_flags(msg), lines=False))}"]
    for detail in details:
        lines += textwrap.wrap(_short(_printable(_as_flags(detail), lines=False)), width=MAX_DETAIL_CHARS,
                               initial_indent="  ", subsequent_indent="    ", break_on_hyphens=False)
    sys.stderr.write("\n".join(lines) + "\n")


def _say(msg: str, args: argparse.Namespace) -> None:
    """Human-readable progress/info goes to stderr when --json (or ``-o -``) reserves stdout for the output."""
    stream = sys.stderr if getattr(args, "json", False) or getattr(args, "out", None) == "-" else sys.stdout
    if not getattr(args, "quiet", False):
        stream.write(_printable(_as_flags(msg)) + "\n")


def _say_sensor(result: dict[str, Any], args: argparse.Namespace) -> None:
    """The sensor a command read for its calibration (``sensor: ...``; a warning when it is another compass's)."""
    for line in (result.get("sensor") or "").splitlines():
        _err(line) if line.startswith("warning:") else _say(line, args)


def _add_data_options(p: argparse.ArgumentParser, *, selection: bool = True) -> None:
    g = p.add_argument_group("data")
    g.add_argument("--format", dest="fmt",
                   choices=["csv", "txt", "xyz", "npz", "mat", "parquet", "dataflash", "tlog", "ulog", "px4log",
                            "rosbag", "phone"],
                   help="file format (default: from the extension; .bin/.tlog/.ulg/.px4log are autopilot logs)")
    g.add_argument("--sensor", metavar="N|NAME",
                   help="autopilot logs: which magnetometer: its number from 1, as the firmware's parameters count "
                        "(COMPASS_OFS = 1, COMPASS_OFS2 = 2; CAL_MAG0 = 1), its name or device id; fit: `all` fits "
                        "every one (default: the one with the most samples)")
    g.add_argument("--columns", help="x,y,z columns: header names or 0-based indices (default: recognised)")
    g.add_argument("--var", help="variable name inside an NPZ or MAT file")
    g.add_argument("--units", help="unit of the data: nT, uT, G, mG, counts (recorded in every output)")
    if selection:
        g.add_argument("--rows", help="use only rows START:STOP (0-based data rows, STOP excluded)")
        g.add_argument("--where", help="use only rows where COLUMN==VALUE (or COLUMN!=VALUE)")
    g.add_argument("--strict", action="store_true",
                   help="refuse rows with missing/non-numeric/NaN values instead of dropping and counting them")
    g.add_argument("--max-fields", type=int, metavar="N",
                   help="refuse a text line of more than N fields (default 10000; docs/cli.md, 'Limits')")
    g.add_argument("--max-decompressed-mb", type=float, metavar="MB",
                   help="refuse compressed input that expands past MB megabytes (default 1024)")


def _add_reference_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("field reference (at most one)")
    g.add_argument("--reference", metavar="F|mean",
                   help="field magnitude in the data's unit, or 'mean' (unknown; default)")
    g.add_argument("--igrf", dest="igrf_spec", metavar="LAT,LON,ALT_M,YYYY-MM-DD",
                   help="IGRF-14 field at this place and date (total field; vector for interference12)")
    g.add_argument("--reference-column", metavar="NAME", help="per-sample magnitude from this column")


def _add_attitude_options(p: argparse.ArgumentParser, *, fit: bool = True) -> None:
    g = p.add_argument_group("attitudes and background (model interference12)")
    g.add_argument("--attitude-columns", metavar="YAW,PITCH,ROLL", help="Euler angles in degrees (Z-Y-X, NED)")
    g.add_argument("--quaternion-columns", metavar="W,X,Y,Z", help="attitude quaternion columns")
    g.add_argument("--quaternion-order", choices=["wxyz", "xyzw"], default="wxyz",
                   help="scalar first (wxyz, default) or last (xyzw)")
    g.add_argument("--quaternion-frame", choices=["ned", "enu"], default="ned",
                   help="navigation frame the quaternions refer to")
    g.add_argument("--background-ned", metavar="N,E,D", help="background field vector in the data's unit")
    g.add_argument("--background-columns", metavar="N,E,D",
                   help="per-sample background field (NED, the data's unit) from these columns, e.g. IGRF along a "
                        "survey line or a reference vector magnetometer")
    g.add_argument("--igrf-columns", metavar="LAT,LON,ALT_M,YYYY-MM-DD",
                   help="per-sample background: IGRF-14 at each row's position (latitude, longitude, altitude columns) "
                        "on this date")
    if fit:
        g.add_argument("--background-run", metavar="FILE", help="iron-free run at the same attitudes")
    g.add_argument("--attitude-file", metavar="FILE",
                   help="attitudes from this file (its --attitude-columns or --quaternion-columns), with its own "
                        "time column, interpolated (slerp) to the magnetometer's --time-column; "
                        "fit: --option estimate_lag=true estimates the lag between the two; evaluate: the "
                        "calibration's lag is applied (docs/vehicle.md)")
    g.add_argument("--attitude-time-column", metavar="NAME",
                   help="time column (s) of --attitude-file (default: the same name as --time-column)")
    g.add_argument("--position-columns", metavar="X,Y,Z",
                   help="the sensor's positions (m, the attitudes' frame; in the data or in --attitude-file): fit: "
                        "the background's gradient across the room (5 terms); evaluate: default the fitted columns "
                        "(docs/vehicle.md)")


def _add_tolles_lawson_options(p: argparse.ArgumentParser, *, fit: bool = True) -> None:
    g = p.add_argument_group("aircraft compensation (model tolles-lawson; docs/method-tolles-lawson.md)")
    g.add_argument("--scalar-column", metavar="S", help="scalar magnetometer column to compensate (nT)")
    _add_time_options(g)
    g.add_argument("--segments", metavar="T0:T1[,T0:T1...]", help="time ranges (s) of calibration manoeuvres")
    if fit:
        g.add_argument("--tl-attitude-columns", metavar="YAW,PITCH,ROLL",
                       help="attitude columns (degrees), only to report the manoeuvre content")


def _add_time_options(g: Any) -> None:
    """``--time-column`` and ``--rate`` (Tolles-Lawson, eddy-current terms, attitudes from a second file)."""
    g.add_argument("--time-column", metavar="T",
                   help="time column, seconds (gives the sample rate; with --attitude-file the magnetometer's time)")
    g.add_argument("--rate", type=float, metavar="HZ", help="sample rate, Hz (when there is no time column)")


def _add_fit_steps(p: argparse.ArgumentParser) -> None:
    """The options of ``fit`` (and ``batch``) that add steps to the fit: regressor terms, a quick recalibration,
    the alignment to the accelerometer."""
    p.add_argument("--regressors", metavar="COL[,COL...]",
                   help="columns the offset depends on linearly (current, throttle, temperature, ...): "
                        "b = b0 + sum k_j (u_j - mean_j), fitted jointly and ranked (models ellipsoid, interference12; "
                        "docs/vehicle.md); apply and evaluate read the same columns")
    p.add_argument("--prior", metavar="CAL.json",
                   help="quick recalibration: keep this earlier calibration's matrix (and regressor terms) and refit "
                        "only its offset, e.g. from a few headings at level (needs the field magnitude; "
                        "docs/vehicle.md)")
    p.add_argument("--target", choices=["ardupilot", "px4"],
                   help="fit exactly the parameters this autopilot loads, within its limits: orientation, offsets, "
                        "scale and symmetric matrix, motor term (docs/autopilot.md)")
    p.add_argument("--level", choices=["auto", "offsets", "scale", "diagonal", "full"],
                   help="--target's level: offsets < + one scale < + diagonal < + off-diagonal (full); auto (default) "
                        "takes the simplest the data identify, by held-out RMS")
    p.add_argument("--motor", metavar="auto|none|current|throttle|current=COLUMN|throttle=COLUMN",
                   help="--target's motor term (COMPASS_MOT, CAL_MAGn_xCOMP) on the logged current or throttle; auto "
                        "(default) fits it when it improves the held-out RMS; a table's current or throttle column is "
                        "found by its usual names (current, curr, battery_current, throttle, thr, ...) or named: "
                        "current=COLUMN")
    p.add_argument("--yaw-source", choices=["auto", "attitude", "dcm", "gsf", "gps"],
                   help="--target's attitude for a log: auto (default: a GPS heading, else the EKF-GSF yaw XKY0, else "
                        "the log's attitude), attitude (the log's EKF attitude ATT; heading-free where its EKF used "
                        "this compass), dcm (roll, pitch and yaw of ArduPilot's DCM, AHR2; heading-free), gsf, gps")
    g = p.add_argument_group("vehicles that cannot be tumbled (boats, rovers, large multicopters; docs/autopilot.md)")
    g.add_argument("--level-turn", action="store_true",
                   help="the vehicle turned but did not tilt: fit the horizontal offsets and scales from its turns, "
                        "the vertical offset from the field's magnitude and inclination (--igrf, or the log's GPS), "
                        "the vertical scale held")
    g.add_argument("--heading", type=float, metavar="DEG",
                   help="the vehicle's true heading while it stood still (degrees from true north): the offsets from "
                        "the field's vector at that attitude, as ArduPilot's MAG_CAL_YAW (needs --igrf or the log's "
                        "GPS; roll and pitch from the log's attitude or --attitude-columns, else level)")
    g.add_argument("--heading-column", metavar="NAME",
                   help="as --heading, with the true heading of each sample from this column (a survey, a GPS "
                        "course)")
    p.add_argument("--accel-columns", metavar="AX,AY,AZ",
                   help="accelerometer columns (specific force, at rest or moving slowly): also estimate the rotation "
                        "from the corrected magnetometer to the accelerometer frame and the dip, with uncertainties, "
                        "and the nearest autopilot board rotation (docs/vehicle.md)")


def _add_gyro_options(p: argparse.ArgumentParser) -> None:
    """The gyroscope of the gyro-aided fit (``--method gyro``, docs/method-gyro.md)."""
    g = p.add_argument_group("gyroscope (the gyro-aided fit of the ellipsoid; docs/method-gyro.md)")
    g.add_argument("--gyro-columns", metavar="GX,GY,GZ|VARIABLE",
                   help="angular rate columns: in the same rows (with --time-column or --rate), or in --gyro-file "
                        "(default x,y,z there); of an NPZ or MAT file, the variable of the same rows (imu_gyr); "
                        "implies --method gyro")
    g.add_argument("--gyro-unit", choices=["rad/s", "deg/s"],
                   help="unit of the rate (default: deg/s when the column names say deg or dps, else rad/s)")
    g.add_argument("--gyro-file", metavar="FILE",
                   help="the gyroscope in a file of its own, with its own clock: the lag between the two is fitted "
                        "(--option max_lag=S, default 0.5; --option estimate_lag=false to hold it at 0); of an NPZ "
                        "or MAT file, --gyro-columns names its variable")
    g.add_argument("--gyro-time-column", metavar="NAME",
                   help="time column (s) of --gyro-file (default: --time-column); of an NPZ or MAT file, its time "
                        "variable (default: its sampling_rate variable, from 0 s)")


def _add_model_options(p: argparse.ArgumentParser, model_help: str) -> None:
    p.add_argument("--model", default="ellipsoid", help=model_help)
    p.add_argument("--method", help="identification method (default: the model's default)")
    p.add_argument("--option", action="append", metavar="KEY=VALUE", help="method option (repeatable)")


def _add_output_options(
    p: argparse.ArgumentParser, *, json_help: str | None = "print one JSON object on stdout",
    quiet_help: str | None = None,
) -> None:
    """``--json`` (unless ``json_help`` is None) and ``-q/--quiet``, the last options of every subcommand."""
    if json_help is not None:
        p.add_argument("--json", action="store_true", help=json_help)
    p.add_argument("-q", "--quiet", action="store_true", help=quiet_help)


def _add_chunk_rows(p: argparse.ArgumentParser) -> None:
    p.add_argument("--chunk-rows", type=int, default=DEFAULT_CHUNK_ROWS, help="rows per chunk (memory bound)")


def _add_fit(sub: Any) -> None:
    p = sub.add_parser("fit", help="fit a calibration to a log", description="Fit a calibration to a log.")
    p.add_argument("data", metavar="DATA")
    _add_data_options(p)
    _add_model_options(p, "error model: ellipsoid, ortho-gain, ortho-gain-bias, scalar9, interference12, zhang-cheng, "
                          "tolles-lawson")
    _add_reference_options(p)
    _add_attitude_options(p)
    _add_tolles_lawson_options(p)
    _add_fit_steps(p)
    g = p.add_argument_group("all compasses of a log (--sensor all; docs/autopilot.md)")
    g.add_argument("--export-to", choices=["ardupilot", "px4", "qgc"],
                   help="with --sensor all: write every compass fitted to one parameter file (--export-out) of "
                        "this firmware")
    g.add_argument("--export-out", metavar="FILE", help="with --sensor all: the parameter file (e.g. compass.param)")
    g.add_argument("--force", action="store_true",
                   help="with --export-to: write the parameters even of a compass --policy rejected or whose unit "
                        "its fit doubted")
    p.add_argument("--deviation-card", metavar="CARD.png",
                   help="with --level-turn or --heading: write the deviation card (heading error against heading, "
                        "before and after) as a figure; its table is printed")
    _add_gyro_options(p)
    p.add_argument("--policy", metavar="FILE.toml|default",
                   help="acceptance limits ([limits] table; docs/cli.md); a failed rule exits 4")
    p.add_argument("-o", "--out", metavar="CAL.json", help="write the calibration here")
    p.add_argument("--report", metavar="REPORT.png",
                   help="write the fit report figure here (.png, .pdf, .svg; .html: a flight's firmware fit as one "
                        "self-contained page, docs/review.md)")
    _add_output_options(p, quiet_help="print only errors (and --json output)")


def _add_apply(sub: Any) -> None:
    p = sub.add_parser("apply", help="correct a log with a calibration",
                       description="Correct every row of a log; all input columns are kept and x/y/z_cal appended.")
    p.add_argument("calibration", metavar="CAL.json")
    p.add_argument("data", metavar="DATA")
    p.add_argument("-o", "--out", metavar="OUT",
                   help="output file (.csv, .parquet or .npz; - for CSV on standard output; default: DATA's name "
                        "with -corrected.csv, beside it, never over an existing file)")
    _add_data_options(p, selection=False)
    _add_chunk_rows(p)
    p.add_argument("--scalar-column", metavar="S", help="scalar column (Tolles–Lawson files; default: as fitted)")
    _add_output_options(p)


def _add_export(sub: Any) -> None:
    p = sub.add_parser("export", help="write a calibration as firmware parameters",
                       description="Write a calibration in a firmware's or tool's own convention "
                                   "(docs/autopilot.md).")
    p.add_argument("calibration", metavar="CAL.json")
    p.add_argument("--to", required=True, dest="target",
                   choices=["ardupilot", "px4", "qgc", "c-header", "json", "ros-yaml", "matlab"],
                   help="qgc: PX4's parameters as QGroundControl's parameter file (Load from file), CAL_MAGn_ID from "
                        "the log's device id")
    p.add_argument("--instance", type=int,
                   help="compass / magnetometer number, 1-based (ArduPilot COMPASS_OFS, OFS2, OFS3; PX4 CAL_MAG0..); "
                        "default: the compass the calibration was fitted to (fit --sensor N), else 1")
    p.add_argument("-o", "--out", metavar="FILE",
                   help="output file (- for standard output; default: CAL.json's name with the target's extension, "
                        "e.g. cal.param, beside it, never over an existing file)")
    p.add_argument("--force", action="store_true",
                   help="write the parameters even of a calibration its fit rejected (--policy) or whose unit the "
                        "fit doubted")
    _add_output_options(p)


#: the extension of ``trimag export``'s default output, per target (issue 42)
_EXPORT_SUFFIXES = {"ardupilot": ".param", "px4": ".params", "qgc": "-qgc.params", "c-header": ".h",
                    "json": "-export.json", "ros-yaml": ".yaml", "matlab": ".m"}


def _default_out(args: argparse.Namespace, source: str, tail: str) -> None:
    """Without ``-o``: the output beside ``source``, named from it (``source``'s stem + ``tail``), said on stderr
    once it is written (:func:`main`; a refusal names no file it never wrote); an existing file of that name is never
    replaced (exit 2)."""
    if args.out is not None:
        return
    target = Path(source).with_name(Path(source).stem + tail)
    if target.exists() or target.is_symlink():
        raise TrimagInputError(f"no -o given and {target} (the default name) already exists: name the output with "
                               "-o FILE, or -o - for standard output")
    args.out = str(target)
    args.default_out = str(target)


def _add_evaluate(sub: Any) -> None:
    p = sub.add_parser("evaluate", help="statistics of a calibration on a log",
                       description="RMS and amplitude of |B| - F before and after a calibration.")
    p.add_argument("calibration", metavar="CAL.json")
    p.add_argument("data", metavar="DATA")
    _add_data_options(p)
    _add_reference_options(p)
    _add_attitude_options(p, fit=False)
    _add_tolles_lawson_options(p, fit=False)
    g = p.add_argument_group("heading (tilt-compensated, against a reference; docs/vehicle.md)")
    g.add_argument("--accel-columns", metavar="AX,AY,AZ",
                   help="accelerometer columns: evaluate the true heading against --heading-column or the yaw of "
                        "--attitude-columns")
    g.add_argument("--heading-column", metavar="H", help="reference heading, degrees clockwise from true north")
    g.add_argument("--declination", metavar="DEG",
                   help="magnetic declination, degrees east (instead of --igrf; default 0: magnetic heading)")
    _add_chunk_rows(p)
    _add_output_options(p)


def _add_simulate(sub: Any) -> None:
    p = sub.add_parser("simulate", help="simulate a sensor with known errors",
                       description="Write a simulated log (x,y,z,qw,qx,qy,qz) for a model with given parameters.")
    p.add_argument("--model", required=True)
    p.add_argument("--params", required=True, metavar="PARAMS.json", help="JSON object {name: value}")
    p.add_argument("--n", type=int, required=True, help="number of samples")
    p.add_argument("--noise", type=float, default=0.0, help="noise standard deviation per axis (field units)")
    p.add_argument("--field", type=float, default=1.0, help="field magnitude (default 1)")
    p.add_argument("--units", help="unit of the simulated field (recorded in the truth file)")
    p.add_argument("--attitudes", choices=["random", "axes"], default="random")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--out", required=True, metavar="OUT.csv")
    p.add_argument("--truth", metavar="TRUTH.json", help="write the true parameters here")
    _add_output_options(p, json_help=None)


def _add_demo(sub: Any) -> None:
    p = sub.add_parser("demo", help="calibrate the bundled real log and write a report",
                       description="Fit the bundled QMC5883L log and write calibration JSON + report PNG.")
    p.add_argument("--out", default=".", metavar="DIR", help="output folder (default: current)")
    _add_output_options(p)


def _add_batch(sub: Any) -> None:
    p = sub.add_parser("batch", help="fit many logs (one calibration each), on local processes or Dask",
                       description="Fit every file matched; write OUT/<name>.json per file and "
                                   "OUT/summary.csv (+ OUT/summary.parquet with the parquet extra). A bad file is "
                                   "reported, not fatal.")
    p.add_argument("inputs", nargs="+", metavar="GLOB", help="glob pattern(s) ('logs/**/*.csv') or files")
    _add_data_options(p, selection=False)
    _add_model_options(p, "error model (as for `trimag fit`)")
    _add_reference_options(p)
    _add_attitude_options(p)
    _add_time_options(p.add_argument_group("time (eddy-current terms, attitudes from a second file)"))
    _add_fit_steps(p)
    _add_gyro_options(p)
    p.add_argument("--policy", metavar="FILE.toml|default",
                   help="acceptance limits for every file (as fit --policy); a rejected calibration exits 4")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes on this machine")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="dask.distributed scheduler, e.g. tcp://host:8786 (needs the batch extra)")
    _add_output_options(p)


def _add_live(sub: Any) -> None:
    p = sub.add_parser("live", help="fit while recording: a local page shows the coverage and when to stop",
                       description="Fit while recording: a local web page (127.0.0.1 only) shows the clouds, the "
                                   "coverage of the sphere of directions, the RMS, the next orientations and when the "
                                   "data are good enough; GET /status returns the same as JSON. The save button and "
                                   "Ctrl-C write the calibration and the samples (docs/recording.md).")
    g = p.add_argument_group("source (exactly one)")
    g.add_argument("--replay", metavar="FILE", help="play back a log (any file `trimag fit` reads)")
    g.add_argument("--rate", type=float, default=2000.0, metavar="HZ",
                   help="replay rate, samples per second (default 2000)")
    g.add_argument("--stdin", action="store_true", help="lines of x,y,z (or a CSV header) on standard input")
    g.add_argument("--serial", metavar="PORT", help="lines of x,y,z (or a CSV header) from a serial port "
                                                    "(needs the live extra: pip install \"trimag[live]\")")
    g.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    g.add_argument("--mavlink", metavar="URL", help="an autopilot's MAVLink stream (udpin:0.0.0.0:14550, "
                                                    "tcp:HOST:5760, a serial device or a .tlog): SCALED_IMU/RAW_IMU "
                                                    "(needs the logs extra)")
    g = p.add_argument_group("data")
    g.add_argument("--format", dest="fmt", help="replay: the log's format (default: from the extension)")
    g.add_argument("--columns", help="x,y,z column names (replay: also 0-based indices)")
    g.add_argument("--var", help="replay of an NPZ or MAT file: the variable holding the field")
    g.add_argument("--sensor", metavar="N|NAME", help="replay of an autopilot log: which magnetometer")
    g.add_argument("--units", help="unit of the data: nT, uT, G, mG, counts (default: the source's own, or unknown)")
    g.add_argument("--reference", type=float, metavar="F", help="field magnitude in the data's unit, when known")
    _add_model_options(p, "error model (as for `trimag fit`; default ellipsoid)")
    p.add_argument("--port", type=int, default=8765, help="local port of the page (default 8765; 0: a free one)")
    p.add_argument("-o", "--out", default="trimag-live-calibration.json", metavar="CAL.json",
                   help="calibration written on save (default trimag-live-calibration.json)")
    p.add_argument("--samples-out", metavar="SAMPLES.csv",
                   help="recorded samples written on save (default: CAL-samples.csv beside --out)")
    p.add_argument("--no-browser", dest="open_browser", action="store_false", help="do not open a browser")
    p.add_argument("--exit-at-end", action="store_true", help="save and exit when the source ends")
    p.add_argument("--interval", type=float, default=0.25, metavar="S", help="seconds between refits (default 0.25)")
    _add_output_options(p, json_help="print the final state as one JSON object on stdout")


def _add_review(sub: Any) -> None:
    p = sub.add_parser("review", help="a local page: what the compasses did in a flight, and their parameters",
                       description="Review a flight: a local web page (127.0.0.1 only) shows the flight, every "
                                   "compass side by side, the expected against the measured field, the field length "
                                   "beside the motor channel, the heading change, the levels and the verdict; drag a "
                                   "range to fit, choose the level and the motor term, download the parameter files "
                                   "(exactly what `trimag export` writes) and the calibration JSON (docs/review.md; "
                                   "needs the review extra: pip install \"trimag[review]\").")
    p.add_argument("log", metavar="LOG", help="an autopilot log (DataFlash .bin/.log, .tlog, ULog .ulg, .px4log) or "
                                              "a table with attitudes (CSV, ...: one compass)")
    p.add_argument("--format", dest="fmt", help="the log's format when its extension does not say")
    p.add_argument("--target", choices=["ardupilot", "px4"],
                   help="whose parameters (default: the log's firmware; a table names none)")
    g = p.add_argument_group("a table (as trimag fit reads it)")
    g.add_argument("--units", help="the table's unit (mG, G, uT, nT): the firmware's parameters need it")
    g.add_argument("--columns", metavar="X,Y,Z", help="the field's columns (default: found by name)")
    g.add_argument("--attitude-columns", metavar="YAW,PITCH,ROLL",
                   help="Euler angles in degrees (Z-Y-X, NED); default: yaw,pitch,roll or yaw_deg,pitch_deg,roll_deg")
    g.add_argument("--time-column", metavar="NAME", help="time in seconds (default: time_s, time, t; else the row)")
    p.add_argument("--igrf", dest="igrf_spec", metavar="LAT,LON,ALT_M,DATE",
                   help="where and when the log was flown, for a log without a GPS fix")
    p.add_argument("--port", type=int, default=8765, help="local port of the page (default 8765; 0: a free one)")
    p.add_argument("--no-browser", dest="open_browser", action="store_false", help="do not open a browser")
    _add_output_options(p, json_help=None)


def _add_reproduce(sub: Any) -> None:
    # the benchmarks are not subcommands: they live in the repository's benchmarks/ folder (not installed)
    p = sub.add_parser("reproduce", help="reproduce a paper's figures and tables",
                       description="Reproduce a paper's figures and tables.")
    p.add_argument("target", metavar="NAME")
    p.add_argument("--out", default="trimag-reproduce", metavar="DIR", help="output folder")
    p.add_argument("--quick", action="store_true", help="small sizes, for a fast check")
    p.add_argument("--trials", type=int, help="Monte Carlo trials")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=1, help="parallel workers")
    _add_output_options(p, json_help="print one JSON summary object on stdout")


#: The subcommands, in the order ``trimag --help`` lists them: each adds its parser (and its flags).
_SUBCOMMANDS: tuple[Callable[[Any], None], ...] = (
    _add_fit, _add_apply, _add_export, _add_evaluate, _add_simulate, _add_demo, _add_batch, _add_live, _add_review,
    _add_reproduce,
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``trimag`` command."""
    parser = _Parser(prog="trimag", description="Calibrate tri-axial magnetometers.")
    parser.add_argument("--version", action="version", version=f"trimag {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for add in _SUBCOMMANDS:
        add(sub)
    return parser


@functools.lru_cache(maxsize=1)
def _command_parser() -> argparse.ArgumentParser:
    """:func:`build_parser`, built once per process with its flags registered: parsing leaves a parser as it was
    (every parse fills a new namespace), and building one takes ~10 ms of argparse (a program calling :func:`main`
    many times, e.g. the suite's fuzz tests, spent a third of a short fit there)."""
    parser = build_parser()
    _register_flags(parser)
    return parser


def _print_fit(result: Any, args: argparse.Namespace) -> None:
    from .quality.report import params_table, summary_table

    for msg in result.messages:
        _err(msg) if msg.startswith("warning:") else _say(msg, args)
    if args.json:
        print(json.dumps(result.summary, allow_nan=False))
        return
    cal = result.calibration
    stats = cal.stats
    _say(f"model {cal.model}, method {cal.method}: {stats['n_used']} samples, "
         f"{'converged' if stats.get('converged') else 'NOT converged'} in {stats.get('iterations')} iterations",
         args)
    _say(summary_table(cal), args)
    _say(params_table(cal), args)
    if cal.units == "unknown":
        _say("note: the data's unit is not given: F and the offsets are in the data's own unit; give --units (nT, uT, "
             "G, mG or counts) to record it (the firmware and the unit checks need it)", args)
    if cal.regressors is not None and "regressors" in cal.diagnostics:
        from .vehicle.regressors import ranking_table

        _say(ranking_table(cal.diagnostics["regressors"]["ranking"], cal.units), args)
    for what, path in result.written.items():
        _say(f"wrote {what}: {path}", args)


def _split_list(text: str | None) -> list[str] | None:
    return None if text is None else [c.strip() for c in text.split(",") if c.strip()]


def _cmd_fit_tolles_lawson(args: argparse.Namespace) -> int:
    from .app import parse_options
    from .app.tolles_lawson import TollesLawsonFitRequest, fit_compensation_file, parse_segments
    from .io.atomic import check_distinct_outputs

    if not args.columns or not args.scalar_column:
        raise TrimagInputError("model tolles-lawson needs --columns FX,FY,FZ (vector magnetometer) and "
                               "--scalar-column S (scalar magnetometer)")
    if args.out is not None:
        _check_writable(args.out)
        check_distinct_outputs({"the input": args.data}, {"out": args.out})
    request = TollesLawsonFitRequest(
        data=Path(args.data), vector_columns=_split_list(args.columns) or [], scalar_column=args.scalar_column,
        time_column=args.time_column, rate_hz=args.rate, segments=parse_segments(args.segments), fmt=args.fmt,
        var=args.var, units=args.units, attitude_columns=_split_list(args.tl_attitude_columns),
        options=parse_options(args.option),
    )
    comp, messages = fit_compensation_file(request)
    for msg in messages:
        _err(msg) if msg.startswith("warning:") else _say(msg, args)
    written = {"compensation": str(comp.to_file(args.out))} if args.out else {}
    if args.json:
        print(json.dumps({**comp.as_dict(), "outputs": written}, allow_nan=False))
        return EXIT_OK
    st = comp.stats
    _say(f"model tolles-lawson: {len(comp.names)} terms, ridge {comp.ridge:.3g}, {st['n_filtered_rows']} band-passed "
         f"samples in {len(st['segments'])} segment(s), condition number {comp.diagnostics['condition_number']:.3g}",
         args)
    _say(f"{'segment':>10}{'rows':>16}{'std before':>12}{'std after':>12}{'ratio':>9}   [nT, band-passed]", args)
    for k, seg in enumerate(st["segments"]):
        ratio = seg["improvement_ratio"]
        _say(f"{k:>10}{seg['rows'][0]:>8}-{seg['rows'][1]:<7}{seg['std_before_nT']:12.4g}{seg['std_after_nT']:12.4g}"
             f"{ratio if ratio is not None else float('nan'):9.3g}", args)
    _say(f"{'term':>10}{'coefficient':>14}{'std':>12}{'formal std':>12}", args)
    for name, value in zip(comp.names, comp.coefficients, strict=True):
        _say(f"{name:>10}{value:14.6g}{comp.uncertainty['std'][name]:12.4g}"
             f"{comp.uncertainty['formal_std'][name]:12.4g}", args)
    for what, path in written.items():
        _say(f"wrote {what}: {path}", args)
    return EXIT_OK


def _where(out: str) -> str:
    return "standard output" if out == "-" else out


def _check_stdout(args: argparse.Namespace) -> None:
    """``-o -`` writes the output to standard output, where ``--json`` would write its object too: refused."""
    if args.out == "-" and getattr(args, "json", False):
        raise TrimagInputError("`-o -` and `--json` both write to standard output; drop one of them")


def _check_writable(path: str | None, *, suffixes: tuple[str, ...] | None = None) -> None:
    """Refuse an output path that cannot be written (or has the wrong extension), before any work is done."""
    import os

    from .io.atomic import check_output_path

    if path is None or path == "-":  # "-": standard output
        return
    target = Path(path)
    if target.is_dir():
        raise TrimagInputError(f"{path} is a folder; give a file name for the output")
    check_output_path(target)  # a symlink, a FIFO or a device is never replaced
    if suffixes is not None and target.suffix.lower() not in suffixes:
        raise TrimagInputError(f"cannot write {target.suffix or 'extension-less'} files here ({path}); use one of "
                               f"{', '.join(suffixes)}")
    probe = target.parent if str(target.parent) else Path(".")
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise TrimagInputError(f"cannot write {path}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK):
        raise TrimagInputError(f"cannot write {path}: no write permission in {probe}")


def _request(cls: type[_R], args: argparse.Namespace, path: Any = None, **given: Any) -> _R:
    """The typed request ``cls`` (:mod:`trimag.app.requests`) of a command from its parsed flags: each field (and each
    field of its ``input``, ``reference`` and ``attitude`` specs, when it has them) takes the flag whose destination
    has its name, the field's default when the command has no such flag; ``path`` is the input's path and
    ``given`` sets fields directly."""
    from .app.requests import AttitudeSpec, InputSpec, ReferenceSpec

    specs: dict[str, type] = {"input": InputSpec, "reference": ReferenceSpec, "attitude": AttitudeSpec}

    def flags(kind: Any, **fixed: Any) -> dict[str, Any]:
        """``kind``'s fields from the flags of the same destination, then ``fixed``."""
        names = [f.name for f in dataclasses.fields(kind) if f.name not in fixed]
        return {**{name: getattr(args, name) for name in names if hasattr(args, name)}, **fixed}

    own = {f.name: f.type for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    parts = {name: kind(**flags(kind, **({"path": path} if kind is InputSpec else {})))
             for name, kind in specs.items() if own.get(name) in (kind, kind.__name__)}  # a spec, not a plain field
    return cls(**flags(cls, **parts, **given))


def _regressor_flag(text: str | None) -> tuple[str, ...] | None:
    """``--regressors A,B`` -> ("A", "B")."""
    names = _split_list(text)
    if names is not None and not names:
        raise TrimagInputError("--regressors names no column; give COL[,COL...]")
    return None if names is None else tuple(names)


#: The options of ``fit`` that a Tolles-Lawson fit does not use (refused with it, issue 39).
_NOT_TOLLES_LAWSON = (
    "report", "deviation_card", "policy", "sensor", "rows", "where", "strict", "reference", "igrf_spec",
    "reference_column", "attitude_columns", "quaternion_columns", "background_ned", "background_columns",
    "igrf_columns", "background_run", "attitude_file", "position_columns", "regressors", "prior", "target", "level",
    "motor", "level_turn", "heading", "heading_column", "export_to", "export_out", "gyro_columns", "gyro_file",
    "gyro_unit", "method",
)


def _cmd_fit(args: argparse.Namespace) -> int:
    from .app import fit_file, parse_options

    _check_writable(args.out)
    _check_writable(args.report, suffixes=(".png", ".pdf", ".svg", ".html"))
    _check_writable(args.deviation_card, suffixes=(".png",))
    _check_stdout(args)
    if args.out == "-" and ((args.sensor or "").strip().lower() == "all" or args.model == "tolles-lawson"):
        raise TrimagInputError("`-o -` writes one calibration to standard output; this fit writes "
                               + ("one file per compass" if args.model != "tolles-lawson" else "a compensation file")
                               + ": give `-o FILE.json`")
    if args.model == "tolles-lawson":
        if args.accel_columns:
            raise TrimagInputError("--accel-columns aligns a vector calibration; a Tolles-Lawson compensation is "
                                   "scalar (drop --accel-columns)")
        # flags of a vector calibration's fit: refused, never ignored (--report drew nothing and said nothing)
        _refuse_unused(args, _NOT_TOLLES_LAWSON, "model tolles-lawson (it prints its per-segment table; `trimag "
                       "evaluate COMP.json DATA` prints it again)")
        return _cmd_fit_tolles_lawson(args)

    from .app.requests import FitRequest

    request = _request(FitRequest, args, args.data, options=parse_options(args.option),
                       regressors=_regressor_flag(args.regressors), rate_hz=args.rate)
    if (args.sensor or "").strip().lower() == "all":
        return _cmd_fit_all(request, args)
    result = fit_file(request)
    _print_fit(result, args)
    verdict = result.summary.get("acceptance")
    if verdict is not None:
        if verdict["not_evaluated"]:
            _err(f"warning: policy rules not evaluated (the data cannot measure them): "
                 f"{', '.join(verdict['not_evaluated'])}")
        if verdict.get("nothing_checked"):
            _err("rejected by the acceptance policy: nothing was checked, none of its rules can be measured on these "
                 "data (give --reference or --igrf, or rules the data can measure; the calibration is written, "
                 "marked rejected)")
            return EXIT_POLICY
        if not verdict["accepted"]:
            from .vehicle.policy import failed_rules

            failed = "; ".join(failed_rules(verdict))
            _err(f"rejected by the acceptance policy: {failed} (the calibration is written, marked rejected)")
            return EXIT_POLICY
    return EXIT_OK


def _cmd_fit_all(request: Any, args: argparse.Namespace) -> int:
    """``trimag fit LOG --sensor all``: every compass fitted, compared, and written (docs/autopilot.md)."""
    from .app.fit_all import comparison_lines, fit_all_sensors

    _check_writable(args.export_out)
    result = fit_all_sensors(request)
    if args.json:
        print(json.dumps(result.summary, allow_nan=False))
    else:
        first = result.fits[min(result.fits)]
        for msg in first.messages:  # the log's summary (its compasses, its reference)
            if not msg.startswith("warning:"):
                _say(msg, args)
        _say(f"compasses fitted: {', '.join(map(str, result.fits))}", args)
        for line in comparison_lines(result, first.calibration.units):
            _say(line, args)
    for k, msg in enumerate(result.messages):
        if msg.startswith("warning:"):  # with the detail lines that follow it
            details = [d[2:] for d in itertools.takewhile(lambda m: m.startswith("  "), result.messages[k + 1:])]
            _err(msg, details)
        elif not msg.startswith("  "):
            _say(msg, args)
    for what, path in result.written.items():
        _say(f"wrote {what}: {path}", args)
    return EXIT_POLICY if result.rejected else EXIT_OK


def _with_progress(args: argparse.Namespace, work: Callable[..., dict[str, Any]], request: Any) -> dict[str, Any]:
    """``work(request, progress=...)`` with the progress bar of :func:`_progress`, closed however it ends."""
    update, close = _progress(args)
    try:
        return work(request, progress=update)
    finally:
        close()


def _progress(args: argparse.Namespace) -> tuple[Callable[[int], None], Callable[[], None]]:
    """A rich progress bar on stderr (rows done) that appears only once work has taken more than a second."""
    from .parallel import ProgressBar

    bar = ProgressBar(f"trimag {args.command}", None, enabled=not getattr(args, "quiet", False), unit="rows")
    return bar.update, bar.close


def _cmd_apply(args: argparse.Namespace) -> int:
    from .app import apply_to_file
    from .app.requests import ApplyRequest
    from .app.tolles_lawson import apply_compensation_file, is_compensation_file

    _default_out(args, args.data, "-corrected.csv")
    _check_writable(args.out, suffixes=(".csv", ".txt", ".parquet", ".npz"))
    _check_stdout(args)
    req = _request(ApplyRequest, args, args.data)
    src = req.input
    if is_compensation_file(req.calibration):
        if args.out == "-":
            raise TrimagInputError("a Tolles-Lawson compensation is applied to a file: give `-o OUT.csv`")
        _refuse_unused(args, ("strict", "sensor"), "a Tolles-Lawson compensation file")
        r = apply_compensation_file(req.calibration, src.path, req.out, fmt=src.fmt, var=src.var,
                                    columns=_split_list(src.columns), scalar_column=req.scalar_column,
                                    units=src.units)
        _say_sensor(r, args)
        return _print_applied(r, args, "compensated", "nT", "could not be compensated (missing values or a segment of "
                              "one row); their compensated cells are empty")

    result = _with_progress(args, apply_to_file, req)
    _say_sensor(result, args)
    if result["column_note"]:
        _say(result["column_note"], args)
    return _print_applied(result, args, "corrected", result["units"], "had missing or non-numeric x/y/z; they are "
                          "kept with empty corrected cells")


def _refuse_unused(args: argparse.Namespace, dests: tuple[str, ...], what: str) -> None:
    """Refuse a flag the command accepts but does not use with ``what`` (never ignore it)."""
    defaults = {"chunk_rows": DEFAULT_CHUNK_ROWS}
    for dest in dests:
        value = getattr(args, dest, None)
        if value not in (None, False, defaults.get(dest)):
            raise TrimagInputError(f"`{dest}` is not used with {what}; drop it")


def _print_applied(r: dict[str, Any], args: argparse.Namespace, verb: str, unit: str, uncorrected: str) -> int:
    """What ``trimag apply`` did: the rows left uncorrected (``uncorrected`` says why) on stderr, then the JSON
    object or one line (``verb`` the rows, in ``unit``)."""
    if r["n_uncorrected"]:
        _err(f"{r['n_uncorrected']} of {r['n_rows']} rows {uncorrected}")
    if args.json:
        print(json.dumps(r))
    else:
        _say(f"{verb} {r['n_rows'] - r['n_uncorrected']} of {r['n_rows']} rows ({unit_words(unit)}); appended "
             f"{', '.join(r['output_columns'])}; wrote {_where(r['out'])}", args)
    return EXIT_OK


def _print_tl_evaluation(r: dict[str, Any], args: argparse.Namespace) -> None:
    _say_sensor(r, args)
    _say(f"{r['n_samples']} samples, {r['n_segments']} segment(s), band {r['band_hz'][0]:g}-{r['band_hz'][1]:g} Hz "
         f"at {r['rate_hz']:g} Hz; scalar {r['scalar_column']}", args)
    _say(f"{'segment':>8}{'t0 [s]':>10}{'t1 [s]':>10}{'std before':>12}{'std after':>12}{'ratio':>9}   [nT]", args)
    for k, seg in enumerate(r["segments"]):
        if seg["std_before_nT"] is None:
            _say(f"{k:>8}{seg['t0_s']:10.1f}{seg['t1_s']:10.1f}   too short to band-pass", args)
            continue
        _say(f"{k:>8}{seg['t0_s']:10.1f}{seg['t1_s']:10.1f}{seg['std_before_nT']:12.4g}{seg['std_after_nT']:12.4g}"
             f"{seg['improvement_ratio']:9.3g}", args)
    _say(f"{'all':>8}{'':20}{r['std_before_nT']:12.4g}{r['std_after_nT']:12.4g}{r['improvement_ratio']:9.3g}", args)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .app.requests import EvaluateRequest
    from .app.tolles_lawson import evaluate_compensation_file, is_compensation_file

    req = _request(EvaluateRequest, args, args.data, rate_hz=args.rate)
    if req.accel_columns or req.heading_column or req.declination is not None:
        return _cmd_evaluate_heading(req, args)
    if req.attitude.attitude_columns or req.attitude.quaternion_columns:
        return _cmd_evaluate_vector(req, args)
    if is_compensation_file(args.calibration):
        _refuse_unused(args, ("strict", "sensor", "rows", "where", "reference", "igrf_spec", "reference_column",
                              "chunk_rows"), "a Tolles-Lawson compensation file (it evaluates whole segments)")
        r = evaluate_compensation_file(
            args.calibration, args.data, fmt=args.fmt, var=args.var, columns=_split_list(args.columns),
            scalar_column=args.scalar_column, units=args.units, time_column=args.time_column, rate_hz=args.rate,
            segments=args.segments,
        )
        if args.json:
            print(json.dumps(r, allow_nan=False))
        else:
            _print_tl_evaluation(r, args)
        return EXIT_OK
    return _cmd_evaluate_scalar(req, args)


def _cmd_evaluate_scalar(req: EvaluateRequest, args: argparse.Namespace) -> int:
    from .app import evaluate_file

    r = _with_progress(args, evaluate_file, req)
    _say_sensor(r, args)
    if r["n_dropped"]:
        column = req.reference.reference_column
        what = " or ".join(["x/y/z"] + (["regressor values"] if r.get("regressors") else [])
                           + ([f"reference ({column})"] if column else []))
        _err(f"skipped {r['n_dropped']} of {r['n_samples']} rows with missing or non-numeric {what}")
    for warning in r["warnings"]:
        _err(f"warning: {warning}")
    if args.json:
        print(json.dumps(r, allow_nan=False))
        return EXIT_OK
    ref = r["reference"]
    _say(f"{r['n_used']} samples; reference F = {ref['value']:.6g} {r['units']} ({ref['source']})"
         if ref["value"] is not None and r["units"] != "unknown" else
         f"{r['n_used']} samples; reference F = {ref['value']:.6g} ({ref['source']}; unit not given)"
         if ref["value"] is not None else f"{r['n_used']} samples; reference per sample ({ref['source']})", args)
    _say(f"{'':16}{'before':>14}{'after':>14}   [{unit_words(r['units'])}]", args)
    for label, key in (("|B| mean", "mean_norm"), ("|B| std", "std_norm"), ("RMS(|B| - F)", "rms"),
                       ("max ||B| - F|", "max_abs"), ("peak-to-peak", "p2p")):
        k_b = f"{key}_before"
        k_a = f"{key}_after"
        _say(f"{label:16}{r[k_b]:14.6g}{r[k_a]:14.6g}", args)
    return EXIT_OK


def _cmd_evaluate_vector(req: EvaluateRequest, args: argparse.Namespace) -> int:
    import numpy as np

    from .app import evaluate_vector_file

    v = evaluate_vector_file(req)
    _say_sensor(v, args)
    for warning in v["warnings"]:
        _err(f"warning: {warning}")
    if args.json:
        print(json.dumps(v, allow_nan=False))
        return EXIT_OK
    mean = "mean " if v["background"]["per_sample"] else ""
    _say(f"{v['n_used']} samples; background NED {mean}{np.round(v['background']['ned'], 3).tolist()} {v['units']} "
         f"({v['background']['source']}); columns {', '.join(v['columns'])}", args)
    _say(f"{'':22}{'before':>14}{'after':>14}   [{unit_words(v['units'])}, deg]", args)
    for k, axis in enumerate("xyz"):
        _say(f"{'RMS error ' + axis:22}{v['before']['rms_axis'][k]:14.6g}{v['after']['rms_axis'][k]:14.6g}", args)
    for label, key in (("RMS vector error", "rms_vector"), ("angular error RMS", "angular_error_rms_deg"),
                       ("angular error max", "angular_error_max_deg")):
        _say(f"{label:22}{v['before'][key]:14.6g}{v['after'][key]:14.6g}", args)
    return EXIT_OK


def _cmd_evaluate_heading(req: EvaluateRequest, args: argparse.Namespace) -> int:
    from .app import evaluate_heading_file

    if not req.accel_columns:
        raise TrimagInputError("--heading-column and --declination need --accel-columns AX,AY,AZ (the heading is "
                               "tilt-compensated with the accelerometer)")
    h = evaluate_heading_file(req)
    _say_sensor(h, args)
    if h["alignment"] == "none":
        _err("warning: the calibration has no alignment (fit with --accel-columns): the magnetometer's axes are "
             "taken as the accelerometer's")
    if h["n_dropped"]:
        _err(f"skipped {h['n_dropped']} of {h['n_samples']} rows with missing or non-numeric values")
    if args.json:
        print(json.dumps(h, allow_nan=False))
        return EXIT_OK
    _say(f"{h['n_used']} samples; true heading = tilt-compensated magnetic heading + declination "
         f"{h['declination_deg']:.3f} deg ({h['declination_source']}); alignment: "
         + (f"from the calibration (nearest board rotation {h['board_rotation']})" if h["alignment"] != "none"
            else "none") + f"; reference: {h['reference_heading']}", args)
    for what in ("rms", "max", "mean", "std"):
        _say(f"{'heading error ' + what:22}{h[f'heading_error_{what}_deg']:12.4g} deg", args)
    return EXIT_OK


def _cmd_export(args: argparse.Namespace) -> int:
    from .app import export_to_file
    from .app.requests import ExportRequest

    _default_out(args, args.calibration, _EXPORT_SUFFIXES[args.target])
    _check_writable(args.out)
    _check_stdout(args)
    r = export_to_file(_request(ExportRequest, args))
    for note in r["notes"]:
        _say(f"note: {note}", args)
    for v in r["violations"]:
        _err(f"warning: outside the firmware's limits: {v}")
    for w in r["warnings"]:
        _err(f"warning: {w}")
    if args.json:
        print(json.dumps(r))
    else:
        _say(f"wrote {args.target} parameters: {_where(r['out'])}", args)
    return EXIT_OK


def _cmd_simulate(args: argparse.Namespace) -> int:
    from .app import simulate_to_file
    from .app.requests import SimulateRequest

    _check_writable(args.out)
    _check_writable(args.truth)
    r = simulate_to_file(_request(SimulateRequest, args, params_path=args.params))
    if r["defaulted"]:
        _say(f"parameters not given (defaults: no error, identity and zero): {', '.join(r['defaulted'])}", args)
    for what, path in r["outputs"].items():
        _say(f"wrote {what}: {path}", args)
    return EXIT_OK


def _cmd_demo(args: argparse.Namespace) -> int:
    from .app import DEMO_DATA, run_demo

    _say(f"trimag demo: calibrating the bundled real log {DEMO_DATA} (QMC5883L, raw counts, hand-rotated)", args)
    result = run_demo(args.out)
    _print_fit(result, args)
    return EXIT_OK


def _cmd_batch(args: argparse.Namespace) -> int:
    from .app import parse_options
    from .app.batch import fit_batch
    from .app.requests import FitRequest

    # every file's request: the flags given, without an output (one calibration per file)
    request = _request(FitRequest, args, "", options=parse_options(args.option),
                       regressors=_regressor_flag(args.regressors), out=None, rate_hz=args.rate)
    result = fit_batch(args.inputs, args.out, request=request, workers=args.workers, scheduler=args.scheduler,
                       progress=not args.quiet)
    for file, error in zip(result.table["file"], result.table["error"], strict=True):
        if error:  # named once: most messages already start with the file's name; the verdict only
            _err(error if str(error).startswith(f"{file}:") else f"{file}: {error}")
    if result.table["error_details"].astype(bool).any() and "summary_csv" in result.written:
        summary = result.written["summary_csv"]
        _err(f"the figures behind each failed file's verdict: the error_details column of {summary}")
    if args.json:
        print(json.dumps(result.summary(), allow_nan=False))
    else:
        _say(f"fitted {result.n_files - result.n_failed} of {result.n_files} files in {result.seconds:.1f} s "
             f"({result.files_per_second:.1f} files/s); wrote {', '.join(result.written.values())} and one "
             f"calibration per file in {args.out}", args)
        if result.n_rejected:
            _say(f"the acceptance policy rejected {result.n_rejected} of them (summary: accepted, rejected_by)", args)
        if "summary_parquet" not in result.written:
            _say('note: summary.parquet not written: it needs pyarrow (pip install "trimag[parquet]")', args)
    return result.exit_code()


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from .experiments import get_experiment

    module = get_experiment(args.target)
    extra: dict[str, Any] = {}
    if hasattr(module, "add_arguments"):
        sub = _Parser(prog=f"trimag reproduce {args.target}", description=f"Options of reproduce {args.target}.")
        module.add_arguments(sub)
        extra = vars(sub.parse_args(args.extra_args))
    elif args.extra_args:
        raise TrimagInputError(f"reproduce {args.target} takes no option {args.extra_args[0]!r}")
    t0 = time.monotonic()
    summary = module.run(Path(args.out), quick=args.quick, trials=args.trials, seed=args.seed,
                         workers=args.workers, json_mode=args.json, **extra)
    summary.setdefault("runtime_s", time.monotonic() - t0)
    if args.json:
        print(json.dumps(summary, allow_nan=False, default=float))
    else:
        _say(f"reproduce {args.target}: done in {summary['runtime_s']:.1f} s; outputs in {args.out}", args)
        text = summary.get("text")
        if text:
            _say(str(text), args)
    return EXIT_OK


def _cmd_live(args: argparse.Namespace) -> int:
    from .app import parse_options
    from .app.requests import LiveRequest
    from .live import run_live

    _check_writable(args.out, suffixes=(".json",))
    _check_writable(args.samples_out, suffixes=(".csv", ".txt"))
    request = _request(LiveRequest, args, options=parse_options(args.option))
    def say(msg: str) -> None:  # flushed: the page's address must reach a pipe (a script, tee) at once
        _say(msg, args)
        sys.stdout.flush()

    result = run_live(request, say=say)
    st = result.status
    if args.json:
        print(json.dumps({**st, "written": result.written, "reason": result.reason}, allow_nan=False))
    else:
        def num(value: Any) -> str:
            return "-" if value is None else f"{value:.4g}"

        _say(f"{st['n_samples']} samples ({st['n_garbage']} lines not understood); coverage "
             f"{num(st['coverage_fraction'])}, RMS before {num(st['rms_before'])}, after {num(st['rms_after'])} "
             f"{st['units']}; {'good enough' if st['good_enough'] else 'NOT good enough'}", args)
        if not st["good_enough"]:
            _say(f"next: {st['next_orientations']}", args)
    if "calibration" not in result.written:  # the same exit code with --json
        failed = st["source_message"] if st["source_message"].startswith("the source failed") else ""
        _err(f"no calibration written: {failed or st.get('fit_message') or 'too few samples'}")
        return EXIT_IDENTIFIABILITY if st["n_samples"] else EXIT_INPUT
    return EXIT_OK


def _cmd_review(args: argparse.Namespace) -> int:
    from .app.requests import ReviewRequest
    from .live.review import run_review

    def say(msg: str) -> None:  # flushed: the page's address must reach a pipe (a script, tee) at once
        _say(msg, args)
        sys.stdout.flush()

    result = run_review(_request(ReviewRequest, args), say=say)
    _say(f"trimag review: stopped ({result.reason})", args)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``trimag`` command; returns the exit code."""
    parser = _command_parser()
    args, unknown = parser.parse_known_args(argv)
    if args.command in ("live", "batch") and getattr(args, "model", None) == "tolles-lawson":
        from .app.tolles_lawson import not_fitted_by

        _err(f"error: {not_fitted_by(args.command)}")  # before its flags, which these commands do not have
        return EXIT_INPUT
    if unknown and args.command != "reproduce":
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    args.extra_args = unknown
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_INPUT
    handlers: dict[str, Callable[[argparse.Namespace], int]] = {
        "fit": _cmd_fit,
        "apply": _cmd_apply,
        "evaluate": _cmd_evaluate,
        "export": _cmd_export,
        "simulate": _cmd_simulate,
        "demo": _cmd_demo,
        "batch": _cmd_batch,
        "reproduce": _cmd_reproduce,
        "live": _cmd_live,
        "review": _cmd_review,
    }
    import signal

    def _terminate(signum: int, frame: Any) -> None:  # SIGTERM unwinds like Ctrl-C: temporary files are removed
        raise _Terminated()

    try:
        signal.signal(signal.SIGTERM, _terminate)
    except ValueError:  # not the main thread (main() called from a thread): keep the default
        pass
    try:
        from .io.limits import input_limits

        with input_limits(getattr(args, "max_fields", None), getattr(args, "max_decompressed_mb", None)):
            code = handlers[args.command](args)
        if code == EXIT_OK and getattr(args, "default_out", None):
            _err(f"no -o given: wrote {args.default_out}")
        return code
    except _Terminated:
        _err("terminated")
        return 143
    except UnicodeDecodeError as exc:
        from .io.tables import not_utf8

        _err(f"error: an input file is {not_utf8(exc)}")
        return EXIT_INPUT
    except BrokenPipeError:  # an OSError: `trimag fit ... | head` closed the pipe
        return EXIT_OK
    except OSError as exc:  # the user's files: missing, unreadable, unwritable, a folder, a full disk
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        _err(f"error: cannot read or write{where}: {exc.strerror or exc}")
        return EXIT_INPUT
    except IdentifiabilityError as exc:
        _err(f"cannot identify the model: {exc}", exc.details)
        return EXIT_IDENTIFIABILITY
    except TrimagInputError as exc:
        _err(f"error: {exc}", exc.details)
        return EXIT_INPUT
    except TrimagError as exc:
        _err(f"error: {exc}", exc.details)
        return exc.exit_code
    except KeyboardInterrupt:
        _err("interrupted")
        return 130
    except MemoryError:
        from .errors import out_of_memory_message

        _err(f"error: {out_of_memory_message()}")
        return EXIT_INPUT
    except ImportError as exc:  # an optional package that a code path imported without `require`: still exit 2
        from ._core.extras import EXTRAS, missing_extra_message

        if (exc.name or "").split(".")[0] not in EXTRAS:
            return _internal_error(exc)
        _err(f"error: {missing_extra_message(exc.name or '', f'trimag {args.command}')}")
        return EXIT_INPUT
    except Exception as exc:
        return _internal_error(exc)


def _internal_error(exc: BaseException) -> int:
    """Exit code 1 is for trimag's own bugs only: say so, in one line (no traceback)."""
    _err(f"internal error (a bug in trimag, not a problem with your input): {type(exc).__name__}: {exc}; "
         "please report it with the command you ran")
    return EXIT_INTERNAL


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
