"""The refusal of an autopilot log that cannot identify a 3-D calibration, said for a newcomer (issue 30, item 7):
which compass was used and which others the log has, what the log shows, what to record, and the modes that
calibrate from such a log anyway (``target``: the firmware-space fit of an ordinary flight; ``level_turn``,
``heading``, ``prior``). No condition number: what the data leave
undetermined is named in words."""

from __future__ import annotations

import re
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import IdentifiabilityError
from ..io.logs.base import compass_labels
from ..quality.diagnostics import PARAMETER_WORDS

_CONDITION = re.compile(r"condition number|e\+\d\d")
_WEAK = re.compile(r"poorly determined: ([a-z0-9_, ]+)")
#: the field direction within this cone (degrees) of its mean: the vehicle stood still
STATIC_CONE_DEG = 5.0


def direction_spread_deg(field: NDArray[np.float64]) -> tuple[float, float]:
    """The smallest and largest angle (degrees) of the field directions from their mean direction."""
    u = field / np.linalg.norm(field, axis=1, keepdims=True)
    mean = u.mean(axis=0)
    mean /= np.linalg.norm(mean)
    angle = np.degrees(np.arccos(np.clip(u @ mean, -1.0, 1.0)))
    return float(angle.min()), float(angle.max())


def _reason(message: str, name: str, field: NDArray[np.float64]) -> str:
    """The refusal's own text without the compass's name, or (a condition number) what the data show instead."""
    text = message[len(name) + 2:] if message.startswith(f"{name}: ") else message
    if not _CONDITION.search(text):
        return text
    weak = _WEAK.search(text)
    names = [n.strip() for n in weak.group(1).split(",")] if weak else []
    words = [PARAMETER_WORDS.get(n, n) for n in names if n]
    lo, hi = direction_spread_deg(field)
    return (f"the field directions stay {lo:.0f}..{hi:.0f} deg from their mean direction: the vehicle turned mostly "
            "about one axis, so a 3-D calibration cannot be identified from this log"
            + (f" ({', '.join(words)} undetermined)" if words else "")
            + ". Record a calibration with the vehicle also pitched nose up and down and rolled on each side")


#: a clause that tells the user what to do (the verdict's second half)
_IMPERATIVE = re.compile(r"(record|log |keep|give|fit |check|add |use |choose|turn |rotate|refit)", re.I)
#: the verdict's parts (what is wrong, what to do) at most this long; longer ones are said in the details only
_WHAT_CHARS, _DO_CHARS = 100, 95
#: the verdict's two parts together at most this long (the line adds the compass and "cannot identify the model")
_VERDICT_CHARS = 140
#: what to do when no clause of the refusal says it briefly
_RECORD = "record a turn through all headings, pitched and rolled"


def top_level_split(text: str, sep: str) -> list[str]:
    """``text`` split at ``sep`` outside parentheses, brackets and backticks (``(mean; RMS 15.5)`` stays whole)."""
    parts, depth, tick, start, k = [], 0, False, 0, 0
    while k < len(text):
        ch = text[k]
        if ch == "`":
            tick = not tick
        elif not tick and ch in "([":
            depth += 1
        elif not tick and ch in ")]":
            depth = max(0, depth - 1)
        elif not tick and depth == 0 and text.startswith(sep, k):
            parts.append(text[start:k])
            start = k + len(sep)
            k = start
            continue
        k += 1
    parts.append(text[start:])
    return [p.strip() for p in parts if p.strip()]


def _without_parentheses(text: str) -> str:
    """``text`` without its (outermost) parenthesised parts."""
    out, depth = [], 0
    for ch in text:
        if ch == "(":
            depth += 1
        elif ch == ")" and depth:
            depth -= 1
        elif depth == 0:
            out.append(ch)
    return "".join(out)


def clauses(reason: str) -> list[str]:
    """A refusal's reason cut into its clauses: at "; " and at a sentence's end, outside parentheses."""
    out: list[str] = []
    for part in top_level_split(reason, "; "):
        out += [c.rstrip(". ") for c in re.split(r"(?<=[a-z0-9)%'])\. (?=[A-Z`-])", part) if c.strip()]
    return out


