"""What the data can identify: sphere coverage of field directions and conditioning of a design.

Every estimator reports these in ``Calibration.diagnostics``; ``IdentifiabilityError`` (exit 3) is raised when
a design is numerically rank deficient, ``IdentifiabilityWarning`` when it is merely ill-conditioned.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.chunks import chunk_rows, row_blocks
from .._core.rowwise import row_dot, scratch
from .._core.solve import levenberg_marquardt
from .._core.sphere import fibonacci_sphere
from ..errors import IdentifiabilityError, IdentifiabilityWarning

__all__ = [
    "CONDITION_ERROR",
    "CONDITION_WARN",
    "DIAGNOSTIC_SAMPLES",
    "FLAT_RATIO",
    "PLANE_NOISE_RATIO",
    "check_not_degenerate",
    "check_not_planar_within_noise",
    "coverage_advice",
    "data_coverage",
    "describe_directions",
    "design_condition",
    "diagnostic_subsample",
    "direction_geometry",
    "fibonacci_sphere",
    "gram_condition",
    "principal_std",
    "raw_direction_geometry",
    "sample_noise_std",
    "single_axis_turn",
    "sphere_centre",
    "sphere_coverage",
    "turn_about_axis",
    "weak_directions",
]

#: Column-normalised condition number above which a fit warns (IdentifiabilityWarning).
CONDITION_WARN = 1e4
#: Column-normalised condition number above which the design is treated as rank deficient (exit 3).
CONDITION_ERROR = 1e9

#: A log whose RMS distance from its best-fitting plane is below this many noise standard deviations lies in one
#: plane within the noise (the sensor turned about a single axis): its out-of-plane shape is fitted to noise.
#: Measured (docs/method-ml.md, "Identifiability"): 1.0-1.9 for single-axis turns at sigma/F = 4e-4 to 5e-2;
#: 5.7 for one hemisphere at sigma/F = 5e-2; 6.3-98 on five real logs.
PLANE_NOISE_RATIO = 3.0
#: Samples whose spread across their flattest direction is below this share of the next spread, and within the fit's
#: residual level, are described as a turn about one axis (a hand-held sensor's wobble adds a little spread across
#: its plane); above it, as samples that do leave the plane but that the ellipsoid does not fit.
FLAT_RATIO = 0.25
#: Diagnostics that summarise the whole log (sphere coverage, degeneracy, and the noise level and Fisher
#: information of the ellipsoid methods) use at most this many evenly spread samples: sums over samples scaled up.
DIAGNOSTIC_SAMPLES = 20_000


def diagnostic_subsample(n: int) -> NDArray[np.int64]:
    """Indices of at most :data:`DIAGNOSTIC_SAMPLES` samples spread evenly over ``0 .. n - 1`` (all when fewer)."""
    return np.linspace(0, n - 1, min(n, DIAGNOSTIC_SAMPLES)).astype(np.int64)


def sphere_coverage(
    directions: ArrayLike, *, n_cells: int = 100, min_count: int | None = None
) -> dict[str, Any]:
    """How much of the sphere of field directions the samples cover.

    Parameters
    ----------
    directions : array_like, shape (N, 3)
        Field vectors (any length; zero rows are ignored), e.g. corrected fields or raw fields minus offset.
    n_cells : int
        Number of equal-area cells (Fibonacci lattice).
    min_count : int, optional
        Samples a cell needs to count as covered; default: 10 % of its share under uniform coverage
        (at least 1), so a few stray samples do not make a cell look covered.

    Returns
    -------
    dict
        ``fraction`` (covered cells / n_cells, 0..1), ``isotropy`` (3 x smallest eigenvalue of the mean
        outer product of unit directions: 1 for an even sphere, 0 for a plane), ``mean_direction_norm``
        (0 for a balanced sphere, 1 for one direction), ``n_cells``, ``min_count``, ``n_used`` (non-zero
        samples counted: at most about :data:`DIAGNOSTIC_SAMPLES`, evenly spread; counts are scaled up to the
        whole log), ``cell_counts`` (list of n_cells ints).
    """
    d = np.asarray(directions, dtype=np.float64)
    stride = max(1, len(d) // DIAGNOSTIC_SAMPLES)  # large logs: an evenly spread subsample, counts scaled
    d = d[::stride]
    norms = np.sqrt(row_dot(d, d))
    nonzero = norms > 0
    u = d[nonzero] / norms[nonzero, None] if not nonzero.all() else d / norms[:, None]
    centres_t = np.ascontiguousarray(fibonacci_sphere(n_cells).T)
    if min_count is None:
        min_count = max(1, int(np.ceil(0.1 * len(u) * stride / n_cells)))  # counts are scaled by the stride
    counts = np.zeros(n_cells, dtype=np.int64)
    # chunks of the nearest-cell search: the (m, n_cells) products and their argmax temporaries stay in cache
    step = chunk_rows(4 * n_cells)
    with scratch(min(len(u), step), n_cells) as dots:  # a reused buffer (trimag._core.rowwise.scratch)
        for rows in row_blocks(len(u), rows=step):
            block = u[rows]
            prod = dots[: len(block)]
            np.matmul(block, centres_t, out=prod)
            counts += np.bincount(prod.argmax(axis=1), minlength=n_cells) * stride
    if len(u):
        scatter = (u.T @ u) / len(u)
        isotropy = float(3.0 * np.linalg.eigvalsh(scatter)[0])
        mean_vector = (np.ones(len(u)) @ u) / len(u)
        mean_norm = float(np.linalg.norm(mean_vector))
    else:
        isotropy, mean_norm, scatter, mean_vector = 0.0, 0.0, None, None
    return {
        "fraction": float(np.mean(counts >= min_count)),
        "isotropy": isotropy,
        "mean_direction_norm": mean_norm,
        "n_cells": n_cells,
        "min_count": int(min_count),
        "n_used": len(u),
        **direction_geometry(u, counts >= min_count, centres_t.T, mean=mean_vector, scatter=scatter),
        "cell_counts": counts.tolist(),
    }


def sphere_centre(B: ArrayLike) -> NDArray[np.float64] | None:
    """Centre (3,) of the sphere of free radius that fits the samples ``B`` (N, 3) best (linear least squares,
    ``|x|^2 = 2 c.x + d``), on an evenly spread subsample of at most :data:`DIAGNOSTIC_SAMPLES`; None when the
    samples do not determine a sphere (fewer than 4, or in one plane or on one line: condition number above 1e6)."""
    x = np.asarray(B, dtype=np.float64)
    x = x[diagnostic_subsample(len(x))] if len(x) > DIAGNOSTIC_SAMPLES else x
    if len(x) < 4:
        return None
    centroid = x.mean(axis=0)
    scale = float(np.abs(x - centroid).max()) or 1.0
    xc = (x - centroid) / scale
    A = np.column_stack([2.0 * xc, np.ones(len(xc))])
    cond, _, _ = design_condition(A)
    if not np.isfinite(cond) or cond > 1e6:
        return None
    sol = np.linalg.lstsq(A, row_dot(xc, xc), rcond=None)[0]
    centre = centroid + scale * sol[:3]
    return centre if np.all(np.isfinite(centre)) else None


def data_coverage(B: ArrayLike) -> dict[str, Any]:
    """The sphere coverage of the field directions a log saw: one number computed from the data alone, the same
    whatever the method fitted to it (and used by the refusals of the application layer).

    The directions are those of the raw samples about the centre of the sphere that fits them best
    (:func:`sphere_centre`; the soft iron is ignored, so the angles are approximate: a few degrees for a few per
    cent of soft iron); samples in one plane are taken about the centre of the circle they lie on. A fitted
    calibration would give other directions, and a badly wrong fit (a small sphere through a narrow cap of
    samples) directions spread over much of the sphere: the coverage is not taken from the fit.

    Returns
    -------
    dict
        :func:`sphere_coverage` of those directions (on at most :data:`DIAGNOSTIC_SAMPLES` evenly spread samples),
        with ``centre`` (3,) and ``basis`` (how the directions were formed).
    """
    x = np.asarray(B, dtype=np.float64)
    x = x[diagnostic_subsample(len(x))] if len(x) > DIAGNOSTIC_SAMPLES else x
    centre = sphere_centre(x)
    basis = "raw samples about the centre of the best-fitting sphere (soft iron ignored)"
    if centre is None and len(x) >= 3:
        mean = x.mean(axis=0)
        vecs = np.linalg.eigh((x - mean).T @ (x - mean))[1]
        p = (x - mean) @ vecs[:, 1:]
        sol = np.linalg.lstsq(np.column_stack([2.0 * p, np.ones(len(p))]), row_dot(p, p), rcond=None)[0]
        centre = mean + vecs[:, 1:] @ sol[:2]
        basis = "raw samples about the centre of the circle they lie on (one plane)"
    if centre is None or not np.all(np.isfinite(centre)):
        centre = x.mean(axis=0) if len(x) else np.zeros(3)
        basis = "raw samples about their mean"
    return {**sphere_coverage(x - centre), "centre": np.asarray(centre, dtype=np.float64).tolist(), "basis": basis}


#: Consecutive samples :func:`sample_noise_std` reads (in the middle of a longer log).
_NOISE_WINDOW = 65_536


def sample_noise_std(B: ArrayLike) -> float | None:
    """The sample-to-sample noise per axis of a log (its unit): ``sqrt(mean(d2^2) / 6)`` of the second differences
    ``d2 = x[i+1] - 2 x[i] + x[i-1]`` of consecutive distinct samples (white noise of standard deviation s gives
    ``var(d2) = 6 s^2``), over at most 65 536 consecutive samples in the middle of the log. Motion between samples
    adds to it (a slowly turned sensor adds little): an upper bound of the noise. None for fewer than 10 samples.
    """
    x = np.asarray(B, dtype=np.float64)
    if len(x) > _NOISE_WINDOW:
        start = (len(x) - _NOISE_WINDOW) // 2
        x = x[start:start + _NOISE_WINDOW]
    if len(x) > 1:
        x = x[np.concatenate([[True], np.any(x[1:] != x[:-1], axis=1)])]  # a logger's repeated rows
    if len(x) < 10:
        return None
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return float(np.sqrt(np.mean(d2 * d2) / 6.0))


#: Share of the samples inside the reported cone (the rest, e.g. a few stray samples, are left out).
CONE_QUANTILE = 0.98
#: Directions within a cone of half-angle below this (degrees) are described as a cone about their mean.
CONE_MAX_DEG = 100.0
#: A cone whose inner angle (the 2 % quantile) is at least this share of its half-angle is a rim: the directions
#: of a turn about a single axis, all at one angle from it.
RIM_RATIO = 0.75
#: Directions whose isotropy (3 x smallest eigenvalue of their mean outer product) is below this lie near a plane.
PLANE_ISOTROPY = 0.1


def direction_geometry(
    u: NDArray[np.float64], covered: NDArray[np.bool_], centres: NDArray[np.float64], *,
    mean: NDArray[np.float64] | None = None, scatter: NDArray[np.float64] | None = None,
) -> dict[str, Any]:
    """The shape of a set of field directions: the cone they stay in and the direction they never reach.

    Parameters
    ----------
    u : ndarray, shape (N, 3)
        Unit field directions (body frame).
    covered : ndarray of bool, shape (n_cells,)
        Which cells of :func:`sphere_coverage` count as covered.
    centres : ndarray, shape (n_cells, 3)
        The cells' centres (:func:`fibonacci_sphere`).
    mean, scatter : ndarray, shape (3,) and (3, 3), optional
        The mean of ``u`` and of its outer products, when already computed.

    Returns
    -------
    dict
        ``shape`` ("cone": within a cone of half-angle below :data:`CONE_MAX_DEG`; "rim": on its surface only, a
        turn about one axis (:data:`RIM_RATIO`); "plane": near a great circle (:data:`PLANE_ISOTROPY`), also a turn
        about one axis; "surround"), ``cone_axis`` (unit vector, the mean direction), ``cone_half_angle_deg`` (the
        angle from it within which :data:`CONE_QUANTILE` of the directions lie; 180 when they surround the
        sensor), ``cone_inner_angle_deg`` (the angle from it within which ``1 - CONE_QUANTILE`` lie),
        ``plane_normal`` (the direction with the least spread of the directions: the axis of a single-axis turn),
        ``never_seen_axis`` (the centre of the empty cell farthest from every covered cell, None when every cell
        is covered) and ``never_seen_within_deg`` (the angle from it to the nearest covered cell's centre).
    """
    if not len(u) or not covered.any():
        return {"shape": None, "cone_axis": None, "cone_half_angle_deg": None, "cone_inner_angle_deg": None,
                "plane_normal": None, "never_seen_axis": None, "never_seen_within_deg": None}
    mean = (np.ones(len(u)) @ u) / len(u) if mean is None else mean
    scatter = (u.T @ u) / len(u) if scatter is None else scatter
    norm = float(np.linalg.norm(mean))
    axis = mean / norm if norm > 1e-12 else np.array([0.0, 0.0, 1.0])
    cosines = u @ axis  # the angle's quantiles are those of the cosine, in reverse (one partition, no arccos)
    k_half, k_inner = int((1.0 - CONE_QUANTILE) * (len(u) - 1)), int(CONE_QUANTILE * (len(u) - 1))
    part = np.partition(cosines, (k_half, k_inner))
    half, inner = (float(np.degrees(np.arccos(np.clip(part[k], -1.0, 1.0)))) for k in (k_half, k_inner))
    ev, vecs = np.linalg.eigh(scatter)
    normal = vecs[:, 0]
    if half < CONE_MAX_DEG:
        shape = "rim" if inner >= RIM_RATIO * half else "cone"
    else:
        shape = "plane" if 3.0 * ev[0] < PLANE_ISOTROPY else "surround"
    never, within = None, None
    if not covered.all():
        empty, full = centres[~covered], centres[covered]
        nearest = np.degrees(np.arccos(np.clip((empty @ full.T).max(axis=1), -1.0, 1.0)))
        k = int(np.argmax(nearest))
        never, within = empty[k].tolist(), float(nearest[k])
    return {"shape": shape, "cone_axis": axis.tolist(), "cone_half_angle_deg": half, "cone_inner_angle_deg": inner,
            "plane_normal": normal.tolist(), "never_seen_axis": never, "never_seen_within_deg": within}


def _axis_name(v: Any) -> str:
    """``+z``, ``-x`` ... when ``v`` is within 20 degrees of a sensor axis, else its components."""
    a = np.asarray(v, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = int(np.argmax(np.abs(a)))
    if abs(a[k]) >= np.cos(np.radians(20.0)):
        return f"{'+' if a[k] > 0 else '-'}{'xyz'[k]} axis"
    return "direction [" + ", ".join(f"{c:.2f}" for c in a) + "]"


def describe_directions(geometry: dict[str, Any]) -> str:
    """One sentence on the field directions a log saw (from :func:`sphere_coverage` or
    :func:`raw_direction_geometry`): the cone they stay in, the covered fraction and the direction never seen."""
    half, axis, kind = geometry.get("cone_half_angle_deg"), geometry.get("cone_axis"), geometry.get("shape")
    if half is None or axis is None:
        return "no field direction could be measured"
    if kind == "rim":
        shape = f"the field directions seen stay on the rim of a cone of half-angle {half:.0f} deg about the " \
                f"sensor's {_axis_name(axis)}, as in a turn about that single axis"
    elif kind == "cone":
        shape = f"the field directions seen stay within a cone of half-angle {half:.0f} deg about the sensor's " \
                f"{_axis_name(axis)}"
    elif kind == "plane":
        shape = f"the field directions seen lie close to one plane, across the sensor's " \
                f"{_axis_name(geometry['plane_normal'])}, as in a turn about that single axis"
    else:
        shape = "the field directions seen surround the sensor"
    text = f"{shape} ({100 * geometry['fraction']:.0f}% of the sphere of directions covered"
    if geometry.get("never_seen_axis") is not None:
        text += f"; no sample within {geometry['never_seen_within_deg']:.0f} deg of its " \
                f"{_axis_name(geometry['never_seen_axis'])}"
    return text + ")"


#: Samples the offset estimate of :func:`raw_direction_geometry` uses (evenly spread).
_GEOMETRY_SAMPLES = 2_000


def raw_direction_geometry(B: NDArray[np.float64], field: float | None = None) -> dict[str, Any] | None:
    """:func:`sphere_coverage` (with its cone and never-seen direction) of raw samples before any calibration.

    The offset is that of the sphere that fits the samples best: of radius ``field`` (the reference magnitude,
    data unit) when given, else of free radius (then it is :func:`data_coverage`, the one coverage of the data,
    issue 32). The soft iron is ignored, so the angles are approximate (a few
    degrees for a few per cent of soft iron). None when no sphere is determined (a free radius on samples in one
    plane: describe them with :func:`turn_about_axis` instead).

    Parameters
    ----------
    B : ndarray, shape (N, 3)
        Raw samples.
    field : float, optional
        The field magnitude in the samples' unit.
    """
    if field is None or not np.isfinite(field) or field <= 0:  # the data's own coverage (one number, issue 32)
        return data_coverage(B) if sphere_centre(B) is not None else None
    x = np.asarray(B, dtype=np.float64)[:: max(1, len(B) // _GEOMETRY_SAMPLES)]
    centroid = x.mean(axis=0)
    xc = x - centroid
    if len(x) < 4:
        return None
    normal = np.linalg.eigh(xc.T @ xc)[1][:, 0]
    depth = float(np.sqrt(max(field**2 - float(np.mean(row_dot(xc, xc))), 0.0)))
    best = None
    for sign in (1.0, -1.0):
        res = levenberg_marquardt(lambda c: np.sqrt(row_dot(xc - c, xc - c)) - field, sign * depth * normal,
                                  method="trf")
        if best is None or res.cost < best.cost:
            best = res
    assert best is not None
    centre = centroid + best.x
    d = x - centre
    if not np.all(np.isfinite(d)):
        return None
    return sphere_coverage(d, min_count=1)


def turn_about_axis(B: NDArray[np.float64]) -> dict[str, Any]:
    """Raw samples seen as a turn about one axis: the axis (least spread), the angle turned about it (degrees,
    360 minus the largest gap of the in-plane angles about the fitted circle's centre) and the RMS spread of the
    samples along it (data unit)."""
    x = np.asarray(B, dtype=np.float64)[:: max(1, len(B) // _GEOMETRY_SAMPLES)]
    xc = x - x.mean(axis=0)
    vecs = np.linalg.eigh(xc.T @ xc)[1]
    normal = vecs[:, 0]
    p = xc @ vecs[:, 1:]
    sol = np.linalg.lstsq(np.column_stack([2.0 * p, np.ones(len(p))]), row_dot(p, p), rcond=None)[0]
    ang = np.sort(np.degrees(np.arctan2(p[:, 1] - sol[1], p[:, 0] - sol[0])))
    gaps = np.diff(np.concatenate([ang, [ang[0] + 360.0]])) if len(ang) else np.array([360.0])
    return {"axis": normal.tolist(), "turned_deg": float(360.0 - gaps.max()),
            "along_std": float(np.sqrt(np.mean((xc @ normal) ** 2)))}


def design_condition(A: ArrayLike) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Condition number of a design matrix after scaling its columns to unit norm.

    Returns
    -------
    cond : float
        Ratio of largest to smallest singular value (``inf`` when rank deficient).
    singular_values : ndarray, shape (p,)
    right_vectors : ndarray, shape (p, p)
        Rows are the right singular vectors (last = weakest direction in scaled parameter space).
    """
    a = np.asarray(A, dtype=np.float64)
    norms = np.linalg.norm(a, axis=0)
    # a column that is zero up to rounding is not scaled up: unit norm would turn rounding noise into apparent
    # information (and the verdict would depend on the order of the sums)
    norms[norms <= 1e-12 * max(float(norms.max(initial=0.0)), 1e-300)] = 1.0
    n, p = a.shape
    if n > 2 * p:
        # tall: the singular values and right vectors of A are those of R in A = QR (Householder, numpy's LAPACK;
        # not scipy's, whose separate OpenBLAS thread pool spin-waits against numpy's: measured 2x slower
        # batch fits). The column-scaled copy goes into a reused buffer (trimag._core.rowwise.scratch).
        with scratch(p, n) as at:
            np.divide(a.T, norms[:, None], out=at)
            r = np.linalg.qr(at.T, mode="r")
        _, s, vt = np.linalg.svd(r)
    else:
        _, s, vt = np.linalg.svd(a / norms, full_matrices=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    return cond, s, vt


def gram_condition(G: ArrayLike) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """:func:`design_condition` of a design ``A`` known only by its Gram matrix ``G = A^T A`` (p, p).

    The same column scaling; the singular values are the square roots of the scaled Gram matrix's eigenvalues.
    Squaring the design costs half the digits: a condition number above about 1e8 is reported as about 1e8, or
    as ``inf`` when an eigenvalue comes out zero or negative. It never fails on a singular ``G``.
    """
    g = np.asarray(G, dtype=np.float64)
    d = np.sqrt(np.clip(np.diag(g), 0.0, None))
    d[d == 0] = 1.0
    ev, vecs = np.linalg.eigh(g / np.outer(d, d))
    s = np.sqrt(np.clip(ev[::-1], 0.0, None))
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    return cond, s, np.ascontiguousarray(vecs[:, ::-1].T)


def weak_directions(
    vt: NDArray[np.float64], s: NDArray[np.float64], names: Sequence[str], *, threshold: float
) -> list[str]:
    """Parameter names that dominate the singular vectors whose singular value is below ``s[0]/threshold``."""
    weak: list[str] = []
    for k in np.nonzero(s < s[0] / threshold)[0]:
        v = np.abs(vt[k])
        for j in np.nonzero(v > 0.3 * v.max())[0]:
            if names[int(j)] not in weak:
                weak.append(names[int(j)])
    return weak


#: the parameters of the models as a user reads them (the ellipsoid's; others keep their names)
PARAMETER_WORDS = {"w11": "the x scale", "w22": "the y scale", "w33": "the vertical (z) scale",
                   "w12": "the x-y coupling", "w13": "the x-z coupling", "w23": "the y-z coupling",
                   "hard_iron_x": "the x offset", "hard_iron_y": "the y offset",
                   "hard_iron_z": "the vertical (z) offset"}


def parameter_words(names: Sequence[str]) -> str:
    """``["hard_iron_x", "w33"]`` -> ``"the x offset and the vertical (z) scale"``, offsets first."""
    said = sorted((PARAMETER_WORDS.get(n, n) for n in names), key=lambda w: "offset" not in w)
    return said[0] if len(said) == 1 else f"{', '.join(said[:-1])} and {said[-1]}"


def condition_words(cond: float) -> str:
    """A condition number as the user reads it: ``"condition number 3.2e+08"``, or for a singular design (infinite
    or NaN) what it means (issue 41, item 17: "condition number inf")."""
    if np.isfinite(cond):
        return f"condition number {cond:.3g}"
    return "a combination of the parameters that the data do not determine at all: a singular design"


def check_condition(
    cond: float,
    *,
    what: str,
    hint: str,
    weak: Sequence[str] = (),
    warn: float = CONDITION_WARN,
    error: float = CONDITION_ERROR,
) -> None:
    """Raise :class:`IdentifiabilityError` above ``error``; warn above ``warn``. Both say what the data do not
    determine in words (:func:`parameter_words` of ``weak``), never the condition number itself: the refusal keeps
    it as a detail (issue 42, item 6: "condition number 4.7e+17" reached the live page)."""
    weak_txt = f" (poorly determined: {', '.join(weak)})" if weak else ""
    if not np.isfinite(cond) or cond > error:
        free = (f"they do not determine {parameter_words(weak)}" if weak else
                "they leave a combination of its parameters undetermined")
        raise IdentifiabilityError(f"the data cannot identify {what}: {free}{weak_txt}; {hint}",
                                   details=[f"{condition_words(cond)} (refused above {error:.0e})"])
    if cond > warn:
        barely = (f"the data barely determine {parameter_words(weak)}" if weak else
                  "the data barely determine a combination of its parameters")
        warnings.warn(
            f"{what} is poorly identified: {barely}{weak_txt}; {hint}",
            IdentifiabilityWarning,
            stacklevel=3,
        )


def principal_std(B: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """Standard deviations of the samples ``B`` (N, 3) along their principal axes (3,), largest first, and their
    largest absolute value; on an evenly spread subsample of at most :data:`DIAGNOSTIC_SAMPLES` samples.

    Computed from the 3 x 3 covariance of the samples scaled by their largest value, component-major in a reused
    buffer (eigenvalue error ~1e-16 of the largest: far below the 1e-12 ratio the plane test needs).
    """
    sub = B[:: max(1, len(B) // DIAGNOSTIC_SAMPLES)]
    with scratch(3, len(sub)) as centred:
        np.copyto(centred, sub.T)
        scale = max(float(centred.max()), -float(centred.min())) or 1.0
        centred -= (centred.sum(axis=1) / centred.shape[1])[:, None]
        centred *= 1.0 / scale
        variances = np.linalg.eigvalsh(centred @ centred.T / centred.shape[1])
    return np.sqrt(np.clip(variances, 0.0, None))[::-1] * scale, scale


def check_not_degenerate(B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Refuse data that no 3-D calibration can use: a stuck sensor, or all samples on one line or plane.

    Returns the principal standard deviations of ``B`` (:func:`principal_std`), for
    :func:`check_not_planar_within_noise`.

    Raises
    ------
    IdentifiabilityError
        With a message saying what to record instead.
    """
    std, scale = principal_std(B)
    if std[0] <= 1e-12 * scale:
        raise IdentifiabilityError(
            "all samples are identical (the sensor appears stuck or the log repeats one value); "
            "check the sensor, then record it while turning it through many attitudes"
        )
    _check_turned(B, std)
    if std[2] <= 1e-6 * std[0]:
        kind = "one line" if std[1] <= 1e-6 * std[0] else "one plane"
        raise IdentifiabilityError(
            f"all samples lie in {kind} (the sensor turned about a single axis, or not at all): the "
            "field along the missing direction is never seen; record rotations about at least two "
            "more axes (or tumble the sensor through all attitudes)"
        )
    return std


#: Samples whose widest principal spread is below this many times their sample-to-sample noise did not turn: a
#: turn of a few degrees spreads them tens of times their noise (a MEMS part at 0.3 % of the field per axis: 1 deg
#: of turn is ~6 x its noise), while a still sensor's spread is its noise (1-1.5 x).
STILL_NOISE_RATIO = 3.0
#: ... and their widest spread is under this angle (degrees) seen from the origin: samples in random order (a
#: simulation, a shuffled file) have a "sample-to-sample noise" as wide as their spread, but a sphere's spread is
#: tens of degrees from the origin (4.8 deg for a phone's hard iron of 12 x the field), a still sensor's its noise
#: (0.2 deg for the unmoved HMC5883L logs).
STILL_MAX_DEG = 1.0


def _check_turned(B: NDArray[np.float64], std: NDArray[np.float64]) -> None:
    """Refuse samples whose widest principal spread ``std[0]`` is within :data:`STILL_NOISE_RATIO` times their
    sample-to-sample noise (:func:`sample_noise_std`) and :data:`STILL_MAX_DEG` seen from the origin: the sensor did
    not turn, and its noise must not be described as a turn or as a sphere of directions (the unmoved HMC5883L logs
    of hmc5883l-sunsided were, review 2)."""
    norm = float(np.linalg.norm(B[diagnostic_subsample(len(B))].mean(axis=0)))
    turned = float(np.degrees(np.arctan2(std[0], norm)))
    if not turned < STILL_MAX_DEG:  # first: it is cheap, and every sensor that turned stops here
        return
    noise = sample_noise_std(B)
    if noise is None or not noise > 0 or std[0] >= STILL_NOISE_RATIO * noise:
        return
    raise IdentifiabilityError(
        f"the sensor did not turn: its samples spread only {std[0]:.4g} RMS at most (principal spreads "
        f"{std[0]:.4g}, {std[1]:.4g}, {std[2]:.4g}), {std[0] / noise:.2g} x the sample-to-sample noise ({noise:.3g} "
        f"per axis, from second differences), about {turned:.2g} deg of the field's direction: record it while "
        "turning it through many attitudes (or tumble it); a vehicle standing still at a known heading can use a "
        "fixed-heading calibration (`heading=DEG`)"
    )


def check_not_planar_within_noise(
    B: NDArray[np.float64], sigma: float, *, std: NDArray[np.float64] | None = None
) -> float:
    """Refuse a log whose spread across its flattest direction is within the fit's residual level; returns the
    ratio it was judged by.

    ``B`` (N, 3): raw samples (:func:`principal_std` takes an evenly spread subsample); ``sigma``: the standard
    deviation per axis of the fit's residuals in their unit. The RMS distance of the samples from their best-fitting
    plane (the smallest principal standard deviation) divided by ``sigma`` is 1-2 when the sensor turned about a
    single axis: the spread out of that plane is noise, so the ellipsoid's extent across it is fitted to noise.
    The same ratio is small when the samples do leave the plane but the residuals are large (the field around the
    sensor changed during the log): the message then says so, measured against the sample-to-sample noise
    (:func:`sample_noise_std`), and does not claim a plane.
    :func:`check_not_degenerate` only catches exact planes (noise-free data); ``std``, the principal standard
    deviations it returned for the same ``B``, saves computing them again.

    Raises
    ------
    IdentifiabilityError
        When the ratio is below :data:`PLANE_NOISE_RATIO`.
    """
    if not sigma > 0:
        return float("inf")
    st = principal_std(B)[0] if std is None else std
    ratio = float(st[2] / sigma)
    if ratio >= PLANE_NOISE_RATIO:
        return ratio
    noise = sample_noise_std(B)
    spreads = f"principal spreads {st[0]:.4g}, {st[1]:.4g}, {st[2]:.4g}"
    residuals = f"the fit's residuals ({sigma:.3g} per axis)"
    if noise is not None and noise > 0:
        versus_noise = (f"{st[2] / noise:.3g} x the sample-to-sample noise ({noise:.3g} per axis, from second "
                        "differences)")
    else:
        versus_noise = ""
    within_noise = not versus_noise or st[2] < PLANE_NOISE_RATIO * noise  # type: ignore[operator]
    if within_noise or st[2] < FLAT_RATIO * st[1]:
        turn = turn_about_axis(B)
        if within_noise:  # the sample-to-sample variation is named when it is the tighter bound of the noise
            tighter = versus_noise and noise < sigma  # type: ignore[operator]
            head, measured = "all samples lie in one plane within the noise", (
                f"{versus_noise + ' and ' if tighter else ''}{ratio:.2g} x {residuals}")
            tail = ""
        else:
            head, measured = "the samples lie close to one plane, within the fit's residuals", (
                f"{versus_noise} but only {ratio:.2g} x {residuals}")
            tail = ("; if the sensor did turn about several axes, the field around it changed during the log (nearby "
                    "or moving iron): record again away from it")
        raise IdentifiabilityError(
            f"{head}: they turned through {turn['turned_deg']:.0f} deg about the sensor's {_axis_name(turn['axis'])}, "
            f"and across that plane they spread {st[2]:.4g} RMS ({spreads}): {measured}, too little to fit the "
            f"ellipsoid's shape across it: record rotations about at least two more axes{tail}"
        )
    normal = np.linalg.eigh(np.cov(B[diagnostic_subsample(len(B))].T))[1][:, 0]
    raise IdentifiabilityError(
        f"the ellipsoid cannot be identified: the samples do leave the plane of their two widest spreads (across it, "
        f"along the sensor's {_axis_name(normal)}, they spread {st[2]:.4g} RMS, {versus_noise}; {spreads}), but "
        f"{residuals} are as large as that spread ({ratio:.2g} x them): the field around the sensor changed during "
        "the log (nearby or moving iron, the vehicle's own field) or the sensor is not linear, so its shape across "
        "that direction is lost in the misfit; record again away from iron, turning the sensor through all attitudes"
    )


def coverage_advice(B: NDArray[np.float64], field: float | None = None, *, what: str) -> str:
    """What the raw samples ``B`` (N, 3) saw, and what to record so that they identify ``what`` (e.g. "the 9
    scalar9 parameters"): the cone of field directions, its covered fraction and the direction never seen
    (:func:`raw_direction_geometry`, with the reference magnitude ``field`` when known), or, for samples in one
    plane, the axis they turned about (:func:`turn_about_axis`)."""
    geometry = raw_direction_geometry(B, field)
    if geometry is None or geometry.get("cone_half_angle_deg") is None:
        return single_axis_turn(B, what)
    text = describe_directions(geometry)
    if geometry["shape"] in ("rim", "plane"):
        return f"{text}: a turn about a single axis cannot identify {what}; record turns about at least two more axes"
    if geometry["shape"] == "cone":
        never = geometry.get("never_seen_axis")
        towards = f" and near its {_axis_name(never)}" if never is not None else ""
        return (
            f"{text}: a cone this narrow cannot identify {what}; tilt the sensor further, so that the field is also "
            f"seen from the side{towards} (turn it over); a vehicle that cannot tilt that far can use a vector fit "
            "with attitudes and the background field (`model=interference12`), which needs much less tilt"
        )
    return f"{text}: record the sensor turning about all three axes (or tumble it through all attitudes)"


def single_axis_turn(B: NDArray[np.float64], what: str) -> str:
    """Samples ``B`` (N, 3) in one plane described as the turn they are (:func:`turn_about_axis`), with advice."""
    turn = turn_about_axis(B)
    return (
        f"the samples turned through {turn['turned_deg']:.0f} deg about the sensor's {_axis_name(turn['axis'])} "
        f"and hardly along it (RMS spread {turn['along_std']:.4g}): a turn about a single axis cannot identify "
        f"{what}; record turns about at least two more axes"
    )
