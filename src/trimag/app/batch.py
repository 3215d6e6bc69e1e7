"""Batch calibration: fit every log matched by a glob (a fleet of sensors, or many runs of one).

Each file is fitted independently with :func:`trimag.app.fit_file` (one :class:`~trimag.app.requests.FitRequest`
per file; same reading rules, references and options as ``trimag fit``), its
:class:`~trimag.calibration.Calibration` written to ``OUT/<name>.json``, and one row per file collected into a
summary table written as ``OUT/summary.csv`` and, with pyarrow (the ``parquet`` extra), ``OUT/summary.parquet``.
A file that cannot be read or fitted gets a row with its error; the others go on.

The work runs through :func:`trimag.parallel.map_trials`: in this process (``workers=1``), on a local pool of
worker processes (``workers > 1``, nothing to start, no Dask needed), or on a ``dask.distributed`` cluster
(``scheduler=ADDRESS``, the ``batch`` extra; the workers must see the same file system paths).

A worker process that dies (the kernel's out-of-memory killer, a crash in a C library) costs only the file it was
fitting: that file's row says so, the others are fitted, the summary is written (issue 33, item 4). The input limits
in force (:mod:`trimag.io.limits`) hold in every worker; decompressed copies go to a temporary folder of this
process, removed at the end whatever happened to the workers. A file that fails leaves no calibration in the output
folder (an earlier run's is removed: it would pass for this input's).
"""

from __future__ import annotations

import dataclasses
import glob
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import pandas as pd

from ..errors import IdentifiabilityError, TrimagError, TrimagInputError, out_of_memory_message
from ..io.atomic import atomic_path, atomic_write_text, check_distinct_outputs
from ..io.limits import InputLimits, current_limits, input_limits
from .requests import FitRequest

__all__ = ["SUMMARY_COLUMNS", "BatchResult", "calibration_names", "expand_inputs", "fit_batch", "fit_one"]

#: Columns of the summary table, in order.
SUMMARY_COLUMNS = (
    "file", "n", "n_used", "rms_before", "rms_after", "units", "converged", "warnings", "error", "error_details",
    "error_type", "calibration", "seconds", "accepted", "rejected_by", "sensor",
)


@dataclass
class BatchResult:
    """What :func:`fit_batch` produced.

    Attributes
    ----------
    table : pandas.DataFrame
        One row per input file, columns :data:`SUMMARY_COLUMNS` (``rms_*`` in each file's unit, which ``units``
        says; empty when the file failed; ``error`` holds the verdict (what ``trimag fit`` says on its first
        line), ``error_details`` the figures behind it (its indented lines, joined by "; "), ``error_type`` ``"input"``,
        ``"identifiability"`` or ``"internal"``; ``accepted`` the acceptance policy's verdict, empty without a
        policy, and ``rejected_by`` the rules that failed, as ``trimag fit --policy`` gives them; ``sensor`` the
        sensor each calibration belongs to, :meth:`SensorRecord.describe <trimag.calibration.SensorRecord.describe>`).
    written : dict
        ``{"summary_csv": path, "summary_parquet": path}`` (``summary_parquet`` only when pyarrow, the
        ``parquet`` extra, is installed).
    seconds : float
        Wall time of the whole batch.
    """

    table: pd.DataFrame
    written: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def n_files(self) -> int:
        return len(self.table)

    @property
    def n_failed(self) -> int:
        return int(self.table["error"].astype(bool).sum())

    @property
    def n_rejected(self) -> int:
        """Files fitted whose calibration the acceptance policy rejected."""
        return int(self.table["accepted"].eq(False).sum())

    @property
    def files_per_second(self) -> float:
        return self.n_files / self.seconds if self.seconds > 0 else float("inf")

    def exit_code(self) -> int:
        """0 when every file was fitted (and accepted); else the exit code of the first failure (2 input, 3
        identifiability, 1 internal), as ``trimag fit`` would have returned for that file, or 4 when the acceptance
        policy rejected a calibration."""
        codes = {"input": 2, "identifiability": 3, "internal": 1}
        failed = self.table[self.table["error"].astype(bool)]
        if not failed.empty:
            return codes.get(str(failed["error_type"].iloc[0]), 1)
        return 4 if self.n_rejected else 0

    def summary(self) -> dict[str, Any]:
        """The JSON object ``trimag batch --json`` prints."""
        failed = self.table[self.table["error"].astype(bool)]
        return {
            "n_files": self.n_files,
            "n_fitted": self.n_files - self.n_failed,
            "n_failed": self.n_failed,
            "n_rejected": self.n_rejected,
            "seconds": self.seconds,
            "files_per_second": self.files_per_second,
            "failed": [{"file": f, "error": e, "details": d}
                       for f, e, d in zip(failed["file"], failed["error"], failed["error_details"], strict=True)],
            "outputs": dict(self.written),
        }


