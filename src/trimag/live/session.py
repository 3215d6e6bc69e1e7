"""The state of a live recording: the samples received, the fit refreshed on a background thread, and the guidance
the page and ``GET /status`` show (coverage, RMS, identifiability, the next orientations, "good enough").

The reader thread appends samples as they arrive; the fit thread refits every ``interval`` seconds on a snapshot of
all the samples so far (:func:`trimag.fit`), so a source that floods faster than the fit only makes the snapshots
larger, never blocks the reader or the page. :meth:`LiveSession.status` returns the last computed state at once.
"""

from __future__ import annotations

import dataclasses
import io
import math
import threading
import time
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..app._checks import check_fitted_field
from ..calibration import Calibration, SensorRecord
from ..errors import IdentifiabilityError, TrimagError, TrimagInputError, TrimagWarning
from ..fitting import fit
from ..io.atomic import atomic_write_text
from ..quality.diagnostics import (
    _axis_name,
    coverage_advice,
    data_coverage,
    describe_directions,
    fibonacci_sphere,
    raw_direction_geometry,
)
from ..units import normalise_unit
from ..vehicle.policy import DEFAULT_LIMITS, check_policy, failed_rules
from .sources import Batch

__all__ = ["GOOD_ENOUGH_INFLATION", "GOOD_ENOUGH_UNSEEN_DEG", "MIN_FIT_SAMPLES", "LiveSession"]

#: Samples before the first fit is tried.
MIN_FIT_SAMPLES = 30
#: "Good enough" also needs the worst-determined parameter combination within this many times the standard
#: deviation a full sphere of the same length gives (``std_inflation_vs_full_sphere``). Measured: 1.0-1.3 for full
#: spheres, 1.6-6.5 on five real logs (1.7 on the bundled demo log), 10-11 for one hemisphere.
GOOD_ENOUGH_INFLATION = 8.0
#: ... and no cap of the sphere of directions unseen beyond this angle (degrees) from the nearest covered cell.
GOOD_ENOUGH_UNSEEN_DEG = 45.0
#: Points of each cloud sent to the page (evenly spread over the samples).
PAGE_POINTS = 1500
#: Entries kept of the history (samples, coverage, RMS after each fit).
HISTORY = 400


def _finite(value: Any) -> Any:
    """``value`` with NaN and infinities as None (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, np.generic):
        return _finite(value.item())
    return value


def next_orientations(geometry: Mapping[str, Any] | None) -> str:
    """Plain words: where the field has not been seen from yet, and how to turn the sensor to see it.

    ``geometry`` is a :func:`trimag.quality.diagnostics.sphere_coverage` result (of corrected or raw directions).
    """
    if geometry is None or geometry.get("cone_axis") is None:
        return "turn the sensor slowly about all three axes (tumble it through every attitude)"
    never = geometry.get("never_seen_axis")
    if never is None:
        return "every region of the sphere of field directions has been seen: keep turning to fill it evenly, or save"
    axis = _axis_name(never)
    within = geometry.get("never_seen_within_deg") or 0.0
    if axis.endswith(" axis"):
        side = axis.removesuffix(" axis")
        region = f"the {side} hemisphere" if within >= 60.0 else f"a cap of about {within:.0f} deg around the {axis}"
        words, target = f"its {axis}", f"the sensor's {axis}"
    else:
        region, target, words = f"around {_direction_in_words(never)}", "it", "this direction"
    return (f"the field has not been seen from {region} yet (no sample within {within:.0f} deg of {target}). "
            f"Next: turn the sensor so that {words} points along the Earth's field (towards magnetic north and, "
            "in the northern hemisphere, steeply down; in the southern, up), then rock it around that attitude")


def _direction_in_words(direction: Any) -> str:
    """A direction in the sensor's frame said with its own axes (no vector): "the sensor's -y axis, tilted towards
    -x (and a little towards +z)", or "midway between the sensor's -x and +y axes" (issue 42)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    order = np.argsort(-np.abs(d))
    names = [f"{'+' if d[k] >= 0 else '-'}{'xyz'[k]}" for k in order]
    sizes = np.abs(d[order])
    if sizes[1] >= 0.6 * sizes[0]:
        text = f"the direction midway between the sensor's {names[0]} and {names[1]} axes"
    elif sizes[1] >= 0.35:
        text = f"the sensor's {names[0]} axis, tilted towards {names[1]}"
    else:
        text = f"the sensor's {names[0]} axis" + (f", tilted a little towards {names[1]}" if sizes[1] >= 0.15 else "")
    if sizes[2] >= 0.15:
        text += f" (and a little towards {names[2]})"
    return text


