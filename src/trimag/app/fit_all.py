"""``trimag fit LOG --sensor all``: every compass of an autopilot log fitted, compared, and written to one parameter
file (issue 30, item 6; docs/autopilot.md "All compasses of a log").

Each compass is fitted as ``--sensor N`` would fit it (:func:`trimag.app.fit.fit_file`, the same request), its
calibration written beside ``out`` as ``STEM-N.json`` (N as the firmware numbers compasses: COMPASS_OFS = 1,
COMPASS_OFS2 = 2; PX4 CAL_MAG0 = 1). The comparison: each compass's offset and fitted field magnitude, and the
heading difference between each compass and the first fitted one, before (the log's onboard calibration) and after
(tilt-compensated with the log's roll and pitch, the other compass interpolated to the first one's time stamps).
A compass that cannot be fitted is named with its reason; the others are still written.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import IdentifiabilityError, TrimagError, TrimagInputError, full_message
from .requests import FitRequest

__all__ = ["AllSensorsResult", "fit_all_sensors"]


@dataclass
class AllSensorsResult:
    """What :func:`fit_all_sensors` produced: the fit of each compass (its number -> :class:`FitResult`), the
    compasses refused (number -> reason), the comparison, the messages (each compass's warnings and acceptance
    verdict among them, naming it) and the files written."""

    fits: dict[int, Any]
    refused: dict[int, str]
    comparison: dict[str, Any]
    messages: list[str] = field(default_factory=list)
    written: dict[str, str] = field(default_factory=dict)

    @property
    def rejected(self) -> list[int]:
        """The compasses fitted but rejected by the acceptance policy (``policy``; the command exits 4)."""
        return [n for n, r in self.fits.items() if not (r.summary.get("acceptance") or {}).get("accepted", True)]

    @property
    def summary(self) -> dict[str, Any]:
        """The JSON object ``trimag fit --sensor all --json`` prints."""
        return {"compasses": {str(n): r.summary for n, r in self.fits.items()},
                "refused": {str(n): why for n, why in self.refused.items()}, "comparison": self.comparison,
                "outputs": self.written}


def numbered(path: str | Path | None, number: int) -> str | None:
    """``cal.json`` -> ``cal-2.json`` (compass 2's file)."""
    if path is None:
        return None
    p = Path(path)
    return str(p.with_name(f"{p.stem}-{number}{p.suffix}"))


def _compasses(req: FitRequest) -> list[tuple[int, str]]:
    """The log's compasses as (number, name): one stream per number (the one with the most samples)."""
    from ..io.logs import log_format, read_log

    path = req.input.path
    if log_format(path, req.input.fmt) is None:
        raise TrimagInputError(f"`sensor=all` fits every compass of an autopilot log; {path} is not one")
    log = read_log(path, req.input.fmt)
    best: dict[int, Any] = {}
    for m in log.magnetometers:
        if m.number not in best or len(m.time_s) > len(best[m.number].time_s):
            best[m.number] = m
    return [(n, best[n].name) for n in sorted(best)]


def fit_all_sensors(req: FitRequest) -> AllSensorsResult:
    """Fit every compass of the log ``req.input.path`` (module docstring); ``req.export_to`` / ``export_out``
    write one parameter file with every compass fitted."""
    from ..io.atomic import check_distinct_outputs
    from .fit import fit_file, fit_inputs

    if (req.export_to is None) != (req.export_out is None):
        raise TrimagInputError("give both `export_to=ardupilot|px4` and `export_out=FILE` (the parameter file)")
    if req.export_out is not None and str(req.export_out).strip() == "-":
        raise TrimagInputError("`export_out` is the parameter file to write; standard output (-) is not one here: "
                               "give a file name (or write one compass to standard output with trimag export CAL.json "
                               "-o -)")
    compasses = _compasses(req)
    outputs: dict[str, str | Path | None] = {"export_out": req.export_out}
    for number, _ in compasses:  # every file this run can write, before it writes one
        outputs.update({f"{what} of compass {number}": numbered(getattr(req, what), number)
                        for what in ("out", "report", "deviation_card")})
    check_distinct_outputs(fit_inputs(req), outputs)
    fits, refused, errors = _fit_each(req, compasses, fit_file)
    messages: list[str] = []
    channel = _one_motor_channel(req, compasses, fits, fit_file)
    if channel is not None:  # every compass again with the one channel: its files replace the first pass's
        for r in fits.values():
            for path in r.written.values():
                Path(path).unlink(missing_ok=True)
        fits, refused, errors = _fit_each(dataclasses.replace(req, motor=f"auto={channel['channel']}"), compasses,
                                          fit_file)
        messages.append(channel["message"])
    if not fits:
        kind = IdentifiabilityError if any(isinstance(e, IdentifiabilityError) for e in errors) else TrimagInputError
        verdict, details = _none_fitted(dict(zip(refused, errors, strict=True)))
        raise kind(verdict, details=details)
    comparison = compare_compasses(fits)
    written = {f"calibration {n}": r.written["calibration"] for n, r in fits.items() if "calibration" in r.written}
    if req.export_to is not None and req.export_out is not None:
        from ..io.atomic import atomic_write_text
        from ..io.export_instances import export_instances

        exportable = _exportable(fits, req, messages)
        try:
            exp = export_instances([(r.calibration, n) for n, r in exportable.items()], req.export_to)
        except TrimagError:  # no parameter file: nothing of this run is left behind (the command exits 2)
            for r in fits.values():
                for path in r.written.values():
                    Path(path).unlink(missing_ok=True)
            raise
        written["parameters"] = str(atomic_write_text(req.export_out, exp.text))
        messages += [f"note: {note}" for note in exp.notes]
        messages += [f"warning: outside the firmware's limits: {v}" for v in exp.violations]
    for n, r in fits.items():
        messages += compass_warnings(n, r)
    for n, exc in zip(refused, errors, strict=True):
        messages.append(f"warning: compass {n} not calibrated (its parameters are not written): {_said(exc)}")
        messages += [f"  {line}" for line in exc.details]  # (details of the warning above: docs/cli.md, "Errors")
    return AllSensorsResult(fits, refused, comparison, messages, written)


#: the head of a compass's refusal (:func:`trimag.app._log_advice.log_refusal`): ``compass 2 (MAG[1]): ``
_HEAD = re.compile(r"^compass \d+ \([^)]*\): ")


def _none_fitted(refusals: dict[int, TrimagError]) -> tuple[str, list[str]]:
    """The refusal of a log none of whose compasses could be fitted: one verdict (the compasses' own when they
    all say the same, else the first's what-to-do), then each compass's verdict and its own details, and the
    details all of them share, once."""
    bodies = {n: _HEAD.sub("", str(e)) for n, e in refusals.items()}
    numbers = ", ".join(map(str, refusals))
    common = [d for d in next(iter(refusals.values())).details if all(d in e.details for e in refusals.values())]
    if len(set(bodies.values())) == 1:
        own = [f"compass {n}: {d}" for n, e in refusals.items() for d in e.details if d not in common]
        return f"every compass ({numbers}): {next(iter(bodies.values()))}", own + common
    first = next(iter(bodies.values()))
    do = first.rsplit("; ", 1)[-1] if "; " in first else "see each compass below"
    details: list[str] = []
    for n, e in refusals.items():
        details.append(str(e) if _HEAD.match(str(e)) else f"compass {n}: {e}")
        details += [f"  {d}" for d in e.details if d not in common]
    return f"no compass could be fitted ({numbers}; each below); {do}", details + common


def _fit_each(req: FitRequest, compasses: list[tuple[int, str]], fit_file: Any, *, outputs: bool = True
              ) -> tuple[dict[int, Any], dict[int, str], list[TrimagError]]:
    """Each compass fitted as ``--sensor N`` would fit it: ``(fits, refused: number -> reason, errors)``; without
    ``outputs`` nothing is written."""
    fits: dict[int, Any] = {}
    refused: dict[int, str] = {}
    errors: list[TrimagError] = []
    for number, name in compasses:
        one = dataclasses.replace(req, input=dataclasses.replace(req.input, sensor=name), export_to=None,
                                  export_out=None,
                                  **({"out": numbered(req.out, number), "report": numbered(req.report, number),
                                      "deviation_card": numbered(req.deviation_card, number)} if outputs else
                                     {"out": None, "report": None, "deviation_card": None, "policy": None}))
        try:
            fits[number] = fit_file(one)
        except TrimagError as exc:
            refused[number] = _said(exc, details=True)
            errors.append(exc)
    return fits, refused, errors


def _said(exc: TrimagError, *, details: bool = False) -> str:
    """A compass's refusal as the command says it (its verdict; with ``details``, its details too, in one line)."""
    return (f"{'cannot identify the model: ' if isinstance(exc, IdentifiabilityError) else ''}"
            f"{full_message(exc) if details else exc}")


def _motor_type(fit: Any) -> str | None:
    return (fit.calibration.diagnostics.get("firmware") or {}).get("motor_type")


def _heldout_rms(fit: Any) -> float:
    """The held-out RMS of the level a firmware fit chose (its levels table)."""
    rows = (fit.calibration.diagnostics.get("firmware") or {}).get("levels") or []
    chosen = [r["heldout_rms"] for r in rows if r.get("chosen") and r.get("heldout_rms") is not None]
    return float(chosen[0]) if chosen else float("inf")


def _one_motor_channel(req: FitRequest, compasses: list[tuple[int, str]], fits: dict[int, Any], fit_file: Any
                       ) -> dict[str, Any] | None:
    """The one motor channel of a vehicle whose compasses, each fitted with ``motor=auto``, chose different ones
    (the firmware's COMPASS_MOTCT / CAL_MAG_COMP_TYP is one parameter, issue 39): every compass fitted again with
    the motor term on each channel only (or none), and the channel of the least summed held-out RMS chosen.
    ``{"channel", "message"}``, or None when the compasses agree (or ``motor`` was given)."""
    from ._firmware import parse_motor

    if req.target is None or parse_motor(req.motor) != ("auto", None):
        return None
    chose = {n: _motor_type(r) for n, r in fits.items()}
    kinds = sorted({k for k in chose.values() if k is not None})
    if len(kinds) < 2:
        return None
    fitted = [(n, name) for n, name in compasses if n in fits]
    totals: dict[str, float] = {}
    for kind in kinds:
        each, refused, _ = _fit_each(dataclasses.replace(req, motor=f"auto={kind}"), fitted, fit_file, outputs=False)
        totals[kind] = float("inf") if refused else sum(_heldout_rms(r) for r in each.values())
    best = min(kinds, key=lambda k: totals[k])
    unit = (next(iter(fits.values())).calibration.diagnostics.get("firmware") or {}).get("unit", "")
    prefer = "; ".join(f"compass {n} {k or 'none'}" for n, k in chose.items())
    sums = ", ".join(f"{k} {totals[k]:.4g}" for k in kinds)
    return {"channel": best, "message": (
        f"one motor channel for the vehicle (the firmware's motor channel is one parameter for every compass): "
        f"fitted alone the compasses preferred different ones ({prefer}); {best} serves them best (summed held-out "
        f"RMS {sums} {unit}): every compass is fitted with the motor term on {best} (or none)")}


def _exportable(fits: dict[int, Any], req: FitRequest, messages: list[str]) -> dict[int, Any]:
    """The compasses whose parameters go to the parameter file: not one the policy rejected or whose unit its fit
    doubted, unless ``req.force`` (issue 41, item 9: the file was written when every compass was rejected). Each left
    out is said in ``messages``; none left: refused (exit 4 for a policy's rejection, else 2), no parameter file."""
    from .export import refuse_rejected

    kept: dict[int, Any] = {}
    left_out: list[TrimagError] = []
    for n, r in fits.items():
        try:
            forced = refuse_rejected(r.calibration, f"compass {n}", req.force)
        except TrimagError as exc:
            left_out.append(exc)
            messages.append(f"warning: {exc} (left out of {req.export_out})")
            continue
        kept[n] = r
        messages += [f"warning: compass {n}: {w}" for w in forced]
    if not kept:
        raise type(left_out[0])(f"no parameter file written ({req.export_out}): " + "; ".join(map(str, left_out)))
    return kept


def compass_warnings(number: int, fit: Any) -> list[str]:
    """Compass ``number``'s warnings and acceptance verdict, each naming it (as ``trimag fit --sensor N`` says
    them)."""
    out = [f"warning: compass {number}: {m.removeprefix('warning:').strip()}" for m in fit.messages
           if m.startswith("warning:")]
    verdict = fit.summary.get("acceptance")
    if verdict is not None:
        if verdict["not_evaluated"]:
            out.append(f"warning: compass {number}: policy rules not evaluated (the data cannot measure them): "
                       f"{', '.join(verdict['not_evaluated'])}")
        if not verdict["accepted"]:
            from ..vehicle.policy import failed_rules

            failed = "; ".join(failed_rules(verdict))
            out.append(f"warning: compass {number} rejected by the acceptance policy: {failed} (its calibration is "
                       "written, marked rejected)")
    return out


def _heading(field_: NDArray[np.float64], down: NDArray[np.float64]) -> NDArray[np.float64]:
    from ..vehicle.heading import tilt_compensated_heading

    return tilt_compensated_heading(field_, -down)


def _regressors(cal: Any, table: Any) -> dict[str, NDArray[np.float64]] | None:
    """The logged channels a calibration's regressor (motor) terms need, from the compass's own table."""
    if cal.regressors is None:
        return None
    return {name: table[name].to_numpy(dtype=np.float64) for name in cal.regressors["names"]}


def compare_compasses(fits: dict[int, Any]) -> dict[str, Any]:
    """Each compass's offset, fitted field magnitude and RMS, and its heading difference from the first compass
    (before: the onboard calibration; after: trimag's), on the first compass's time stamps within the other's
    span."""
    from ..vehicle.heading import heading_difference

    first = min(fits)
    ref = fits[first].samples.table
    t0 = ref["time_s"].to_numpy(dtype=np.float64)
    att = [c for c in ("pitch_deg", "roll_deg") if c in ref.columns]
    if len(att) == 2:
        from scipy.spatial.transform import Rotation

        pr = ref[att].to_numpy(dtype=np.float64)
        ok = np.isfinite(pr).all(axis=1)
        down = np.tile([0.0, 0.0, 1.0], (len(t0), 1))
        down[ok] = Rotation.from_euler("ZYX", np.column_stack([np.zeros(ok.sum()), pr[ok]]), degrees=True).inv() \
            .apply([0.0, 0.0, 1.0])
    else:
        down = np.tile([0.0, 0.0, 1.0], (len(t0), 1))
    views = {}
    for n, r in fits.items():
        table = r.samples.table
        t = table["time_s"].to_numpy(dtype=np.float64)
        order = np.argsort(t)
        after = r.calibration.apply(r.samples.field, regressors=_regressors(r.calibration, table))
        before = table[[f"mag_logged_{a}" for a in "xyz"]].to_numpy(dtype=np.float64)
        inside = (t0 >= t[order][0]) & (t0 <= t[order][-1])
        views[n] = {name: np.column_stack([np.interp(t0, t[order], v[order, k]) for k in range(3)])
                    for name, v in (("before", before), ("after", after))} | {"inside": inside}
    rows = []
    for n, r in sorted(fits.items()):
        cal = r.calibration
        row: dict[str, Any] = {"compass": n, "name": r.samples.log_info["sensor"], "offset": cal.offset.tolist(),
                               "field_magnitude": cal.stats.get("mean_norm_after"), "rms_after": cal.stats["rms_after"],
                               "method": cal.method}
        if n != first:
            both = views[n]["inside"] & views[first]["inside"]
            for when in ("before", "after"):
                d = heading_difference(_heading(views[n][when][both], down[both]),
                                       _heading(views[first][when][both], down[both]))
                row[f"heading_difference_{when}_deg"] = {"rms": float(np.sqrt(np.mean(d**2))),
                                                         "mean": float(np.mean(d)), "max": float(np.abs(d).max()),
                                                         "n": int(both.sum())}
        rows.append(row)
    return {"reference_compass": first, "level": len(att) != 2, "compasses": rows}


def comparison_lines(result: AllSensorsResult, unit: str) -> list[str]:
    """The comparison as a table, for the user."""
    c = result.comparison
    first = c["reference_compass"]
    lines = [f"{'compass':>8}  {'name':<22}{'method':<14}{'offset x':>10}{'y':>10}{'z':>10}{'|B| fitted':>12}"
             f"{'RMS':>8}   heading - compass {first}: before / after (RMS, mean, deg)"]
    for row in c["compasses"]:
        text = (f"{row['compass']:>8}  {row['name']:<22}{row['method']:<14}"
                + "".join(f"{v:10.4g}" for v in row["offset"])
                + f"{row['field_magnitude'] or float('nan'):12.5g}{row['rms_after']:8.3g}")
        if row["compass"] != first:
            b, a = row["heading_difference_before_deg"], row["heading_difference_after_deg"]
            text += f"   {b['rms']:.2f}, {b['mean']:+.2f} / {a['rms']:.2f}, {a['mean']:+.2f}"
        lines.append(text)
    lines.append(f"[{unit}; headings tilt-compensated with the log's roll and pitch]" if not c["level"] else
                 f"[{unit}; headings of a level vehicle: the log has no attitude]")
    return lines
