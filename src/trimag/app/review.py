"""``trimag review``: what the compasses of a flight did, and the parameters to hand over (issue 40; docs/review.md).

:class:`FlightReview` reads an autopilot log once and answers what the review page (:mod:`trimag.live.review`) and
the HTML report (``trimag fit LOG --target T --report report.html``) show:

- :meth:`~FlightReview.overview`: the flight (attitude, throttle, current against time), every compass side by side
  (device, rate, gaps, the log's calibration, health) and the choices (level, motor channel, yaw source);
- :meth:`FlightReview.fit`: every compass fitted by :func:`trimag.app.fit_file` (the command line's own fit, with
  ``rows`` the chosen time range) at the chosen level, motor term and yaw source; the rows outside the range are held
  out and judged; per compass (:meth:`~FlightReview.compass_result`) the level table, the halves check, the heading
  check, the verdict and the figures: expected (IGRF rotated by the attitude, with the board trim) against measured
  body field, field length with the motor channel beside it, the heading change;
- :meth:`~FlightReview.download`: the parameter file of one or all compasses exactly as ``trimag export`` writes it
  (:func:`trimag.io.export_instances.export_instances`), or a calibration's JSON.

Nothing is fitted, corrected or exported a second time here: the figures are Plotly figure specifications (plain
JSON) the page and the report draw with Plotly's own ``plotly.min.js`` (the ``review`` extra).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from ..calibration import Calibration
from ..errors import IdentifiabilityError, TrimagError, TrimagInputError
from ._flight import DISPLAY_POINTS, LEVELS, MOTORS, CompassResult, FlightLog, plotly_js, report_html

__all__ = ["DISPLAY_POINTS", "LEVELS", "MOTORS", "CompassResult", "FlightReview", "plotly_js", "report_html"]


class FlightReview(FlightLog):
    """An autopilot log under review: read once (:class:`FlightLog`), fitted on request.

    Parameters
    ----------
    path : str or Path
        A log ``trimag fit`` reads (DataFlash ``.bin``/``.log``, ``.tlog``, ULog, ``.px4log``), or a table (CSV,
        ...) with its attitude columns: one compass, fitted as ``trimag fit FILE --attitude-columns ...``.
    fmt : str, optional
        The log's format when its extension does not say.
    target : str, optional
        ``"ardupilot"`` or ``"px4"``; default: the log's own firmware.
    igrf_spec : str, optional
        ``LAT,LON,ALT_M,DATE`` for a log without a GPS fix.
    units, columns, attitude_columns, time_column : str, optional
        A table's unit and columns (``trimag fit``'s ``--units``, ``--columns``, ``--attitude-columns``; the time
        column in seconds): by default the usual names (yaw/pitch/roll, time_s/time/t).
    """

    def fit(self, start_s: float | None = None, stop_s: float | None = None, level: str = "auto",
            motor: str = "auto", yaw_source: str = "auto", compasses: Sequence[int] | None = None,
            progress: Callable[[str], None] | None = None) -> dict[int, CompassResult]:
        """Fit every compass (or ``compasses``) over ``[start_s, stop_s]`` (default: the whole log) with
        :func:`trimag.app.fit_file`; a compass the data cannot calibrate gets its refusal (the command line's exit
        code and line), not an exception."""
        from .fit import fit_file

        if level not in LEVELS:
            raise TrimagInputError(f"`level` must be one of {', '.join(LEVELS)}; got {level!r}")
        if motor not in MOTORS:
            raise TrimagInputError(f"`motor` must be one of {', '.join(MOTORS)}; got {motor!r}")
        if yaw_source not in self.yaw_sources():
            raise TrimagInputError(f"`yaw_source` must be one of {', '.join(self.yaw_sources())} for this log; got "
                                   f"{yaw_source!r}")
        lo, hi = self.span_s
        start = lo if start_s is None else float(start_s)
        stop = hi if stop_s is None else float(stop_s)
        if not (np.isfinite(start) and np.isfinite(stop) and stop > start):
            raise TrimagInputError(f"the range to fit must run forward in time; got {start_s}..{stop_s} s")
        numbers = [m.number for m in self.log.magnetometers] if compasses is None else list(compasses)
        results: dict[int, CompassResult] = {}
        for number in numbers:
            if progress is not None:
                progress(f"fitting compass {number} of {len(numbers)} ({start:.1f}..{stop:.1f} s, level {level}, "
                         f"motor {motor})")
            req = self.request(number, start, stop, level, motor, yaw_source)
            result = CompassResult(number, None, rows=str(req.input.rows), command=self.command(req))
            if not self.target:  # shown, not fitted: the firmware is the user's to name
                result.error = (f"error: a {self.log.format} names no firmware whose parameters to fit: give --target "
                                "ardupilot or --target px4")
                result.exit_code = 2
                results[number] = result
                continue
            try:
                fitted = fit_file(req)
            except IdentifiabilityError as exc:
                result.error, result.exit_code = f"cannot identify the model: {exc}", exc.exit_code
            except TrimagError as exc:
                result.error, result.exit_code = f"error: {exc}", exc.exit_code
            else:  # the calibration as its JSON reads back: what `trimag export CAL.json` is given
                cal = Calibration.from_json(fitted.calibration.to_json())
                result.calibration, result.summary, result.messages = cal, fitted.summary, fitted.messages
            results[number] = result
        with self._lock:
            self.results.update(results)
            self.choice = {"start_s": start, "stop_s": stop, "level": level, "motor": motor,
                           "yaw_source": yaw_source}
        return results
