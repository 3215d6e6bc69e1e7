"""Figures and the text report of a fit (matplotlib, Agg backend; nothing is shown on screen).

:func:`fit_report` draws one PNG: |B| before and after per sample, the distribution of |B| - F, the coverage of
the sphere of field directions, and the point cloud before and after in three projections.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..io.atomic import atomic_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["fit_report", "params_table", "save_figure", "summary_rows", "summary_table"]

_MAX_POINTS = 6000


def _figure(figsize: tuple[float, float]) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, layout="constrained")


def save_figure(fig: Figure, path: str | os.PathLike[str], *, dpi: int = 110) -> Path:
    """Save a figure as PNG atomically (temporary file in the same folder, then rename)."""
    target = Path(path)
    with atomic_path(target) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return target


def summary_rows(cal: Calibration) -> list[tuple[str, float, float]]:
    """(quantity, before, after) rows of |B| statistics in the calibration's unit."""
    s = cal.stats
    return [
        ("|B| mean", s["mean_norm_before"], s["mean_norm_after"]),
        ("|B| std", s["std_norm_before"], s["std_norm_after"]),
        ("RMS(|B| - F)", s["rms_before"], s["rms_after"]),
        ("max ||B| - F|", s["max_abs_before"], s["max_abs_after"]),
    ]


def summary_table(cal: Calibration) -> str:
    """A small plain-text before/after table."""
    from ..units import unit_words

    ref = cal.reference or {}
    value = ref.get("value")
    source = ref.get("source", "?")
    head = "" if value is None else f"reference F = {value:.6g} {cal.units} ({source})" if unit_words(cal.units) == \
        cal.units else f"reference F = {value:.6g} ({source}; unit not given)"
    lines = [head, f"{'':16}{'before':>14}{'after':>14}   [{unit_words(cal.units)}]"]
    for name, before, after in summary_rows(cal):
        lines.append(f"{name:16}{before:14.6g}{after:14.6g}")
    return "\n".join(line for line in lines if line)


def _param_kinds(model: str) -> dict[str, str]:
    """The parameters' declared kinds (:attr:`trimag.models.base.ErrorModel.kinds`) of a registered model; empty
    for another (e.g. an ``affine`` calibration, whose parameters are then shown without a unit)."""
    from ..models import MODELS, get_model

    return dict(get_model(model).kinds) if model in MODELS else {}


def params_table(cal: Calibration) -> str:
    """The model's named parameters with 1-sigma uncertainties when known, angles also in degrees, and the
    iteration history when the method recorded one."""
    import math

    from ..units import unit_after, unit_words

    std = (cal.uncertainty or {}).get("param_std", {}) or {}
    unit = unit_after(cal.units)
    lines = [f"{cal.model} parameters (value +- 1 sigma):"]
    kinds = _param_kinds(cal.model)
    firmware = (cal.diagnostics or {}).get("firmware")
    status = (firmware.get("param_status") if isinstance(firmware, dict) else None) or {}
    for name, value in cal.params.items():
        s = std.get(name) if status.get(name, "fitted") == "fitted" else None
        pm = f" +- {s:.3g}" if s is not None else ""
        if status.get(name, "fitted") != "fitted":  # a firmware fit: held, not identified, kept: never a sigma
            lines.append(f"  {name:12s} = {value:.8g}  ({status[name]})")
            continue
        if kinds.get(name) == "angle":
            deg = f"  ({math.degrees(value):.5f} deg" + (f" +- {math.degrees(s):.2g}" if s is not None else "") + ")"
            lines.append(f"  {name:12s} = {value:.6g}{pm} rad{deg}")
        elif kinds.get(name) == "offset":
            lines.append(f"  {name:12s} = {value:.6g}{pm} {unit}")
        else:
            lines.append(f"  {name:12s} = {value:.8g}{pm}")
    hist = (cal.diagnostics or {}).get("history") or []
    if hist and isinstance(hist, list) and isinstance(hist[0], dict) and "rms" in hist[0]:
        steps = ", ".join(f"{h.get('iteration', i)}: {h['rms']:.4g}" for i, h in enumerate(hist))
        lines.append(f"iteration history, RMS(|B| - F) [{unit_words(cal.units)}]: {steps}")
    if (cal.diagnostics or {}).get("fallback"):
        info = cal.diagnostics.get("fallback_info") or {}
        lines.append(f"note: Levenberg-Marquardt fallback ({info.get('reason', 'see diagnostics')})")
    balance = (cal.diagnostics or {}).get("balanced_offset")
    if isinstance(balance, dict) and balance.get("applied"):
        lines.append(
            "note: offset = sample mean (field directions balanced: chi2 "
            f"{balance.get('chi2', float('nan')):.3g}, p = {balance.get('p_value', float('nan')):.3g}; "
            "`option balance=never` to keep the maximum-likelihood offset)"
        )
    return "\n".join(lines)