def expand_inputs(patterns: str | Sequence[str]) -> list[Path]:
    """Expand glob patterns (``**`` recursive) and plain paths into a sorted list of distinct files.

    Raises
    ------
    TrimagInputError
        A pattern matches nothing.
    """
    if isinstance(patterns, str | os.PathLike):
        patterns = [os.fspath(patterns)]
    found: dict[str, Path] = {}
    for pattern in patterns:
        pattern = os.fspath(pattern)
        matches = sorted(glob.glob(pattern, recursive=True)) if glob.has_magic(pattern) else [pattern]
        matches = [m for m in matches if Path(m).is_file()]
        if not matches and Path(pattern).is_dir():
            raise TrimagInputError(f"{pattern} is a folder: give the logs in it as a quoted pattern, e.g. "
                                   f"'{os.path.join(pattern, '*.csv')}'")
        if not matches:
            raise TrimagInputError(
                f"{pattern!r} matches no file; quote the pattern (e.g. 'logs/*.csv') so trimag expands it, "
                "and check the folder"
            )
        for m in matches:
            found.setdefault(os.path.abspath(m), Path(m))
    return [found[k] for k in sorted(found)]


def calibration_names(files: Sequence[Path]) -> list[str]:
    """One distinct output name per input: the file stem, or, when stems repeat, the path below the common
    folder with separators replaced by ``__`` (``a/run.csv``, ``b/run.csv`` -> ``a__run``, ``b__run``)."""
    stems = [f.stem for f in files]
    if len(set(stems)) == len(stems):
        return stems
    absolute = [os.path.abspath(f) for f in files]
    root = os.path.commonpath([os.path.dirname(a) for a in absolute])
    names = [os.path.splitext(os.path.relpath(a, root))[0].replace(os.sep, "__") for a in absolute]
    if len(set(names)) != len(names):  # same path minus extension, e.g. run.csv and run.parquet
        names = [os.path.relpath(a, root).replace(os.sep, "__").replace(".", "_") for a in absolute]
    return names


def _failure(exc: BaseException) -> tuple[str, str]:
    """The row's ``error`` and ``error_type`` of a file that failed: what ``trimag fit`` would say (its verdict; the
    details, :attr:`TrimagError.details <trimag.errors.TrimagError.details>`, go to ``error_details``) and its exit
    code's kind (an unreadable file, an unwritable output, not enough memory: the user's input, exit 2)."""
    if isinstance(exc, IdentifiabilityError):
        return str(exc), "identifiability"
    if isinstance(exc, TrimagError):
        return str(exc), "input" if isinstance(exc, TrimagInputError) else "internal"
    if isinstance(exc, UnicodeDecodeError):
        return "the file is not UTF-8 text; save it as UTF-8", "input"
    if isinstance(exc, OSError):
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        return f"cannot read or write{where}: {exc.strerror or exc}", "input"
    if isinstance(exc, MemoryError):
        return out_of_memory_message("this file"), "input"
    return f"internal error (a bug in trimag, not a problem with this file): {type(exc).__name__}: {exc}", "internal"


def _worker_died(job: tuple[str, str]) -> dict[str, Any]:
    """The row of a file whose worker process died while fitting it alone (``map_trials``' ``worker_died``)."""
    row: dict[str, Any] = dict.fromkeys(SUMMARY_COLUMNS)
    row.update(file=job[0], warnings="", error_type="input", error_details="", seconds=float("nan"), error=(
        "the worker process fitting this file died (killed by the system, most often for lack of memory): fit it "
        "alone with `trimag fit` to see what it needs, or lower the input limits (--max-fields, "
        "--max-decompressed-mb)"))
    _remove_stale(job[1])
    return row


