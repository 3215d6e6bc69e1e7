"""Tolles–Lawson fit: band-passed (ridge) least squares of the TL design on a scalar magnetometer.

Equations (docs/method-tolles-lawson.md): with ``A`` the TL design of each contiguous segment
(:func:`trimag.models.tolles_lawson.design`) and ``S`` the scalar magnetometer, both band-passed segment by
segment and trimmed (:class:`trimag.aircraft.filtering.BandPass`), then stacked into ``A_f`` and ``S_f``:

    c = (A_f' A_f + lambda I)^-1 A_f' S_f                                      (MagNav.jl create_TL_coef)

``lambda`` is given, 0 (ordinary least squares), or chosen by time-blocked cross-validation (``"cv"``: the
stacked rows cut into ``k`` contiguous blocks; each block predicted from the others; lambda minimising the
held-out error on a log grid). The compensated scalar is ``S - A c`` (the unfiltered design).

Near-collinear terms (MagNav's default 18 terms hold two sums the band-passed data barely see: ``ind_xx + ind_yy +
ind_zz`` and the eddy one) make ``A_f' A_f + lambda I`` numerically singular; its solve then returned coefficients
of 1e9 fitted to rounding noise (issue 33, item 6). The system is solved with its columns scaled to unit diagonal;
when the ratio of its smallest to largest eigenvalue is below 1e-12 the directions under that ratio are left out
(the minimum-norm least-squares solution: their combinations are not identified, the collinear-terms warning says
so). The band-passed standard deviations reported after compensation, per segment and overall, are those of the
compensated signal ``S - A c`` band-passed segment by segment, not differences of the block sums (which cancel
catastrophically on large coefficients).

Uncertainty. The formal covariance ``s^2 H^-1 A_f'A_f H^-1`` (``H = A_f'A_f + lambda I``, ``s^2`` the residual
variance) assumes white residuals; band-passed residuals are strongly correlated and the aircraft's field is
not exactly the model, so the formal sigmas understate the spread between calibration segments. A moving-block
bootstrap over time blocks (default 10 s, about one manoeuvre) refits ``c`` on resampled blocks; the reported
``std`` is the larger of the two.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..aircraft.compensation import ScalarCompensation
from ..aircraft.filtering import BandPass, finite_runs
from ..errors import IdentifiabilityError, TrimagInputError
from ..models.tolles_lawson import TERM_KINDS, TollesLawsonTerms, parse_terms

__all__ = ["fit_tolles_lawson"]


@dataclass(frozen=True)
class FilteredSums:
    """The band-passed TL system reduced to sums over consecutive time blocks (bounded memory).

    Each segment is designed, band-passed and trimmed on its own, then cut into blocks of ``block_rows`` rows
    (its remainder joins its last block; no block straddles two segments) and kept only as the block sums below:
    every later step (solve, residual variance, cross-validation, bootstrap, per-segment statistics,
    collinearity) works on these sums, so memory does not grow with the band-passed design.

    Attributes
    ----------
    G : ndarray, shape (n_blocks, p, p)
        ``A_b' A_b`` of each block of the band-passed design.
    g : ndarray, shape (n_blocks, p)
        ``A_b' y_b``.
    yy, y_sum, n : ndarray, shape (n_blocks,)
        ``y_b' y_b``, ``sum(y_b)`` and the number of rows of each block.
    A_sum : ndarray, shape (n_blocks, p)
        Column sums of each block.
    segment_of_block : ndarray of int, shape (n_blocks,)
        Index (into ``segments``) of each block's segment.
    segments : list of (start, stop)
        Row ranges of the input used (after skipping the too-short ones).
    n_skipped_segments, n_skipped_rows : int
        Segments too short for the filter, and their rows.
    """

    G: NDArray[np.float64]
    g: NDArray[np.float64]
    yy: NDArray[np.float64]
    y_sum: NDArray[np.float64]
    A_sum: NDArray[np.float64]
    n: NDArray[np.int64]
    segment_of_block: NDArray[np.int64]
    segments: list[tuple[int, int]]
    n_skipped_segments: int
    n_skipped_rows: int

    def total(self, mask: NDArray[np.bool_] | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        """``(A'A, A'y, y'y)`` summed over the blocks in ``mask`` (all by default)."""
        m = slice(None) if mask is None else mask
        return self.G[m].sum(axis=0), self.g[m].sum(axis=0), float(self.yy[m].sum())

    def rss(self, coef: NDArray[np.float64], mask: NDArray[np.bool_] | None = None) -> float:
        """Residual sum of squares ``|y - A c|^2`` over the blocks in ``mask``."""
        G, g, yy = self.total(mask)
        return float(yy - 2.0 * coef @ g + coef @ G @ coef)

    def residual_std(self, coef: NDArray[np.float64] | None, mask: NDArray[np.bool_] | None = None) -> float:
        """Std of ``y - A c`` (of ``y`` when ``coef`` is None) over the blocks in ``mask``."""
        m = slice(None) if mask is None else mask
        n = float(self.n[m].sum())
        if coef is None:
            ss, s1 = float(self.yy[m].sum()), float(self.y_sum[m].sum())
        else:
            ss, s1 = self.rss(coef, mask), float(self.y_sum[m].sum() - coef @ self.A_sum[m].sum(axis=0))
        return float(np.sqrt(max(ss / n - (s1 / n) ** 2, 0.0)))


def _block_sums(A: NDArray[np.float64], y: NDArray[np.float64], block_rows: int) -> tuple[NDArray[Any], ...]:
    """Sums of consecutive blocks of rows (the remainder joins the last block), vectorised over blocks."""
    n, p = A.shape
    nb = max(n // block_rows, 1)
    L = n // nb if nb == 1 else block_rows
    full = (nb - 1) * L
    head_A = A[:full].reshape(nb - 1, L, p)
    head_y = y[:full].reshape(nb - 1, L)
    G = np.concatenate([np.einsum("bli,blj->bij", head_A, head_A), (A[full:].T @ A[full:])[None]])
    g = np.concatenate([np.einsum("bli,bl->bi", head_A, head_y), (A[full:].T @ y[full:])[None]])
    yy = np.concatenate([np.einsum("bl,bl->b", head_y, head_y), [y[full:] @ y[full:]]])
    y_sum = np.concatenate([head_y.sum(axis=1), [y[full:].sum()]])
    A_sum = np.concatenate([head_A.sum(axis=1), A[full:].sum(axis=0)[None]])
    counts = np.concatenate([np.full(nb - 1, L), [n - full]]).astype(np.int64)
    return G, g, yy, y_sum, A_sum, counts


def filtered_sums(
    vector_nT: NDArray[np.float64],
    scalar_nT: NDArray[np.float64],
    segments: Sequence[tuple[int, int]],
    terms: TollesLawsonTerms,
    bandpass: BandPass,
    block_rows: int,
) -> FilteredSums:
    """Design and target of every segment, band-passed and trimmed segment by segment, reduced to block sums."""
    parts: list[tuple[NDArray[np.float64], ...]] = []
    owner: list[NDArray[np.int64]] = []
    used: list[tuple[int, int]] = []
    n_skip = n_skip_rows = 0
    for start, stop in segments:
        if stop - start < bandpass.min_length:
            n_skip += 1
            n_skip_rows += stop - start
            continue
        A_f = bandpass.apply(terms.design(vector_nT[start:stop], scalar_nT[start:stop]))
        y_f = bandpass.apply(scalar_nT[start:stop])
        parts.append(_block_sums(A_f, y_f, block_rows))
        owner.append(np.full(len(parts[-1][0]), len(used), dtype=np.int64))
        used.append((start, stop))
    if not used:
        raise IdentifiabilityError(
            f"no segment is long enough for the band-pass filter (each needs >= {bandpass.min_length} samples "
            f"= {bandpass.min_length / bandpass.rate_hz:.3g} s at {bandpass.rate_hz:g} Hz without gaps: the filter's "
            f"edges and one period of the band's low edge {bandpass.low_hz:g} Hz); record longer calibration "
            "manoeuvres or give longer segments (or check the rate)"
        )
    G, g, yy, y_sum, A_sum, counts = (np.concatenate([part[k] for part in parts]) for k in range(6))
    return FilteredSums(G, g, yy, y_sum, A_sum, counts.astype(np.int64), np.concatenate(owner), used, n_skip,
                        n_skip_rows)


#: smallest eigenvalue ratio of the scaled normal equations solved as they are (see the module docstring)
_RCOND = 1e-12


def _solve_gram(G: NDArray[np.float64], g: NDArray[np.float64], lam: float) -> NDArray[np.float64]:
    """Ridge normal equations ``(G + lam I) c = g``, columns scaled to unit diagonal; directions whose eigenvalue is
    below :data:`_RCOND` of the largest are left out (minimum-norm least squares)."""
    H = G + lam * np.eye(G.shape[0]) if lam else G
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    d[d == 0] = 1.0
    Hn = H / np.outer(d, d)
    w, V = np.linalg.eigh(Hn)
    if w[0] > _RCOND * w[-1]:  # well conditioned: the plain solve
        return np.asarray(np.linalg.solve(H, g), dtype=np.float64)
    keep = w > _RCOND * w[-1]
    return np.asarray(V[:, keep] @ ((V[:, keep].T @ (g / d)) / w[keep]) / d, dtype=np.float64)


def _cv_lambda(sums: FilteredSums, folds: int = 5) -> tuple[float, dict[str, Any]]:
    """Ridge lambda by time-blocked cross-validation: ``folds`` contiguous folds of the blocks, in time order."""
    nb = len(sums.n)
    folds = max(min(folds, nb), 2)
    labels = np.minimum(np.arange(nb) * folds // nb, folds - 1)
    G_all, g_all, _ = sums.total()
    p = G_all.shape[0]
    grid = float(np.trace(G_all)) / p * np.logspace(-10, 0, 21)
    scores = []
    for lam in grid:
        sse = 0.0
        for k in range(folds):
            test = labels == k
            G_k, g_k, _ = sums.total(test)
            sse += sums.rss(_solve_gram(G_all - G_k, g_all - g_k, float(lam)), test)
        scores.append(sse / float(sums.n.sum()))
    best = int(np.argmin(scores))
    return float(grid[best]), {"grid": grid.tolist(), "cv_mse": scores, "folds": folds, "chosen": float(grid[best])}


def _formal_std(sums: FilteredSums, coef: NDArray[np.float64], lam: float) -> NDArray[np.float64]:
    """Sigmas of ``s^2 H^-1 G H^-1`` (white residuals assumed), ``s^2`` on the effective degrees of freedom."""
    G, _, _ = sums.total()
    H_inv = np.linalg.pinv(G + lam * np.eye(G.shape[0]))
    dof = float(np.trace(H_inv @ G))
    s2 = sums.rss(coef) / max(float(sums.n.sum()) - dof, 1.0)
    return np.asarray(np.sqrt(np.clip(np.diag(s2 * H_inv @ G @ H_inv), 0.0, None)), dtype=np.float64)


def _block_bootstrap_std(sums: FilteredSums, lam: float, n_boot: int, seed: int) -> NDArray[np.float64]:
    """Std of the coefficients over a block bootstrap: time blocks drawn with replacement, the fit redone."""
    nb = len(sums.n)
    rng = np.random.default_rng(seed)
    counts = np.stack([np.bincount(rng.integers(0, nb, nb), minlength=nb) for _ in range(n_boot)]).astype(float)
    Gs = np.tensordot(counts, sums.G, axes=1)
    gs = counts @ sums.g
    coefs = np.stack([_solve_gram(Gs[b], gs[b], lam) for b in range(n_boot)])
    return np.asarray(coefs.std(axis=0, ddof=1), dtype=np.float64)


def _segment_consistency(sums: FilteredSums, lam: float, n_boot: int, seed: int) -> dict[str, Any] | None:
    """Predicted against observed spread of the coefficients between segments fitted one by one.

    Each segment long enough (more band-passed rows than coefficients, at least 4 blocks) is fitted alone; for
    consecutive pairs ``z = (c_i - c_j) / sqrt(s_i^2 + s_j^2)``, with formal and with block-bootstrap sigmas.
    An RMS z near 1 means the sigmas predict the spread; the formal one is typically several times larger.
    """
    p = sums.G.shape[1]
    fits = []
    for k in range(len(sums.segments)):
        mask = sums.segment_of_block == k
        if int(sums.n[mask].sum()) <= 2 * p or int(mask.sum()) < 4:
            continue
        sub = FilteredSums(sums.G[mask], sums.g[mask], sums.yy[mask], sums.y_sum[mask], sums.A_sum[mask],
                           sums.n[mask], np.zeros(int(mask.sum()), dtype=np.int64), [sums.segments[k]], 0, 0)
        G, g, _ = sub.total()
        c = _solve_gram(G, g, lam)
        fits.append((k, c, _formal_std(sub, c, lam), _block_bootstrap_std(sub, lam, n_boot, seed) if n_boot else None))
    if len(fits) < 2:
        return None
    pairs, z_f, z_b = [], [], []
    for (i, ci, fi, bi), (j, cj, fj, bj) in itertools.pairwise(fits):
        zf = (ci - cj) / np.sqrt(fi**2 + fj**2)
        z_f.append(zf)
        entry: dict[str, Any] = {"segments": [i, j], "rms_z_formal": float(np.sqrt(np.mean(zf**2)))}
        if bi is not None and bj is not None:
            zb = (ci - cj) / np.sqrt(np.maximum(fi, bi) ** 2 + np.maximum(fj, bj) ** 2)
            z_b.append(zb)
            entry["rms_z_reported"] = float(np.sqrt(np.mean(zb**2)))
        pairs.append(entry)
    out: dict[str, Any] = {"pairs": pairs, "rms_z_formal": float(np.sqrt(np.mean(np.square(z_f))))}
    if z_b:
        out["rms_z_reported"] = float(np.sqrt(np.mean(np.square(z_b))))
    out["note"] = ("z = difference of two segments' coefficients over its predicted sigma: ~1 when the sigmas hold; "
                   "'reported' uses max(formal, bootstrap), as the fit reports")
    return out


def _collinear_terms(sums: FilteredSums, names: list[str]) -> dict[str, Any]:
    """Condition of the band-passed design, variance inflation factors and the near-collinear term groups."""
    G, _, _ = sums.total()
    n = float(sums.n.sum())
    scale = np.sqrt(np.diag(G))
    scale[scale == 0] = 1.0
    Gn = G / np.outer(scale, scale)
    eigval, eigvec = np.linalg.eigh(Gn)
    eigval = np.clip(eigval[::-1], 0.0, None)
    eigvec = eigvec[:, ::-1]
    sv = np.sqrt(eigval)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    mean = sums.A_sum.sum(axis=0) / n
    cov = G / n - np.outer(mean, mean)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    sd[sd == 0] = 1.0
    vif = np.diag(np.linalg.pinv(cov / np.outer(sd, sd)))
    groups = []
    for k in np.flatnonzero(sv < sv[0] * 1e-3):
        members = [names[j] for j in np.flatnonzero(np.abs(eigvec[:, k]) > 0.25)]
        groups.append({"singular_value_ratio": float(sv[k] / sv[0]), "terms": members})
    out: dict[str, Any] = {
        "condition_number": cond,
        "vif": dict(zip(names, vif.tolist(), strict=True)),
        "collinear_groups": groups,
    }
    diag = [names.index(x) for x in ("ind_xx", "ind_yy", "ind_zz") if x in names]
    if len(diag) == 3:
        w = np.zeros(len(names))
        w[diag] = 1.0
        total_sd = float(np.sqrt(max(float(w @ cov @ w), 0.0)))
        out["induced_diagonal_sum_ratio"] = total_sd / max(float(sd[diag].max()), 1e-300)
    return out


def manoeuvre_content(
    vector_nT: NDArray[np.float64], attitude_deg: NDArray[np.float64] | None = None
) -> dict[str, float]:
    """Peak-to-peak manoeuvre amplitude of one segment, degrees.

    With attitudes (yaw, pitch, roll in degrees) their peak-to-peak (yaw unwrapped); without, the peak-to-peak of
    the field direction's angles in the body frame: ``asin(u_x)``, ``asin(u_y)`` (about the pitch and roll axes
    for a field near the vertical) and ``atan2(u_y, u_x)`` (heading-like).
    """
    if attitude_deg is not None:
        yaw = np.degrees(np.unwrap(np.radians(attitude_deg[:, 0])))
        return {"yaw_p2p_deg": float(np.ptp(yaw)), "pitch_p2p_deg": float(np.ptp(attitude_deg[:, 1])),
                "roll_p2p_deg": float(np.ptp(attitude_deg[:, 2]))}
    u = vector_nT / np.linalg.norm(vector_nT, axis=1, keepdims=True)
    heading = np.degrees(np.unwrap(np.arctan2(u[:, 1], u[:, 0])))
    return {
        "direction_x_p2p_deg": float(np.ptp(np.degrees(np.arcsin(np.clip(u[:, 0], -1, 1))))),
        "direction_y_p2p_deg": float(np.ptp(np.degrees(np.arcsin(np.clip(u[:, 1], -1, 1))))),
        "direction_heading_p2p_deg": float(np.ptp(heading)),
    }


def segment_std(
    signal_nT: NDArray[np.float64], segments: Sequence[tuple[int, int]], bandpass: BandPass
) -> list[float | None]:
    """Std of the band-passed, trimmed signal of each segment (None when a segment is too short)."""
    out: list[float | None] = []
    for start, stop in segments:
        x = signal_nT[start:stop]
        out.append(float(np.std(bandpass.apply(x))) if stop - start >= bandpass.min_length else None)
    return out


def fit_tolles_lawson(
    vector_nT: ArrayLike,
    scalar_nT: ArrayLike,
    *,
    rate_hz: float,
    segments: Sequence[tuple[int, int]] | None = None,
    terms: str | Sequence[str] | None = None,
    band_hz: tuple[float, float] = (0.1, 0.9),
    poles: int = 4,
    trim: int = 20,
    ridge: float | str = 0.0,
    Bt_source: str = "vector",
    Bt_scale: float = 50_000.0,
    derivative_scheme: str = "central",
    bootstrap: int = 200,
    bootstrap_block_s: float = 10.0,
    seed: int = 0,
    attitude_deg: ArrayLike | None = None,
    sensors: dict[str, Any] | None = None,
) -> ScalarCompensation:
    """Fit Tolles–Lawson coefficients (see the module docstring for the equations).

    Parameters
    ----------
    vector_nT : array_like, shape (N, 3)
        Vector magnetometer (fluxgate), nT, in time order.
    scalar_nT : array_like, shape (N,)
        Scalar magnetometer to compensate, nT.
    rate_hz : float
        Sample rate, Hz.
    segments : sequence of (start, stop), optional
        Contiguous row ranges to fit on (calibration-box manoeuvres); default: the runs of finite rows.
    terms : str or sequence, optional
        Term groups (default permanent, induced, eddy: 18 coefficients, as MagNav.jl).
    band_hz, poles, trim : filter (default 0.1-0.9 Hz, 4 poles, 20 samples trimmed per segment end).
    ridge : float or "cv"
        Ridge lambda (MagNav.jl's default in its examples: 1e-3 on its scale), 0 for least squares, or "cv".
    Bt_source : {"vector", "scalar"}
        Magnitude used for the direction cosines.
    bootstrap : int
        Block-bootstrap replicates for the coefficient uncertainty (0: formal only).
    attitude_deg : array_like, shape (N, 3), optional
        Yaw, pitch, roll (degrees) for the manoeuvre-content report.

    Returns
    -------
    ScalarCompensation

    Raises
    ------
    TrimagInputError
        Shapes, non-physical inputs, a bad option.
    IdentifiabilityError
        No segment long enough, fewer filtered rows than coefficients.
    """
    B, S = _checked_series(vector_nT, scalar_nT, Bt_source)
    model_terms = TollesLawsonTerms(parse_terms(terms), float(Bt_scale), derivative_scheme, Bt_source)
    bandpass = BandPass(float(band_hz[0]), float(band_hz[1]), float(rate_hz), int(poles), int(trim))
    ok = np.isfinite(B).all(axis=1) & np.isfinite(S)
    block_rows = max(round(bootstrap_block_s * rate_hz), 10)
    sums = filtered_sums(B, S, _finite_segments(ok, segments), model_terms, bandpass, block_rows)
    n, p = int(sums.n.sum()), len(model_terms.names)
    if n <= p:
        raise IdentifiabilityError(
            f"{n} band-passed samples cannot identify {p} Tolles–Lawson coefficients; record a longer calibration"
        )
    lam, cv_info = _ridge_lambda(ridge, sums)
    G_all, g_all, _ = sums.total()
    coef = _solve_gram(G_all, g_all, lam)
    uncertainty = _coefficient_uncertainty(sums, coef, lam, model_terms.names, int(bootstrap), bootstrap_block_s,
                                           block_rows, seed)
    stats = _fit_stats(B, S, ok, sums, coef, model_terms, bandpass,
                       None if attitude_deg is None else np.asarray(attitude_deg, dtype=float))
    diagnostics = _fit_diagnostics(sums, model_terms, lam, cv_info, int(bootstrap), seed,
                                   stats["std_before_nT"], stats["std_after_nT"], stats["segments"])
    return ScalarCompensation(
        terms=model_terms, coefficients=coef, bandpass=bandpass, ridge=lam, sensors=dict(sensors or {}),
        uncertainty=uncertainty, stats=stats, diagnostics=diagnostics,
    )


def _checked_series(
    vector_nT: ArrayLike, scalar_nT: ArrayLike, Bt_source: str
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The vector (N, 3) and scalar (N,) series as float arrays, after the shape and option checks."""
    B = np.asarray(vector_nT, dtype=np.float64)
    S = np.asarray(scalar_nT, dtype=np.float64)
    if B.ndim != 2 or B.shape[1] != 3 or S.shape != (len(B),):
        raise TrimagInputError(f"need a vector (N, 3) and a scalar (N,) series; got {B.shape} and {S.shape}")
    if Bt_source not in ("vector", "scalar"):
        raise TrimagInputError(f"Bt_source must be 'vector' or 'scalar'; got {Bt_source!r}")
    return B, S


def _finite_segments(ok: NDArray[np.bool_], segments: Sequence[tuple[int, int]] | None) -> list[tuple[int, int]]:
    """The runs of finite rows (``ok``), within the given ``segments`` when there are any."""
    if segments is None:
        return list(finite_runs(ok))
    return [run for a, b in segments for run in ((a + s, a + e) for s, e in finite_runs(ok[a:b]))]


def _ridge_lambda(ridge: float | str, sums: FilteredSums) -> tuple[float, dict[str, Any] | None]:
    """The ridge lambda (a number >= 0, or chosen by cross-validation for ``"cv"``) and the cross-validation
    record (None for a number)."""
    if isinstance(ridge, str):
        if ridge.strip().lower() != "cv":
            raise TrimagInputError(f"ridge must be a number >= 0 or 'cv'; got {ridge!r}")
        return _cv_lambda(sums)
    lam = float(ridge)
    if not (lam >= 0 and np.isfinite(lam)):
        raise TrimagInputError(f"ridge must be a number >= 0 or 'cv'; got {ridge!r}")
    return lam, None


def _coefficient_uncertainty(
    sums: FilteredSums, coef: NDArray[np.float64], lam: float, names: list[str], bootstrap: int, block_s: float,
    block_rows: int, seed: int,
) -> dict[str, Any]:
    """Formal and block-bootstrap standard deviations of the coefficients (nT per term unit) and the reported
    ``std = max(formal, bootstrap)``."""
    formal = _formal_std(sums, coef, lam)
    uncertainty: dict[str, Any] = {"formal_std": dict(zip(names, formal.tolist(), strict=True))}
    std = formal
    if bootstrap:
        boot = _block_bootstrap_std(sums, lam, bootstrap, seed)
        std = np.maximum(formal, boot)
        uncertainty.update({
            "bootstrap_std": dict(zip(names, boot.tolist(), strict=True)),
            "bootstrap": {"replicates": bootstrap, "block_s": block_s, "block_rows": block_rows,
                          "blocks": len(sums.n), "seed": seed},
        })
    uncertainty["std"] = dict(zip(names, std.tolist(), strict=True))
    uncertainty["note"] = ("std = max(formal, block bootstrap); formal sigmas assume white residuals and "
                           "understate the spread between calibration segments")
    return uncertainty


def _fit_stats(
    B: NDArray[np.float64], S: NDArray[np.float64], ok: NDArray[np.bool_], sums: FilteredSums,
    coef: NDArray[np.float64], terms: TollesLawsonTerms, bandpass: BandPass, att: NDArray[np.float64] | None,
) -> dict[str, Any]:
    """Sample counts, band-passed std before and after compensation (nT), overall and per segment with its
    manoeuvre content. After: of the compensated signal band-passed segment by segment (see the module
    docstring)."""
    per_segment = []
    moments = np.zeros(3)  # n, sum, sum of squares of every segment's band-passed compensated signal
    for k, (start, stop) in enumerate(sums.segments):
        mask = sums.segment_of_block == k
        residual = bandpass.apply(S[start:stop] - terms.design(B[start:stop], S[start:stop]) @ coef)
        moments += np.array([len(residual), residual.sum(), residual @ residual])
        sb, sa = sums.residual_std(None, mask), float(np.std(residual))
        entry: dict[str, Any] = {"rows": [start, stop], "n": stop - start, "std_before_nT": sb, "std_after_nT": sa,
                                 "improvement_ratio": (sb / sa) if sa > 0 else None}
        entry.update(manoeuvre_content(B[start:stop], None if att is None else att[start:stop]))
        per_segment.append(entry)
    y_std = sums.residual_std(None)
    r_std = float(np.sqrt(max(moments[2] / moments[0] - (moments[1] / moments[0]) ** 2, 0.0)))
    return {
        "n_samples": len(B),
        "n_used": int(sum(b - a for a, b in sums.segments)),
        "n_filtered_rows": int(sums.n.sum()),
        "n_dropped_rows": int((~ok).sum()),
        "n_skipped_segments": sums.n_skipped_segments,
        "n_skipped_rows": sums.n_skipped_rows,
        "std_before_nT": y_std,
        "std_after_nT": r_std,
        "improvement_ratio": y_std / r_std if r_std > 0 else None,
        "segments": per_segment,
    }


def _fit_diagnostics(
    sums: FilteredSums, model_terms: TollesLawsonTerms, lam: float, cv_info: dict[str, Any] | None,
    bootstrap: int, seed: int, y_std: float, r_std: float, segments: list[dict[str, Any]],
) -> dict[str, Any]:
    """Term kinds, collinearity, the ridge cross-validation, segment consistency and the warnings of a fit."""
    diagnostics: dict[str, Any] = {"term_kinds": {g: TERM_KINDS[g] for g in model_terms.terms}}
    diagnostics.update(_collinear_terms(sums, model_terms.names))
    if cv_info is not None:
        diagnostics["ridge_cv"] = cv_info
    consistency = _segment_consistency(sums, lam, min(bootstrap, 100), seed)
    if consistency is not None:
        diagnostics["segment_consistency"] = consistency
    warnings_list = []
    if diagnostics["collinear_groups"]:
        groups = "; ".join(" + ".join(g["terms"]) for g in diagnostics["collinear_groups"])
        warnings_list.append(
            f"near-collinear terms (their coefficients are not separately identified, only their sum): {groups}"
        )
    if y_std > 0 and r_std >= y_std:
        warnings_list.append("the compensation does not reduce the band-passed scalar: check the columns and units")
    worse = [k for k, seg in enumerate(segments) if seg["std_after_nT"] >= seg["std_before_nT"] > 0]
    if worse and not r_std >= y_std:
        warnings_list.append(
            f"the compensation does not reduce the band-passed scalar of segment(s) {', '.join(map(str, worse))}: "
            "they do not behave as the others (another aircraft configuration, a disturbance); fit them apart or "
            "leave them out with `segments`"
        )
    diagnostics["warnings"] = warnings_list
    return diagnostics
