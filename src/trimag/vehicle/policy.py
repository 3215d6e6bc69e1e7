"""Acceptance policy: declared limits a calibration must meet (``trimag fit --policy FILE.toml``; exit code 4).

A policy file has a ``[limits]`` table; every rule present is checked, and every failed rule is listed with its
measured value. A rule that the data cannot evaluate (no reference for the field error, no IGRF for the heading)
is reported as not evaluated, never as passed; a policy none of whose rules could be evaluated accepts nothing (the
verdict says that nothing was checked: exit 4). ``--policy default`` uses :data:`DEFAULT_LIMITS`.

Every limit is a finite number (an integer or a float; not a string, a boolean or NaN), ``>= 0``, and ``min_coverage``
at most 1: a limit no measurement can meet, or one every measurement meets by accident of a type, is refused when the
file is read (exit 2, before the fit).

| rule | measured as |
|---|---|
| ``max_rms_after`` | RMS of ``|B| - F`` after calibration, in the data's unit |
| ``max_field_error_pct`` | fitted magnitude against the reference or IGRF, % |
| ``min_coverage`` | fraction of the sphere of field directions seen (0-1) |
| ``max_offset`` | largest hard-iron component, in the data's unit |
| ``max_heading_sigma_deg`` | largest predicted 1-sigma heading error of a level sensor (needs ``--igrf``) |
| ``max_inclination_error_deg`` | dip fitted with the accelerometer (``--accel-columns``) against IGRF's (needs both) |
| ``max_halves_ratio`` | ``--target`` fits: each half's fit on the other half over the log's calibration there, RMS |

``max_halves_ratio`` is the larger of the two halves' ratios (:mod:`trimag.vehicle._firmware_halves`; 1: no better
than the calibration the vehicle has, so ``max_halves_ratio = 1.0`` rejects what the halves check only warns of).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..errors import TrimagError, TrimagInputError

__all__ = ["DEFAULT_LIMITS", "PolicyRejected", "check_policy", "failed_rules", "read_policy"]

#: ``--policy default``: what a fitted MEMS or fluxgate calibration should meet in the field
DEFAULT_LIMITS: dict[str, float] = {"max_field_error_pct": 5.0, "min_coverage": 0.5, "max_heading_sigma_deg": 1.0}

_RULES = ("max_rms_after", "max_field_error_pct", "max_inclination_error_deg", "min_coverage",
          "max_heading_sigma_deg", "max_offset", "max_halves_ratio")


class PolicyRejected(TrimagError):
    """The calibration fails its acceptance policy (exit code 4)."""

    exit_code = 4


def read_policy(spec: str) -> dict[str, float]:
    """The ``[limits]`` of a policy file, or the default limits for ``"default"``."""
    if spec == "default":
        return dict(DEFAULT_LIMITS)
    p = Path(spec)
    if not p.is_file():
        raise TrimagInputError(f"policy file {spec!r} does not exist (or use `policy=default`)")
    from ..validation import load_toml

    data = load_toml(p.read_text(encoding="utf-8"), f"{p}: not a TOML policy file")
    limits = data.get("limits")
    if not isinstance(limits, dict) or not limits:
        raise TrimagInputError(f"{p}: needs a [limits] table with at least one of {', '.join(_RULES)}")
    unknown = [k for k in limits if k not in _RULES]
    if unknown:
        raise TrimagInputError(f"{p}: unknown rule(s) {', '.join(unknown)}; rules are {', '.join(_RULES)}")
    return {rule: _limit(p, rule, value) for rule, value in limits.items()}


def _limit(path: Path, rule: str, value: Any) -> float:
    """A limit as a float: a finite number >= 0 (at most 1 for ``min_coverage``), else refused naming it."""
    what = "a fraction from 0 to 1" if rule == "min_coverage" else "a finite number >= 0"
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TrimagInputError(f"{path}: {rule} = {value!r} is not a number; give {what}")
    limit = float(value)
    if not np.isfinite(limit) or limit < 0 or (rule == "min_coverage" and limit > 1):
        raise TrimagInputError(f"{path}: {rule} = {value!r} can never be met as intended; give {what}")
    return limit


def check_policy(cal: Calibration, limits: dict[str, float], *, inclination_deg: float | None = None,
                 reference_F: float | None = None) -> dict[str, Any]:
    """Evaluate every rule in ``limits``; returns ``{"accepted", "failed", "passed", "not_evaluated"}`` (and
    ``"nothing_checked": True`` when no rule could be evaluated: then not accepted)."""
    measured: dict[str, float | None] = {}
    stats, diag = cal.stats, cal.diagnostics
    measured["max_rms_after"] = stats.get("rms_after")
    fitted = (cal.reference or {}).get("fitted_radius") or stats.get("mean_norm_after")
    measured["max_field_error_pct"] = (
        abs(float(fitted) / reference_F - 1.0) * 100.0 if reference_F and fitted else None
    )
    measured["min_coverage"] = (diag.get("coverage") or {}).get("fraction")
    measured["max_offset"] = float(np.abs(np.asarray(cal.offset)).max())
    dip = (diag.get("alignment") or {}).get("dip_deg")
    measured["max_inclination_error_deg"] = (
        abs(float(dip) - inclination_deg) if dip is not None and inclination_deg is not None else None
    )
    measured["max_halves_ratio"] = _halves_ratio(diag)
    measured["max_heading_sigma_deg"] = None
    if inclination_deg is not None and "max_heading_sigma_deg" in limits:
        from .heading import predicted_heading_sigma

        try:
            measured["max_heading_sigma_deg"] = predicted_heading_sigma(cal, inclination_deg)["max_deg"]
        except TrimagInputError:
            pass
    failed: list[dict[str, Any]] = []
    passed: list[dict[str, Any]] = []
    not_evaluated: list[str] = []
    for rule, limit in limits.items():
        value = measured.get(rule)
        if value is None or not np.isfinite(value):
            not_evaluated.append(rule)
            continue
        ok = value >= limit if rule.startswith("min_") else value <= limit
        (passed if ok else failed).append({"rule": rule, "limit": limit, "measured": float(value)})
    verdict: dict[str, Any] = {"accepted": not failed and bool(passed), "failed": failed, "passed": passed,
                               "not_evaluated": not_evaluated}
    if not passed and not failed:
        verdict["nothing_checked"] = True
    return verdict


def failed_rules(verdict: Mapping[str, Any], digits: int = 4) -> list[str]:
    """Each failed rule of ``verdict`` (:func:`check_policy`) as the user reads it: ``"max_offset = 100: measured
    120.5"`` (the measured value to ``digits`` significant digits)."""
    return [f"{f['rule']} = {f['limit']:g}: measured {f['measured']:.{digits}g}" for f in verdict.get("failed") or []]


def _halves_ratio(diagnostics: Mapping[str, Any]) -> float | None:
    """The halves check's worst ratio of the other half's fit to the log's calibration (a firmware fit), or None."""
    halves = (diagnostics.get("firmware") or {}).get("halves") or {}
    if not halves.get("checked"):
        return None
    ratios = [halves[k]["rms_other_half_fit"] / halves[k]["rms_log"] for k in ("first", "second")
              if halves.get(k) and halves[k]["rms_log"] > 0]
    return max(ratios) if ratios else None