def _remove_stale(out: str) -> None:
    """Remove an earlier run's calibration of a file that failed now (a regular file only)."""
    path = Path(out)
    try:
        if path.is_file() and not path.is_symlink():
            path.unlink()
    except OSError:
        pass


def fit_one(job: tuple[str, str], request: FitRequest | None = None, *, limits: InputLimits | None = None,
            scratch: str | None = None, **fit_options: Any) -> dict[str, Any]:
    """Fit one file and write its calibration; never raises (a failure becomes the row's ``error``).

    Parameters
    ----------
    job : (str, str)
        Input path and output calibration path.
    request : FitRequest, optional
        The fit asked for every file (its input's path and its ``out`` are replaced by the job's).
    limits : InputLimits, optional
        The input limits to read with (:mod:`trimag.io.limits`; default: those in force).
    scratch : str, optional
        Folder for the file's decompressed copy (a new folder in it, removed when the file is done).
    **fit_options
        Without ``request``: keyword arguments of :func:`trimag.app.fit_file` (model, method, options, units,
        reference, ...).

    Returns
    -------
    dict
        One summary row (keys :data:`SUMMARY_COLUMNS`).
    """
    path, out = job
    t0 = time.perf_counter()
    row: dict[str, Any] = dict.fromkeys(SUMMARY_COLUMNS)
    row.update(file=path, warnings="", error="", error_details="", error_type="")
    limits = limits or current_limits()
    try:
        from ..io.normalise import scratch_folder
        from . import fit_file  # the public entry (monkeypatched by the tests)

        with input_limits(limits.max_fields, limits.max_decompressed_mb), scratch_folder(scratch):
            if request is not None:
                one = dataclasses.replace(request, input=dataclasses.replace(request.input, path=path), out=out)
                result = fit_file(one, **fit_options)
            else:
                result = fit_file(path, out=out, **fit_options)
        s = result.summary
        row.update(
            n=s.get("n_samples"), n_used=s.get("n_used"), rms_before=s.get("rms_before"),
            rms_after=s.get("rms_after"), units=s.get("units"), converged=bool(s.get("converged")),
            warnings="; ".join(s.get("warnings") or []), calibration=out,
        )
        record = getattr(getattr(result, "calibration", None), "sensor", None)
        row["sensor"] = record.describe() if record is not None else ""
        verdict = s.get("acceptance")
        if verdict is not None:
            from ..vehicle.policy import failed_rules

            row.update(accepted=bool(verdict["accepted"]), rejected_by="; ".join(failed_rules(verdict, digits=3)))
    except Exception as exc:
        message, kind = _failure(exc)
        row.update(error=message or type(exc).__name__, error_type=kind,
                   error_details="; ".join(getattr(exc, "details", ())))
        _remove_stale(out)
    row["seconds"] = time.perf_counter() - t0
    return row


def _table(rows: list[dict[str, Any]]) -> pd.DataFrame:
    df = pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
    df["n"] = df["n"].astype("Int64")
    df["n_used"] = df["n_used"].astype("Int64")
    df["rms_before"] = pd.to_numeric(df["rms_before"]).astype("float64")
    df["rms_after"] = pd.to_numeric(df["rms_after"]).astype("float64")
    df["converged"] = df["converged"].astype("boolean")
    df["accepted"] = df["accepted"].astype("boolean")
    for col in ("file", "units", "warnings", "error", "error_details", "error_type", "calibration", "rejected_by",
                "sensor"):
        df[col] = df[col].astype("string")
    df["seconds"] = df["seconds"].astype("float64")
    return df


def _write_parquet(df: pd.DataFrame, path: Path) -> Path | None:
    """Write the summary as Parquet when pyarrow (the ``parquet`` extra) is installed; None otherwise."""
    from .._core.extras import available

    if not available("pyarrow"):
        return None
    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False, engine="pyarrow")
    return path


