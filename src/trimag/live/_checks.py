"""What ``trimag live`` refuses before a session starts (exit 2), so that no recording is made that cannot be saved:
numbers that cannot work (a rate, interval, reference or port that is not finite and in range), an unknown unit,
outputs that cannot be written or would replace the replayed log, a method that needs more than the magnetometer's
samples (a gyroscope, attitudes, a known magnitude without ``--reference``), and a replayed log whose unit
contradicts the one given or whose fitted field contradicts ``--reference`` (checked as ``trimag fit`` checks
it).
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..app._checks import check_fitted_field, check_log_unit, check_unit
from ..app.requests import LiveRequest
from ..errors import TrimagInputError
from ..io import Samples
from ..io.atomic import same_file
from ..units import normalise_unit
from ..validation import check_reference_magnitude
from .server import check_port
from .session import samples_path

__all__ = ["MAX_INTERVAL_S", "check_method", "check_request", "replay_units"]

#: The longest wait between refits (seconds): a longer one would only leave the page without a fit.
MAX_INTERVAL_S = 3600.0


def check_request(request: LiveRequest) -> None:
    """Refuse a request that cannot give a saved recording (:class:`~trimag.errors.TrimagInputError`, exit 2)."""
    _ = request.source  # exactly one source
    _check_numbers(request)
    normalise_unit(request.units)
    out = Path(request.out)
    samples = samples_path(request.out, request.samples_out)
    if same_file(out, samples):
        raise TrimagInputError(f"`out` and `samples_out` are the same file ({out}); give two names")
    for what, path in (("out", out), ("samples_out", samples)):
        if request.replay is not None and same_file(path, Path(request.replay)):
            named = f"`{what}`" if what == "out" or request.samples_out is not None else (
                "the samples file (`samples_out`, by default beside `out`)")
            raise TrimagInputError(f"{named} would replace the replayed log {request.replay}; give another name")
        _check_writable(path, what)


def check_method(request: LiveRequest) -> None:
    """Refuse a model/method that ``live`` cannot feed (exit 2): it records the magnetometer's samples only, so a
    method that needs the gyroscope's rate (``gyro``) or an attitude per sample (``linear-vector``), or a known
    field magnitude when ``reference`` is not given, would never fit (the session ran to its end and wrote no
    calibration, exit 3)."""
    from ..estimators import make_estimator

    estimator = make_estimator(request.model, request.method, dict(request.options))
    needs = {"gyro": "the gyroscope's rate", "vector": "an attitude for every sample"}.get(estimator.reference_kind)
    if needs is not None:
        raise TrimagInputError(
            f"method {estimator.name!r} needs {needs}, which `trimag live` does not record: record with the default "
            "method, then fit the samples file with `trimag fit`")
    if estimator.requires_reference and request.reference is None:
        raise TrimagInputError(f"method {estimator.name!r} needs the field's magnitude: give `reference=F` in the "
                               "data's unit")


def _check_numbers(request: LiveRequest) -> None:
    if request.rate is not None and not (math.isfinite(request.rate) and request.rate > 0):
        raise TrimagInputError(f"`rate` must be a finite positive number of samples per second; got {request.rate}")
    if not (math.isfinite(request.interval) and 0 <= request.interval <= MAX_INTERVAL_S):
        raise TrimagInputError(f"`interval` must be 0-{MAX_INTERVAL_S:g} seconds between refits; got "
                               f"{request.interval}")
    if request.reference is not None:
        check_reference_magnitude(request.reference)
    if request.serial is not None and request.baud <= 0:
        raise TrimagInputError(f"`baud` must be positive; got {request.baud}")
    check_port(request.port)


def _check_writable(path: Path, what: str) -> None:
    """Refuse an output that cannot be written: a folder, or a place where no file can be created (tried)."""
    if path.is_dir():
        raise TrimagInputError(f"`{what}` {path} is a folder; give a file name")
    folder = path.parent
    while not folder.exists() and folder != folder.parent:  # the writer creates the missing folders
        folder = folder.parent
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".probe", dir=folder)
    except OSError as exc:
        raise TrimagInputError(f"cannot write `{what}` {path}: {exc.strerror or exc} in {folder}") from None
    os.close(fd)
    os.unlink(probe)


def replay_units(samples: Samples, request: LiveRequest) -> tuple[str | None, list[str]]:
    """The unit of a replayed log, checked as ``trimag fit`` checks it: the log's own (a vehicle log) or its
    column headers' against ``units``, the samples' magnitude against the unit and ``reference``; returns the unit
    (None when unknown) and the messages (warnings start with ``warning:``)."""
    units = check_log_unit(request.units, samples.log_info, request.columns)
    units, messages = check_unit(samples, units, request.reference, None)
    if units is not None and request.reference is not None:
        _check_replayed_field(samples, units, request)
    return units, messages


def _check_replayed_field(samples: Samples, units: str, request: LiveRequest) -> None:
    """A known ``reference`` and a replayed log: the unit is judged on the fitted field, as ``trimag fit`` judges
    it (:func:`~trimag.app._checks.check_fitted_field`, exit 2 with fit's message), so that a session in the wrong
    unit is not recorded. A log that cannot be fitted yet is left to the session (its page says why)."""
    import warnings

    import numpy as np

    from ..errors import TrimagError, TrimagWarning
    from ..fitting import fit

    B = np.asarray(samples.field, dtype=np.float64)
    B = B[np.isfinite(B).all(axis=1)]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TrimagWarning)
            cal = fit(B, request.model, request.method, request.reference, units=units, **dict(request.options))
    except (TrimagError, ValueError, np.linalg.LinAlgError, FloatingPointError):
        return
    check_fitted_field(cal, units)


@contextmanager
def output_lock(request: LiveRequest) -> Iterator[None]:
    """Hold an exclusive lock on the session's outputs (the calibration and the samples file) while it runs (issue
    41, item 15: two sessions with the same ``out`` left one's calibration beside the other's samples); a second
    session on either output is refused (exit 2) before anything starts. The lock is ``fcntl.flock`` on a hidden
    ``.NAME.lock`` beside each output, removed when the session ends (the kernel drops the lock of a killed one)."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock (the outputs are still written atomically)
        yield
        return
    held: list[tuple[Path, int]] = []
    try:
        for path in (Path(request.out), samples_path(request.out, request.samples_out)):
            lock = path.with_name(f".{path.name}.lock")
            lock.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                raise TrimagInputError(f"another trimag live session is writing {path} (it holds {lock}): give "
                                       "another -o (and --samples-out), or stop that session first") from None
            held.append((lock, fd))
        yield
    finally:
        for lock, fd in reversed(held):
            lock.unlink(missing_ok=True)
            os.close(fd)
