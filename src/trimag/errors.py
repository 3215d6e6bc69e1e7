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
    """Base class of all trimag errors."""

    exit_code = 1


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


def out_of_memory_message(what: str = "the data") -> str:
    """The one line for a :class:`MemoryError` while reading or fitting: the machine's memory, not a bug (exit 2)."""
    return (f"not enough memory for {what}: the log is larger than this machine (or its memory limit) can hold while "
            "reading and fitting it (2 to 17 bytes per byte of CSV text, the shorter the rows the more); fit part of "
            "it with `rows=START:STOP`, or run on a machine with more memory")