def fit_batch(
    patterns: str | Sequence[str],
    out_dir: str | Path,
    *,
    model: str = "ellipsoid",
    method: str | None = None,
    options: dict[str, Any] | None = None,
    workers: int = 1,
    scheduler: Any = None,
    progress: bool | str = True,
    chunksize: int | None = None,
    backend: str | None = None,
    request: FitRequest | None = None,
    **fit_options: Any,
) -> BatchResult:
    """Fit every file matched by ``patterns``; write one calibration per file and the summary table.

    Parameters
    ----------
    patterns : str or sequence of str
        Glob patterns (``**`` recursive) or file paths.
    out_dir : path
        Output folder (created): ``<name>.json`` per file (see :func:`calibration_names`), ``summary.csv``,
        ``summary.parquet`` (with the ``parquet`` extra).
    model, method, options
        As for ``trimag fit`` (``options``: method keyword arguments).
    workers : int
        Parallel worker processes on this machine; 1 runs in this process.
    scheduler : str or distributed.Client, optional
        A ``dask.distributed`` scheduler address (or client); overrides ``workers``. Needs the ``batch`` extra.
    progress : bool or str
        Progress bar on stderr (see :func:`trimag.parallel.map_trials`).
    chunksize : int, optional
        Files per task (default: about 8 tasks per worker).
    backend : {"processes", "threads"}, optional
        Local pool for ``workers > 1`` (default: processes; see :func:`trimag.parallel.map_trials`).
    request : FitRequest, optional
        The fit asked for every file (what ``trimag batch`` builds from its flags): its input's path and ``out`` are
        replaced per file, and ``model``, ``method``, ``options`` and ``fit_options`` are not used.
    **fit_options
        Without ``request``: further :func:`trimag.app.fit_file` arguments for every file (``fmt``, ``units``,
        ``reference``, ``igrf_spec``, ...).

    Returns
    -------
    BatchResult
        The summary table (also written), output paths and wall time.

    Raises
    ------
    TrimagInputError
        A pattern matches no file, an unknown model/method/argument, a policy that cannot be read, or both
        ``request`` and fit arguments (checked once, before any work).
    """
    from ..estimators import make_estimator
    from ..parallel import check_workers, map_trials

    request = _batch_request(request, model=model, method=method, options=options, **fit_options)
    # unknown model, method or option: fail once, up front (``eddy`` is the application's, not the estimator's)
    make_estimator(request.model, request.method, {k: v for k, v in request.options.items() if k != "eddy"})
    if request.policy is not None:  # a policy that cannot be read: once, before any file is fitted
        from ..vehicle.policy import read_policy

        read_policy(request.policy)
    files = expand_inputs(patterns)
    out = Path(out_dir)
    jobs = [(str(f), str(out / f"{name}.json")) for f, name in zip(files, calibration_names(files), strict=True)]
    check_distinct_outputs({f"the input file {k + 1}": f for k, f in enumerate(files)},
                           {**{f"calibration of {f}": o for f, o in jobs}, "summary.csv": out / "summary.csv",
                            "summary.parquet": out / "summary.parquet"})
    check_workers(workers, scheduler)  # before anything is written
    if out.exists() and not out.is_dir():
        raise TrimagInputError(f"`out` {out} is a file; batch writes a folder (one calibration per log and the "
                               "summary): give a folder's name")
    out.mkdir(parents=True, exist_ok=True)
    scratch = tempfile.mkdtemp(prefix="trimag-batch-")  # this process's: removed even when a worker is killed
    task = partial(fit_one, request=request, limits=current_limits(), scratch=scratch)
    t0 = time.perf_counter()
    try:
        rows = map_trials(task, jobs, workers=workers, scheduler=scheduler,
                          progress="batch fits" if progress is True else progress, chunksize=chunksize,
                          backend=backend, worker_died=_worker_died)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    seconds = time.perf_counter() - t0
    table = _table(rows)
    written = {
        "summary_csv": str(atomic_write_text(out / "summary.csv", table.to_csv(index=False, lineterminator="\n"))),
    }
    parquet = _write_parquet(table, out / "summary.parquet")
    if parquet is not None:
        written["summary_parquet"] = str(parquet)
    return BatchResult(table, written, seconds)


def _batch_request(request: FitRequest | None, **arguments: Any) -> FitRequest:
    """The fit asked for every file: ``request``, or one from the flat fit ``arguments`` (its path is replaced per
    file); a request with arguments other than :func:`fit_batch`'s defaults is refused."""
    if request is None:
        return FitRequest.of("", **arguments)
    defaults = {"model": "ellipsoid", "method": None, "options": None}
    if any(arguments.get(k, v) != v for k, v in defaults.items()) or set(arguments) - set(defaults):
        raise TrimagInputError("give either a FitRequest or fit arguments, not both")
    return request