def verdict_and_details(reason: str) -> tuple[str, list[str]]:
    """A refusal's ``reason`` as ``(verdict, details)``: the verdict is its first clause (up to its first ": " when
    long) and the first short clause that says what to do (else :data:`_RECORD`); the details are every clause,
    so nothing of the reason is lost."""
    parts = clauses(reason)
    if not parts:
        return reason, []
    what = parts[0]
    if len(what) > _WHAT_CHARS:
        what = top_level_split(what, ": ")[0]
    if len(what) > _WHAT_CHARS:  # its parentheses are in the details
        what = re.sub(r"\s+", " ", _without_parentheses(what)).strip()
    do = next((short for part in parts[1:] for c in [part, *top_level_split(part, ": ")[1:]] if _IMPERATIVE.match(c)
               for short in (c, top_level_split(c, ", ")[0]) if len(short) <= _DO_CHARS), None)
    if do is None and len(parts[0]) > len(what):  # "X: give Y" in the first clause
        tail = top_level_split(parts[0], ": ")[-1]
        do = tail if _IMPERATIVE.match(tail) and len(tail) <= _DO_CHARS else None
    do = do or _RECORD
    if len(what) + len(do) > _VERDICT_CHARS:
        what = top_level_split(what, ": ")[0]
    if len(what) + len(do) > _VERDICT_CHARS and len(_RECORD) < len(do):
        do = _RECORD
    verdict = f"{what}; {do[:1].lower()}{do[1:]}"
    return verdict, ([] if verdict == reason else parts)


def log_refusal(exc: IdentifiabilityError, log_info: dict[str, Any], field: NDArray[np.float64], *,
                target: str | None = None, igrf_given: bool = False) -> IdentifiabilityError:
    """``exc`` (a log's fit refused) said with the log's compasses and the modes that would help: one verdict line
    (which compass, what is wrong, what to do), the rest as details (:attr:`~trimag.errors.TrimagError.details`):
    the reason's clauses, the log's compasses, the firmware-space fit (not offered when it was the fit refused,
    ``target``; IGRF not asked for when given) and the modes for a vehicle that cannot be tumbled, each once."""
    name = str(log_info.get("sensor", ""))
    reason = _reason(str(exc).rstrip(". "), name, field).rstrip(". ")
    compasses = log_info.get("compasses") or []
    listed = ", ".join(compass_labels([(int(c["number"]), str(c["name"])) for c in compasses]))
    number = log_info.get("compass")
    head = f"compass {number} ({name})" if number is not None else name
    static = len(field) and direction_spread_deg(field)[1] < STATIC_CONE_DEG
    modes = ["`heading=DEG` takes the offsets from the vehicle's known true heading while it stood still (as "
             "ArduPilot's MAG_CAL_YAW)",
             "`level_turn` fits a vehicle that turns but cannot tilt (a boat, a rover): horizontal offsets and scales, "
             "the vertical offset from the field's magnitude",
             "`prior=CAL.json` keeps an earlier full calibration and refits its offsets"]
    if not static:
        modes = [modes[1], modes[0], modes[2]]
    firmware = "" if target else _firmware_fit(log_info, igrf_given).strip().rstrip(".")
    verdict, details = verdict_and_details(reason)
    details = [*details, *([f"the log's compasses: {listed}; another with `sensor=N`"] if listed else []),
               *([firmware] if firmware else []), "for a vehicle that cannot be tumbled:",
               *(f"- {mode}" for mode in modes)]
    return IdentifiabilityError(f"{head}: {verdict}", details=details)


def _firmware_fit(log_info: dict[str, Any], igrf_given: bool = False) -> str:
    """The firmware-space fit that an autopilot's ordinary flight can give (``target``, docs/autopilot.md), named
    with the firmware of the log's format; empty for logs of no autopilot (a phone, a ROS bag)."""
    fmt = str(log_info.get("format", ""))
    target = "px4" if "PX4" in fmt else ("ardupilot" if ("ArduPilot" in fmt or "MAVLink" in fmt) else None)
    if target is None:
        return ""
    gps = "" if log_info.get("gps") or igrf_given else \
        " (this log has no GPS fix: add `igrf_spec=LAT,LON,ALT_M,YYYY-MM-DD`)"
    return (f" From an ordinary flight, `target={target}` fits the parameters the firmware loads (the levels the "
            f"flight identifies, against the IGRF field rotated by the logged attitude){gps}.")
