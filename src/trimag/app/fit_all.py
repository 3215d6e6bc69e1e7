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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import IdentifiabilityError, TrimagError, TrimagInputError
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
    compasses = _compasses(req)
    outputs: dict[str, str | Path | None] = {"export_out": req.export_out}
    for number, _ in compasses:  # every file this run can write, before it writes one
        outputs.update({f"{what} of compass {number}": numbered(getattr(req, what), number)
                        for what in ("out", "report", "deviation_card")})
    check_distinct_outputs(fit_inputs(req), outputs)
    fits: dict[int, Any] = {}
    refused: dict[int, str] = {}
    errors: list[TrimagError] = []
    messages: list[str] = []
    for number, name in compasses:
        one = dataclasses.replace(req, input=dataclasses.replace(req.input, sensor=name), out=numbered(req.out, number),
                                  report=numbered(req.report, number),
                                  deviation_card=numbered(req.deviation_card, number), export_to=None,
                                  export_out=None)
        try:
            fits[number] = fit_file(one)
        except TrimagError as exc:
            refused[number] = f"{'cannot identify the model: ' if isinstance(exc, IdentifiabilityError) else ''}{exc}"
            errors.append(exc)
    if not fits:
        kind = IdentifiabilityError if any(isinstance(e, IdentifiabilityError) for e in errors) else TrimagInputError
        raise kind("no compass of this log could be fitted: " + "; ".join(
            f"compass {n}: {why}" for n, why in refused.items()))
    comparison = compare_compasses(fits)
    written = {f"calibration {n}": r.written["calibration"] for n, r in fits.items() if "calibration" in r.written}
    if req.export_to is not None and req.export_out is not None:
        from ..io.atomic import atomic_write_text
        from ..io.export_instances import export_instances

        try:
            exp = export_instances([(r.calibration, n) for n, r in fits.items()], req.export_to)
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
    for n, why in refused.items():
        messages.append(f"warning: compass {n} not calibrated (its parameters are not written): {why}")
    return AllSensorsResult(fits, refused, comparison, messages, written)


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