class LiveSession:
    """Samples received so far, the latest fit and the guidance drawn from it.

    Parameters
    ----------
    model, method : str
        Error model and method for :func:`trimag.fit` (``"ellipsoid"`` and its default method by default).
    units : str, optional
        The samples' unit; the source's own (a log's header, a MAVLink message) when None.
    reference : float, optional
        The field magnitude in ``units`` (unknown when None: the fit estimates it).
    limits : mapping, optional
        Acceptance limits (:data:`trimag.vehicle.policy.DEFAULT_LIMITS` by default) for ``good_enough``.
    interval : float
        Seconds between refits.
    options : mapping, optional
        Method options for :func:`trimag.fit`.
    """

    def __init__(self, *, model: str = "ellipsoid", method: str | None = None, units: str | None = None,
                 reference: float | None = None, limits: Mapping[str, float] | None = None, interval: float = 0.25,
                 options: Mapping[str, Any] | None = None, source: str = "",
                 sensor: SensorRecord | None = None) -> None:
        self.model, self.method, self.units = model, method, units
        #: the sensor the samples come from, recorded in the saved calibration (its unit: the session's)
        self.sensor = sensor
        self.reference, self.interval = reference, interval
        self.limits = dict(DEFAULT_LIMITS if limits is None else limits)
        self.options = dict(options or {})
        self.source = source
        self._lock = threading.Lock()
        self._fit_lock = threading.Lock()
        self._buffer = np.empty((4096, 3))
        self._n = 0
        self._garbage = 0
        self._source_state = "waiting"
        self._source_message = ""
        self._started = time.monotonic()
        self._stop = threading.Event()
        self._new_data = threading.Event()
        self._fit_state: dict[str, Any] = {}
        self._fitted_n = 0
        self._history: list[list[float | None]] = []
        self._latest: tuple[Calibration | None, int] = (None, 0)  # the last calibration and its number of samples
        self._save_lock = threading.Lock()
        self._after_stop = 0
        self._threads: list[threading.Thread] = []
        self._n_fits = 0

    @property
    def calibration(self) -> Calibration | None:
        """The latest calibration fitted (None before the first)."""
        return self._latest[0]

    # -- input -------------------------------------------------------------------------------------------------
    def add(self, batch: Batch) -> None:
        """Append a batch of samples (thread-safe); non-finite rows count as garbage."""
        x = np.asarray(batch.samples, dtype=np.float64).reshape(-1, 3)
        good = np.isfinite(x).all(axis=1)
        with self._lock:
            if self._stop.is_set():  # the recording has stopped: what arrives now is not part of it
                self._after_stop += len(x)
                return
            if batch.units is not None:
                self._check_units(batch.units, batch.units_stated_by)
            self._garbage += int(batch.n_garbage) + int((~good).sum())
            x = x[good]
            need = self._n + len(x)
            if need > len(self._buffer):
                grown = np.empty((max(need, 2 * len(self._buffer)), 3))
                grown[: self._n] = self._buffer[: self._n]
                self._buffer = grown
            self._buffer[self._n : need] = x
            self._n = need
            if self._source_state == "waiting":
                self._source_state = "running"
        if len(x):
            self._new_data.set()

    def _check_units(self, stated: str, by: str) -> None:
        """The unit a source states (a header, a MAVLink message) is the samples' unit: taken when none was given;
        a different one given is refused as ``trimag fit`` refuses it, which ends the source."""
        if self.units is None:
            self.units = stated
        elif normalise_unit(self.units) != normalise_unit(stated):
            raise TrimagInputError(f"{by} {stated} but `units={self.units}`; give the data's real unit")

    def samples(self) -> NDArray[np.float64]:
        """A copy of every sample received so far, shape (N, 3)."""
        return self._snapshot()[0]

    def _snapshot(self) -> tuple[NDArray[np.float64], int, str]:
        """One consistent snapshot: every sample so far (a copy, (N, 3)), the lines not understood, the unit."""
        with self._lock:
            return self._buffer[: self._n].copy(), self._garbage, self.units or "unknown"

    def end(self, message: str = "the source ended") -> None:
        """Mark the source as ended (no more samples will come)."""
        with self._lock:
            self._source_state = "ended"
            self._source_message = message
        self._new_data.set()

    def consume(self, batches: Iterable[Batch]) -> None:
        """Feed every batch of ``batches`` until it ends or :meth:`stop`; any error of the source ends it (shown as
        the source's message), never the session."""
        try:
            for batch in batches:
                if self._stop.is_set():
                    break
                self.add(batch)
            if self._stop.is_set():
                self.end("stopped")
                return
        except TrimagError as exc:
            self.end(f"the source failed: {exc}")
        except Exception as exc:  # a serial port unplugged, a socket closed: shown, not fatal
            self.end(f"the source failed: {type(exc).__name__}: {exc}")
        else:
            self.end("the source ended")

    # -- threads -----------------------------------------------------------------------------------------------
    def start(self, batches: Iterable[Batch]) -> None:
        """Start the reader thread (on ``batches``) and the fit thread."""
        reader = threading.Thread(target=self.consume, args=(batches,), name="trimag-live-reader", daemon=True)
        fitter = threading.Thread(target=self._fit_loop, name="trimag-live-fit", daemon=True)
        self._threads = [reader, fitter]
        reader.start()
        fitter.start()

    def stop(self) -> None:
        """Stop the recording: no sample is added after this (the reader stops at its next batch, the samples it
        still brings are counted as ``samples_after_stop``), and the fit thread ends."""
        with self._lock:
            self._stop.set()
        self._new_data.set()
        for t in self._threads:
            if t.name == "trimag-live-fit":
                t.join(timeout=30)

    @property
    def ended(self) -> bool:
        """Whether the source has ended."""
        with self._lock:
            return self._source_state == "ended"

    @property
    def up_to_date(self) -> bool:
        """Whether the latest fit used every sample received (or no fit is possible yet)."""
        with self._lock:
            return self._fitted_n == self._n

    def _fit_loop(self) -> None:
        while not self._stop.is_set():
            self._new_data.wait(timeout=self.interval)
            self._new_data.clear()
            if self._stop.is_set():
                return
            with self._lock:
                stale = self._n != self._fitted_n
            if stale:
                self.refit()
            self._stop.wait(self.interval)

    # -- the fit -----------------------------------------------------------------------------------------------
    def refit(self, B: NDArray[np.float64] | None = None) -> Calibration | None:
        """Fit ``B`` (every sample received so far when None) now, on the calling thread, and show it (unless the
        page already shows a fit of more samples); returns the calibration of exactly ``B`` (None when ``B`` cannot
        identify the model yet)."""
        with self._fit_lock:
            if B is None:
                B = self.samples()
            t0 = time.monotonic()
            state = self._fit(B)
            state["fit_seconds"] = time.monotonic() - t0
            cal = state.pop("calibration", None)
            with self._lock:
                if cal is not None and len(B) >= self._latest[1]:
                    self._latest = (cal, len(B))
                if len(B) >= self._fitted_n:  # samples only grow: a smaller snapshot is an older one
                    self._fit_state = state
                    self._fitted_n = len(B)
                    self._history.append([len(B), state.get("coverage_fraction"), state.get("rms_after")])
                    del self._history[:-HISTORY]
                self._n_fits += 1
            return cal

    def _fit(self, B: NDArray[np.float64]) -> dict[str, Any]:
        units = self.units or "unknown"
        what = f"the {self.model} model"
        state: dict[str, Any] = {"fitted": False, "fitted_samples": len(B), "identifiable": False,
                                 "converged": False, "fit_message": "", "rms_before": None, "rms_after": None}
        if len(B) < MIN_FIT_SAMPLES:
            state["fit_message"] = f"waiting for {MIN_FIT_SAMPLES} samples"
            state["next_orientations"] = next_orientations(None)
            state["coverage"] = None
            return state
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", TrimagWarning)
                cal = fit(B, self.model, self.method, self.reference, units=units, **self.options)
        except IdentifiabilityError as exc:
            state["fit_message"] = f"cannot identify the model yet: {exc}"
            state.update(self._raw_guidance(B, what))
            return state
        except TrimagError as exc:
            state["fit_message"] = f"no fit yet: {exc}"
            state.update(self._raw_guidance(B, what))
            return state
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
            state["fit_message"] = f"no fit yet: {type(exc).__name__}: {exc}"
            state.update(self._raw_guidance(B, what))
            return state
        if self.reference is not None and units != "unknown":
            try:  # the unit judged on the fitted field, as trimag fit judges it: a 1000x gain is no calibration
                check_fitted_field(cal, units)
            except TrimagInputError as exc:
                state["fit_message"] = f"no fit: {exc}"
                state.update(self._raw_guidance(B, what))
                return state
        stats, diag = cal.stats, cal.diagnostics
        coverage = diag.get("coverage") or {}
        ident = diag.get("identifiability") or {}
        warn_texts = [str(w.message) for w in caught if issubclass(w.category, TrimagWarning)]
        verdict = check_policy(cal, self.limits, reference_F=self.reference)
        inflation = ident.get("std_inflation_vs_full_sphere")
        unseen = coverage.get("never_seen_within_deg")
        identifiable = not warn_texts and ident.get("warning") is None
        reasons: list[str] = []
        if not identifiable:
            reasons.append("poorly identified: " + "; ".join(warn_texts or [str(ident.get("warning"))]))
        reasons += failed_rules(verdict, digits=3)
        if not verdict["passed"] and not verdict["failed"]:
            reasons.append("no rule of the acceptance policy could be evaluated")
        if inflation is not None and not inflation <= GOOD_ENOUGH_INFLATION:
            reasons.append(f"the worst-determined parameters ({', '.join(ident.get('weakest_combination') or [])}) "
                           f"have {inflation:.3g}x the standard deviation of a full sphere (at most "
                           f"{GOOD_ENOUGH_INFLATION:g}x)")
        if unseen is not None and unseen > GOOD_ENOUGH_UNSEEN_DEG:
            reasons.append(f"a region of field directions {unseen:.0f} deg across is unseen (at most "
                           f"{GOOD_ENOUGH_UNSEEN_DEG:g} deg)")
        converged = bool(stats.get("converged", True))
        if not converged:
            reasons.append("the fit did not converge")
        corrected = cal.apply(B[self._page_index(len(B))])
        # the fit keeps the coverage's figures, not its cells: the map counts them again, as the fit did (the data's
        # directions, trimag.quality.diagnostics.data_coverage: the same cells as the number)
        coverage = {**coverage, "cell_counts": data_coverage(B)["cell_counts"]}
        state.update({
            "fitted": True, "calibration": cal, "identifiable": identifiable, "converged": converged,
            "rms_before": stats.get("rms_before"), "rms_after": stats.get("rms_after"),
            "coverage_fraction": coverage.get("fraction"), "coverage": coverage,
            "coverage_description": describe_directions(coverage) if coverage.get("cone_axis") else "",
            "next_orientations": next_orientations(coverage),
            "weakest_combination": ident.get("weakest_combination"), "std_inflation_vs_full_sphere": inflation,
            "condition_number": diag.get("condition_number"), "warnings": warn_texts,
            "good_enough": not reasons, "not_good_enough_because": reasons, "acceptance": verdict,
            "fit_message": f"{cal.model} fit by {cal.method}",
            "matrix": np.asarray(cal.matrix).tolist(), "offset": np.asarray(cal.offset).tolist(),
            "param_std": (cal.uncertainty or {}).get("param_std"), "points_corrected": np.round(corrected, 6).tolist(),
            "fitted_magnitude": (cal.reference or {}).get("fitted_radius") or stats.get("mean_norm_after"),
        })
        return state

    def _raw_guidance(self, B: NDArray[np.float64], what: str) -> dict[str, Any]:
        """Coverage and advice from the raw samples when no fit is possible (a sphere fitted to them)."""
        try:
            geometry = raw_direction_geometry(B, self.reference)
            advice = coverage_advice(B, self.reference, what=what)
        except Exception:
            geometry, advice = None, next_orientations(None)
        return {"coverage": geometry, "coverage_fraction": (geometry or {}).get("fraction"),
                "next_orientations": advice if geometry is None or geometry.get("shape") != "surround"
                else next_orientations(geometry),
                "good_enough": False, "not_good_enough_because": ["no calibration can be fitted yet"]}

    @staticmethod
    def _page_index(n: int) -> NDArray[np.int64]:
        return np.linspace(0, n - 1, min(n, PAGE_POINTS)).astype(np.int64) if n else np.empty(0, np.int64)

    # -- output ------------------------------------------------------------------------------------------------
    def status(self, *, points: bool = True) -> dict[str, Any]:
        """The state as JSON-ready data: ``n_samples``, ``n_garbage``, ``coverage_fraction``, ``rms_before``,
        ``rms_after``, ``converged``, ``identifiable``, ``next_orientations``, ``good_enough`` (and why not),
        the source's state, and with ``points`` the raw and corrected clouds (a subsample) and the coverage cells."""
        with self._lock:
            n, garbage = self._n, self._garbage
            state = dict(self._fit_state)
            raw = self._buffer[self._page_index(n)].copy() if points else None
            out: dict[str, Any] = {
                "n_samples": n, "n_garbage": garbage, "units": self.units or "unknown", "model": self.model,
                "source": self.source, "source_state": self._source_state, "source_message": self._source_message,
                "elapsed_s": time.monotonic() - self._started, "n_fits": self._n_fits,
                "fit_lag_samples": n - self._fitted_n, "history": [list(h) for h in self._history],
                "samples_after_stop": self._after_stop,
            }
        coverage = state.pop("coverage", None) or {}
        corrected = state.pop("points_corrected", None)
        out.update({
            "fitted_samples": state.get("fitted_samples", 0), "coverage_fraction": state.get("coverage_fraction"),
            "rms_before": state.get("rms_before"), "rms_after": state.get("rms_after"),
            "converged": state.get("converged", False), "identifiable": state.get("identifiable", False),
            "next_orientations": state.get("next_orientations", next_orientations(None)),
            "good_enough": state.get("good_enough", False),
            "up_to_date": out["fit_lag_samples"] == 0 and self._n_fits > 0,
            **{k: v for k, v in state.items() if k not in out},
        })
        if points:
            assert raw is not None
            out["points_raw"] = np.round(raw, 6).tolist()
            out["points_corrected"] = corrected
            out["coverage_cells"] = coverage.get("cell_counts")
            out["coverage_centres"] = (np.round(fibonacci_sphere(int(coverage["n_cells"])), 5).tolist()
                                       if coverage.get("n_cells") else None)
            out["coverage_min_count"] = coverage.get("min_count")
            out["never_seen_axis"] = coverage.get("never_seen_axis")
        return _finite(out)

    def save(self, out: str | Path, samples_out: str | Path | None = None) -> dict[str, str]:
        """Write one snapshot of the recorded samples (CSV ``x,y,z``, each name with the unit when it is known:
        ``x_G``, so that every command reads the file in its unit) and the calibration fitted to exactly that
        snapshot (JSON), each atomically, the samples first; the fit is redone on the snapshot unless the latest
        one used the same samples. Saves run one at a time. Returns what was written (the calibration is missing
        when the samples cannot identify the model)."""
        out = Path(out)
        target = samples_path(out, samples_out)
        with self._save_lock:
            B, garbage, units = self._snapshot()
            text = io.StringIO()
            names = ",".join(f"{axis}_{units}" if units != "unknown" else axis for axis in "xyz")  # x_G: the unit
            text.write(f"# trimag live recording ({self.source}); unit {units}\n{names}\n")
            np.savetxt(text, B, delimiter=",", fmt="%.17g")
            try:
                written = {"samples": str(atomic_write_text(target, text.getvalue()))}
            except OSError as exc:  # a full disk: the recording is kept elsewhere, and both places named
                kept = _rescue(text.getvalue())
                where = (f"the {len(B)} samples are kept in {kept}" if kept is not None else
                         f"the {len(B)} samples could not be kept anywhere (the temporary folder and the home folder "
                         "failed too)")
                raise TrimagInputError(f"cannot write the samples to {target}: {exc.strerror or exc}; {where}; free "
                                       "some space (or give another -o) and fit them with trimag fit") from None
            with self._lock:
                cal, n = self._latest
            if cal is None or n != len(B):  # samples only grow: the same count is the same samples
                cal = self.refit(B)
            if cal is not None:
                cal = cal.with_stats(n_samples=len(B), n_dropped=garbage)
                if self.sensor is not None:
                    cal = cal.with_sensor(dataclasses.replace(self.sensor, unit=units))
                try:
                    written["calibration"] = str(atomic_write_text(out, cal.to_json() + "\n"))
                except OSError as exc:
                    raise TrimagInputError(f"cannot write the calibration to {out}: {exc.strerror or exc}; the "
                                           f"{len(B)} samples are in {target}: fit them again with trimag fit "
                                           f"{target}") from None
            return written


def _rescue(text: str) -> Path | None:
    """Write a recording's samples (CSV ``text``) to a new file in the temporary folder, else the home folder, when
    their own file cannot be written (issue 41, item 7: a full disk lost the recording); the path, or None when
    neither place takes them."""
    import os
    import tempfile

    for folder in (tempfile.gettempdir(), str(Path.home())):
        try:
            fd, name = tempfile.mkstemp(prefix=f"trimag-live-{time.strftime('%Y%m%d-%H%M%S')}-",
                                        suffix="-samples.csv", dir=folder)
        except OSError:
            continue
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(text)
            return Path(name)
        except OSError:
            Path(name).unlink(missing_ok=True)
    return None


def samples_path(out: str | Path, samples_out: str | Path | None = None) -> Path:
    """Where the samples are saved: ``samples_out``, else ``CAL-samples.csv`` beside the calibration ``out``."""
    if samples_out is not None:
        return Path(samples_out)
    out = Path(out)
    return out.with_name(out.stem + "-samples.csv")
