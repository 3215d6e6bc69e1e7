"""One validator for every field array that enters trimag (style guide: scikit-learn's ``check_array``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import IdentifiabilityError, TrimagInputError

__all__ = [
    "MAX_NESTING", "MAX_READING", "WILD_FACTOR", "check_field", "check_nesting", "check_reference_values",
    "describe_wild_rows", "load_json", "load_toml", "wild_rows",
]

#: A row whose magnitude is more than this many times the median magnitude of its samples is a glitch (a logger's
#: bit flip, a spike, a unit change mid-log), not a field: hard and soft iron keep every real reading of a log
#: within a few times its median (a hard iron as large as the field: 0-2 F around a median of 1.4 F; gains of 10:1:
#: F-10 F around about 6 F).
WILD_FACTOR = 10.0
#: Largest value taken as a reading: beyond it, squares of magnitudes approach overflow (no sensor reads 1e150 in
#: any unit).
MAX_READING = 1e150
#: The field magnitudes a reference may take, in any unit (nT, uT, G, mG, counts, a normalised field of 1): below
#: 1e-9 (1e-4 nT given in G) or above 1e12 (1000 T in nT; no ADC counts so far) no field is calibrated against.
REFERENCE_RANGE = (1e-9, 1e12)
#: Residuals below this fraction of the field are round-off (double precision leaves ~1e-16 of it; no sensor
#: resolves 1e-9 of the field): checks that compare residuals (worse than raw, halves that disagree) find nothing
#: in them (noise-free simulated data were "changed during the log (8.9 sigma)" and "worse than raw").
ROUNDOFF_FRACTION = 1e-9
#: Deepest nesting of lists and tables accepted in a JSON or TOML input (trimag's own files nest 5 deep); a deeper
#: document is refused before Python's parsers recurse past their limit (a RecursionError was exit 1).
MAX_NESTING = 64
_MEDIAN_SAMPLES = 2048  # rows of the quick median that lets a log without wild rows skip the exact screen


def check_field(
    B: ArrayLike,
    *,
    name: str = "B",
    min_samples: int = 1,
    allow_single: bool = False,
    model: str | None = None,
) -> NDArray[np.float64]:
    """Validate a field array and return it as float64 of shape (N, 3).

    Parameters
    ----------
    B : array_like, shape (N, 3) (or (3,) when ``allow_single``)
        Field samples, one row per sample, columns x, y, z.
    name : str
        The argument's name, used in messages.
    min_samples : int
        Fewest rows the caller needs (e.g. a model's parameter count).
    allow_single : bool
        Accept a single vector of shape (3,) and return it as (1, 3).
    model : str, optional
        Model name, for the too-few-samples message.

    Returns
    -------
    ndarray, shape (N, 3), float64
        C-ordered and never the caller's writable array: a read-only view when ``B`` is already a C-ordered
        float64 array (no copy), otherwise a new array. The input is never modified.

    Raises
    ------
    TrimagInputError
        Wrong shape, non-numeric or non-finite values.
    IdentifiabilityError
        Fewer than ``min_samples`` rows.
    """
    try:
        if isinstance(B, np.ndarray) and B.dtype == np.float64 and B.flags.c_contiguous:
            # already what trimag needs: a read-only view, no copy (a 1e7-row log is 240 MB); any attempt to
            # write into it raises, so the caller's array can never be modified
            arr = B.view()
            arr.flags.writeable = False
        else:
            arr = np.array(B, dtype=np.float64, copy=True, order="C")  # C order: row blocks are contiguous
    except (TypeError, ValueError) as exc:
        raise TrimagInputError(f"`{name}` must be numeric with shape (N, 3); got {type(B).__name__}") from exc
    if arr.ndim == 1 and allow_single and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise TrimagInputError(
            f"`{name}` must have shape (N, 3) (one row per sample, columns x, y, z); got {arr.shape}"
        )
    if arr.shape[0] == 0:
        raise TrimagInputError(f"`{name}` is empty: no samples to work with")
    # NaN and inf make the sum non-finite (one pass, no (N, 3) mask); only then (or on overflow) look closer
    with np.errstate(over="ignore", invalid="ignore"):
        total = arr.sum()
    if not np.isfinite(total) and not np.isfinite(arr).all():
        bad = ~np.isfinite(arr).all(axis=1)
        raise TrimagInputError(
            f"`{name}` has {int(bad.sum())} row(s) with NaN or inf (first at row {int(np.argmax(bad))}); "
            "drop them first (the file readers do this and report the count)"
        )
    wild = wild_rows(arr)
    if wild.any():
        raise TrimagInputError(
            f"`{name}` has {describe_wild_rows(arr, wild)}; drop them first (the file readers drop and count such "
            "rows)"
        )
    if arr.shape[0] < min_samples:
        what = f" model {model!r}" if model else " this fit"
        raise IdentifiabilityError(
            f"{arr.shape[0]} samples are too few for{what}: at least {min_samples} are needed; "
            "record more samples in more attitudes"
        )
    return arr


def check_reference_values(values: Any, n: int, *, name: str = "reference") -> NDArray[np.float64]:
    """Validate a scalar reference (one value, or one per sample) and return shape (N,) float64."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise TrimagInputError(f"`{name}` must be a scalar or have shape ({n},); got {arr.shape}")
    if not np.isfinite(arr).all() or (arr <= 0).any():
        raise TrimagInputError(f"`{name}` must be finite and positive (a field magnitude)")
    low, high = REFERENCE_RANGE
    if arr.size and not (low <= arr.min() and arr.max() <= high):
        bad = float(arr.min() if arr.min() < low else arr.max())
        raise TrimagInputError(f"`{name}` {bad:.6g} is not a field magnitude in any unit (one is {low:g} to "
                               f"{high:g}); give the field in the data's unit, e.g. 48193 (nT) or 0.48 (G)")
    return arr


def check_reference_magnitude(value: Any, *, name: str = "reference") -> float:
    """The one field magnitude ``value`` (a number, or a string of one) as a float; refused
    (:class:`TrimagInputError`) unless finite, positive and within :data:`REFERENCE_RANGE`."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise TrimagInputError(f"`{name}` takes a field magnitude (a number); got {value!r}") from None
    if not (np.isfinite(number) and number > 0):
        raise TrimagInputError(f"`{name}` must be a finite positive field magnitude; got {value!r}")
    return float(check_reference_values(number, 1, name=name)[0])


def _norms(B: NDArray[np.float64], huge: NDArray[np.bool_] | None = None) -> NDArray[np.float64]:
    """Row magnitudes, 0 for the rows in ``huge`` (their squares would overflow)."""
    safe = B if huge is None or not huge.any() else np.where(huge[:, None], 0.0, B)
    return np.sqrt(safe[:, 0] ** 2 + safe[:, 1] ** 2 + safe[:, 2] ** 2)


def wild_rows(B: ArrayLike) -> NDArray[np.bool_]:
    """Rows that are not magnetometer readings: a value beyond :data:`MAX_READING`, or a magnitude more than
    :data:`WILD_FACTOR` times the median magnitude (of the other rows).

    Parameters
    ----------
    B : array_like, shape (N, 3)
        Finite field samples, any unit.

    Returns
    -------
    ndarray of bool, shape (N,)
        True for a wild row. A log without one costs two passes and a median of 2048 rows (the exact screen runs
        only when the largest value could make a row wild).
    """
    arr = np.asarray(B, dtype=np.float64)
    n = len(arr)
    if n == 0:
        return np.zeros(0, dtype=bool)
    top = max(float(arr.max()), -float(arr.min()))
    if top <= MAX_READING:
        quick = float(np.median(_norms(arr[:: max(n // _MEDIAN_SAMPLES, 1)])))
        if np.sqrt(3.0) * top <= 0.5 * WILD_FACTOR * quick:  # no row can be wild, with a factor 2 to spare
            return np.zeros(n, dtype=bool)
    huge = np.asarray((np.abs(arr) > MAX_READING).any(axis=1))
    norms = _norms(arr, huge)
    median = float(np.median(norms[~huge])) if not huge.all() else 0.0
    return huge | (norms > WILD_FACTOR * median) if median > 0 else huge


def describe_wild_rows(B: ArrayLike, wild: NDArray[np.bool_], row_label: str = "row", first: int | None = None) -> str:
    """What the wild rows of ``B`` are, for a message: their count, the rule and the first one (its label
    ``row_label first``, ``first`` defaulting to its 0-based position)."""
    arr = np.asarray(B, dtype=np.float64)
    k = int(np.argmax(wild))
    huge = np.asarray((np.abs(arr) > MAX_READING).any(axis=1))
    norms = _norms(arr, huge)
    median = float(np.median(norms[~wild])) if not wild.all() else 0.0
    if huge[k]:
        what = f"a value beyond {MAX_READING:g}, not a magnetometer reading"
    else:
        what = f"|B| = {norms[k]:.4g}, {norms[k] / median:.0f}x the median"
    return (f"{int(wild.sum())} row(s) whose |B| is more than {WILD_FACTOR:g}x the median |B| ({median:.4g}) or that "
            f"hold a value beyond {MAX_READING:g} (not a magnetometer reading: a logging glitch), first at "
            f"{row_label} {k if first is None else first} ({what})")


def _nesting(text: str) -> int:
    """Deepest nesting of ``[`` and ``{`` in JSON or TOML text, brackets inside strings counted too (an upper
    bound: a deep string of brackets is refused as well, which no trimag file holds)."""
    import re

    depth = top = 0
    for bracket in re.findall(r"[\[\]{}]", text):
        depth = max(depth + (1 if bracket in "[{" else -1), 0)
        top = max(top, depth)
    return top


def check_nesting(text: str, what: str, error: type[TrimagInputError] = TrimagInputError) -> None:
    """Refuse JSON or TOML ``text`` nested deeper than :data:`MAX_NESTING` (``error``, its message starting with
    ``what``)."""
    if _nesting(text) > MAX_NESTING:
        raise error(f"{what}: nested more than {MAX_NESTING} levels deep (lists or tables within each other); not a "
                    "file trimag or a person wrote")


def load_json(text: str, what: str, error: type[TrimagInputError] = TrimagInputError) -> Any:
    """Parse JSON ``text``; malformed or nested deeper than :data:`MAX_NESTING` raises ``error`` (a
    :class:`TrimagInputError`) starting with ``what``."""
    import json

    check_nesting(text, what, error)
    try:
        return json.loads(text)
    except ValueError as exc:  # JSONDecodeError, or an integer of more than 4300 digits
        raise error(f"{what}: not valid JSON ({json_error(exc)})") from None


def json_error(exc: ValueError) -> str:
    """What is wrong with a JSON text ``json.loads`` refused, in the user's words (Python refuses to read an integer
    of more than ``sys.get_int_max_str_digits()`` digits, and says so in its own terms)."""
    import sys

    if "integer string conversion" in str(exc):
        return f"a number with more than {sys.get_int_max_str_digits()} digits"
    return str(exc)


def load_toml(text: str, what: str) -> dict[str, Any]:
    """Parse TOML ``text`` (as :func:`load_json`)."""
    import tomllib

    check_nesting(text, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise TrimagInputError(f"{what}: not valid TOML ({exc})") from None


def listed(names: Any, limit: int = 10) -> str:
    """``names`` joined with commas for a message, at most ``limit`` of them and then how many more (issue 41,
    item 14: 100 000 names made a 1.6 MB error line)."""
    items = [str(n) for n in names]
    if len(items) <= limit:
        return ", ".join(items)
    return f"{', '.join(items[:limit])} and {len(items) - limit} more"