def fit_report(
    raw: ArrayLike,
    cal: Calibration,
    *,
    reference: ArrayLike | float | None = None,
    title: str = "",
    notes: Sequence[str] = (),
    time_s: ArrayLike | None = None,
) -> Figure:
    """Draw the fit report.

    Parameters
    ----------
    raw : array_like, shape (N, 3)
        The raw samples the calibration was fitted (or is evaluated) on, in ``cal.units``.
    cal : Calibration
    reference : float or array_like (N,), optional
        Reference magnitude(s); defaults to the calibration's reference value.
    title : str
    notes : sequence of str
        Extra lines printed under the title (e.g. dropped-row counts).
    time_s : array_like, shape (N,), optional
        The samples' time stamps (s; a flight log's): the magnitude is drawn against time, not sample number.
    """
    B = np.asarray(raw, dtype=np.float64)
    corrected = cal.apply(B)
    n_before = np.linalg.norm(B, axis=1)
    n_after = np.linalg.norm(corrected, axis=1)
    if reference is None:
        ref_value = (cal.reference or {}).get("value")
        F: Any = float(ref_value) if ref_value is not None else float(n_after.mean())
    else:
        F = reference
    sub = np.arange(len(B))[:: max(1, len(B) // _MAX_POINTS)]

    fig = _figure((15, 9))
    axes = fig.subplots(2, 3)
    t = None if time_s is None else np.asarray(time_s, dtype=np.float64)
    if t is not None and t.shape != (len(B),):
        raise TrimagInputError(f"time_s must have one time stamp per sample ({len(B)}); got shape {t.shape}")
    _magnitude_panel(axes[0, 0], n_before, n_after, F, sub, cal.units, t)
    _error_panel(axes[0, 1], n_before - F, n_after - F, cal)
    _coverage_panel(axes[0, 2], B)
    _cloud_panels(axes[1], B, corrected, sub, cal.units)
    head = title or f"trimag fit: model {cal.model}, method {cal.method}"
    sub_title = "; ".join([f"N = {cal.stats.get('n_used', len(B))}", *notes])
    fig.suptitle(f"{head}\n{sub_title}", fontsize=11)
    return fig


def _magnitude_panel(ax: Any, n_before: NDArray[np.float64], n_after: NDArray[np.float64], F: Any,
                     sub: NDArray[np.intp], unit: str, time_s: NDArray[np.float64] | None = None) -> None:
    """|B| per sample (the samples ``sub``) before and after, and the reference ``F`` (a number or (N,)); against
    ``time_s`` (a flight's time stamps) when given, else against the sample number."""
    x = sub if time_s is None else time_s[sub]
    ax.plot(x, n_before[sub], ".", ms=2, color="tab:red", label="before")
    ax.plot(x, n_after[sub], ".", ms=2, color="tab:blue", label="after")
    if np.ndim(F) == 0:
        ax.axhline(float(F), color="k", lw=1, label=f"F = {float(F):.5g}")
    else:
        ax.plot(x, np.asarray(F)[sub], "k-", lw=1, label="F (per sample)")
    ax.set(xlabel="sample" if time_s is None else "time (s)", ylabel=f"|B| [{unit}]",
           title="field magnitude per sample" if time_s is None else "field magnitude against time")
    ax.legend(loc="best", fontsize=8)


def _error_panel(ax: Any, err_b: NDArray[np.float64], err_a: NDArray[np.float64], cal: Calibration) -> None:
    """Histograms of |B| - F before (top) and after (bottom), each on axes of its own over its own 0.5-99.5
    percentile range with 60 bins, with the calibration's RMS: on one axis the demo's after, 100x narrower than the
    before, was a sliver at one end of it (issue 42, item 6). ``ax``'s place is split in two."""
    rms_b, rms_a = cal.stats.get("rms_before", np.nan), cal.stats.get("rms_after", np.nan)
    spec = ax.get_subplotspec()
    fig = ax.figure
    ax.remove()
    top, bottom = spec.subgridspec(2, 1)
    for k, (err, rms, colour, label) in enumerate(((err_b, rms_b, "tab:red", "before"),
                                                    (err_a, rms_a, "tab:blue", "after"))):
        axis = fig.add_subplot(top if k == 0 else bottom)
        finite = err[np.isfinite(err)]
        lo, hi = ((float(np.percentile(finite, 0.5)), float(np.percentile(finite, 99.5))) if len(finite)
                  else (0.0, 1.0))
        if not hi > lo:
            lo, hi = lo - 0.5, hi + 0.5
        # stepfilled: one outline per histogram (hundreds of bars would double the report's drawing time)
        axis.hist(finite, bins=np.linspace(lo, hi, 61), color=colour, alpha=0.6, histtype="stepfilled",
                  label=f"{label}: RMS {rms:.3g}")
        axis.set_xlim(lo, hi)
        axis.set(xlabel=f"|B| - F [{cal.units}]", ylabel="samples")
        axis.set_title(f"magnitude error {label} (0.5-99.5 % of samples)", fontsize=10)
        axis.legend(fontsize=8)


#: Colours of the coverage panel's cells: covered (as on the live page) and not.
_COVERED, _EMPTY = "#1b7f3b", "#d9d9d9"


def _coverage_panel(ax: Any, raw: NDArray[np.float64]) -> None:
    """The coverage of the sphere of field directions, drawn as the number is counted
    (:func:`~trimag.quality.diagnostics.data_coverage`): the equal-area cells, filled when they hold enough samples,
    and the directions themselves, in azimuth against sin(elevation) (an equal-area map)."""
    from .._core.sphere import fibonacci_sphere
    from .diagnostics import data_coverage

    cov = data_coverage(raw)
    centre = np.asarray(cov["centre"])
    sub = raw[:: max(1, len(raw) // _MAX_POINTS)] - centre
    u = sub / np.maximum(np.linalg.norm(sub, axis=1, keepdims=True), 1e-300)
    cells = fibonacci_sphere(int(cov["n_cells"]))
    covered = np.asarray(cov["cell_counts"]) >= int(cov["min_count"])
    ax.scatter(np.degrees(np.arctan2(u[:, 1], u[:, 0])), u[:, 2], s=1, color="tab:blue", alpha=0.3, zorder=1)
    ax.scatter(np.degrees(np.arctan2(cells[:, 1], cells[:, 0])), cells[:, 2], s=90,
               c=[_COVERED if k else _EMPTY for k in covered], edgecolors="#555555", linewidths=0.4, alpha=0.75,
               zorder=2)
    ax.set(xlim=(-190, 190), ylim=(-1.08, 1.08), xlabel="azimuth of the field seen [deg]", ylabel="sin(elevation)",
           title=f"sphere coverage: {100 * float(np.mean(covered)):.0f}% of the {len(cells)} equal-area cells\n"
                 f"hold >= {cov['min_count']} samples (green)")
    ax.text(0.01, 0.01, "raw samples about the best-fitting sphere's centre (a property of the data, not of the fit)",
            transform=ax.transAxes, fontsize=7, color="#555555")


def _cloud_panels(axes: Any, B: NDArray[np.float64], corrected: NDArray[np.float64], sub: NDArray[np.intp],
                  unit: str) -> None:
    """The point clouds before and after in the x-y, y-z and x-z planes (three axes)."""
    for k, (i, j, name) in enumerate(((0, 1, "x-y"), (1, 2, "y-z"), (0, 2, "x-z"))):
        ax = axes[k]
        ax.plot(B[sub, i], B[sub, j], ".", ms=1.5, color="tab:red", alpha=0.5, label="before")
        ax.plot(corrected[sub, i], corrected[sub, j], ".", ms=1.5, color="tab:blue", alpha=0.5, label="after")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set(xlabel=f"{name[0]} [{unit}]", ylabel=f"{name[2]} [{unit}]", title=f"point cloud, {name} plane")
        if k == 0:
            ax.legend(fontsize=8, markerscale=6)


def deviation_figure(card: dict[str, Any], *, title: str = "deviation card", before: str = "before",
                     after: str = "after") -> Figure:
    """The deviation card of :func:`trimag.vehicle.heading.deviation_card` as a figure: the heading error against
    the heading, before (``before`` names it) and after (or the error the calibration predicts, 1 sigma, as a
    band around zero)."""
    fig = _figure((8.0, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    h = np.asarray(card["headings_deg"], dtype=np.float64)
    n = np.asarray(card["n"])
    has = n > 0

    def values(key: str) -> NDArray[np.float64]:
        return np.array([np.nan if v is None else v for v in card[key]], dtype=np.float64)

    ax.axhline(0.0, color="k", lw=0.8)
    ax.plot(h[has], values("before_mean_deg")[has], "o-", color="tab:red", label=f"{before}: mean error")
    if card.get("after"):
        ax.errorbar(h[has], values("after_mean_deg")[has], yerr=values("after_rms_deg")[has], fmt="s-",
                    color="tab:blue", capsize=2, label=f"{after}: mean error (bars: RMS)")
    if card.get("after_sigma_deg"):
        sigma = np.asarray(card["after_sigma_deg"], dtype=np.float64)
        ax.fill_between(h, -sigma, sigma, color="tab:blue", alpha=0.25, label=f"{after}: predicted 1 sigma")
    ax.set(xlabel="heading [deg]", ylabel="heading error [deg]", title=title, xlim=(-5, 360))
    ax.set_xticks(np.arange(0, 361, 45))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    return fig


__all__ += ["deviation_figure"]
