"""Exceptions and warnings raised by trimag.

Every error a user can cause subclasses a built-in, so ``except ValueError`` keeps working, and maps to one
documented exit code of the ``trimag`` command (see ``docs/cli.md``):

=========================  ==========  =======================================================
class                      exit code   meaning
=========================  ==========  =======================================================
``TrimagInputError``       2           bad input or usage: shape, NaN, unit, file, column
``IdentifiabilityError``   3           the data cannot identify the requested model
anything else              1           internal error (a bug: please report it)
=========================  ==========  =======================================================
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = [
    "CalibrationFormatError",
    "IdentifiabilityError",
    "IdentifiabilityWarning",
    "MissingExtraError",
    "NotFittedError",
    "TrimagError",
    "TrimagInputError",
    "TrimagWarning",
    "UnitMismatchError",
]


class TrimagError(Exception):
    """Base class of all trimag errors.

    The message (``str(exc)``) is the whole verdict in one short line: what is wrong and what to do. ``details``
    are the figures behind it, one short line each, which the ``trimag`` command prints indented under the verdict
    (docs/cli.md, "Errors"); :func:`full_message` joins both into one line (a JSON field, a batch summary cell).
    """

    exit_code = 1
    #: the figures behind the verdict, one short line each (empty when the verdict says it all)
    details: tuple[str, ...] = ()

    def __init__(self, *args: object, details: Sequence[str] = ()) -> None:
        super().__init__(*args)
        if details:
            self.details = tuple(str(line) for line in details)


class TrimagInputError(TrimagError, ValueError):
    """The input is malformed: wrong shape, non-finite values, unknown unit, unreadable file."""

    exit_code = 2


class UnitMismatchError(TrimagInputError):
    """Data in one unit were given to a calibration made for another."""


class MissingExtraError(TrimagInputError, ImportError):
    """A feature needs an optional package that is not installed; the message names the extra that installs it
    (e.g. ``pip install "trimag[parquet]"``)."""


class CalibrationFormatError(TrimagInputError):
    """A calibration file is not a trimag calibration, or was written by an incompatible version."""


class IdentifiabilityError(TrimagError, ValueError):
    """The samples cannot identify the requested model (too few, coplanar, degenerate attitude coverage).

    The message says which data are missing, e.g. "record rotations about at least two axes".
    """

    exit_code = 3


class NotFittedError(TrimagError, ValueError, AttributeError):
    """An estimator was used before ``fit``."""


class TrimagWarning(UserWarning):
    """Base class of trimag warnings."""


class IdentifiabilityWarning(TrimagWarning):
    """The model is identifiable, but poorly: a large condition number or a weakly covered sphere."""


def full_message(exc: BaseException) -> str:
    """``exc``'s verdict and its details (:attr:`TrimagError.details`) in one line, joined by "; "."""
    details = getattr(exc, "details", ())
    return "; ".join([str(exc), *details]) if details else str(exc)


def out_of_memory_message(what: str = "the data") -> str:
    """The one line for a :class:`MemoryError` while reading or fitting: the machine's memory, not a bug (exit 2)."""
    return (f"not enough memory for {what}: the log is larger than this machine (or its memory limit) can hold while "
            "reading and fitting it (2 to 17 bytes per byte of CSV text, the shorter the rows the more); fit part of "
            "it with `rows=START:STOP`, or run on a machine with more memory")
