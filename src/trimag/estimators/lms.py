"""``lms``: the adaptive (stochastic-gradient) baseline paper D compares against, a dual normalised LMS.

Paper D (methods.md) cites an earlier calibration solved with a "dual LMS" adaptive filter, which needs data
from all directions. The cited paper is not available; this is a documented reconstruction. Two normalised
LMS updates run side by side on the same error, one for the correction matrix and one for the offset, sample
by sample in the recorded order (an adaptive filter sees the data as a stream), for ``n_epochs`` passes::

    e_i  = u_i - b,   y_i = M e_i,   err_i = t_i - |y_i|
    g_M  = d|y_i|/dM (upper entries),  g_b = d|y_i|/db
    M   += mu_matrix * err_i * g_M / |g_M|^2
    b   += mu_offset * err_i * g_b / |g_b|^2

in the unit-free scaling ``u = V / F_ref``, ``t_i = F_i / F_ref`` (``F_ref`` the RMS reference magnitude), from
the nominal start (identity scaled to the mean magnitude, zero offset). It stops early when the RMS error over
an epoch falls below ``tol``. The update is sequential by nature: it is the one place in trimag with a Python
loop over samples, and ``max_updates`` bounds its cost on long logs.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.chunks import row_blocks
from ..calibration import Calibration
from ..errors import TrimagInputError
from ._common import iterative_start
from ._finish import finish_iterative
from ._quadric import check_identifiable, identifiability_report, require_magnitude
from .base import Estimator

__all__ = ["LMS"]



def dual_lms(
    u: NDArray[np.float64],
    t: NDArray[np.float64],
    p0: NDArray[np.float64],
    *,
    mu_matrix: float,
    mu_offset: float,
    n_epochs: int,
    tol: float,
    order: NDArray[np.int64] | None = None,
) -> tuple[NDArray[np.float64], int, list[float]]:
    """Run the dual NLMS recursion.

    Parameters
    ----------
    u : ndarray, shape (N, 3)
        Scaled samples.
    t : ndarray, shape (N,)
        Scaled target magnitudes.
    p0 : ndarray, shape (9,)
        Start: upper entries of ``M`` (row-major: m11 m12 m13 m22 m23 m33), then ``b``.
    order : ndarray of int, shape (n_epochs, N), optional
        Sample order per epoch (default: recorded order).

    Returns
    -------
    p : ndarray, shape (9,)
    epochs : int
        Epochs run.
    history : list of float
        RMS error ``sqrt(mean(err_i^2))`` of each epoch (errors seen during the pass).
    """
    m11, m12, m13, m22, m23, m33, bx, by, bz = (float(v) for v in p0)
    n = len(u)
    eps = 1e-300
    history: list[float] = []
    epochs = 0
    for ep in range(n_epochs):
        sq = 0.0
        for block in row_blocks(n):  # Python floats for one chunk at a time (24 bytes each), not all N
            if order is None:
                rows, targets = u[block].tolist(), t[block].tolist()
            else:
                sel = order[ep, block]
                rows, targets = u[sel].tolist(), t[sel].tolist()
            for (ux, uy, uz), target in zip(rows, targets, strict=True):
                ex, ey, ez = ux - bx, uy - by, uz - bz
                y1 = m11 * ex + m12 * ey + m13 * ez
                y2 = m22 * ey + m23 * ez
                y3 = m33 * ez
                mag = math.sqrt(y1 * y1 + y2 * y2 + y3 * y3)
                if not mag > 0 or not math.isfinite(mag):
                    return np.full(9, np.nan), ep + 1, history
                n1, n2, n3 = y1 / mag, y2 / mag, y3 / mag
                err = target - mag
                sq += err * err
                g = (n1 * ex, n1 * ey, n1 * ez, n2 * ey, n2 * ez, n3 * ez)
                gb = (-n1 * m11, -(n1 * m12 + n2 * m22), -(n1 * m13 + n2 * m23 + n3 * m33))
                sm = mu_matrix * err / (sum(v * v for v in g) + eps)
                sb = mu_offset * err / (gb[0] ** 2 + gb[1] ** 2 + gb[2] ** 2 + eps)
                m11 += sm * g[0]
                m12 += sm * g[1]
                m13 += sm * g[2]
                m22 += sm * g[3]
                m23 += sm * g[4]
                m33 += sm * g[5]
                bx += sb * gb[0]
                by += sb * gb[1]
                bz += sb * gb[2]
        epochs = ep + 1
        history.append(math.sqrt(sq / n))
        if history[-1] < tol:
            break
    return np.array([m11, m12, m13, m22, m23, m33, bx, by, bz]), epochs, history


class LMS(Estimator):
    """Dual normalised LMS on the magnitude error (paper D's adaptive baseline, reconstructed).

    Parameters
    ----------
    model : str
        ``"zhang-cheng"``.
    mu_matrix, mu_offset : float
        Normalised step sizes (0 < mu < 2 for a stable NLMS update).
    n_epochs : int
        Passes over the data.
    tol : float
        Stop when an epoch's RMS magnitude error (scaled, unit-free) falls below this.
    shuffle : bool
        Visit the samples in a new random order each epoch (``seed``) instead of the recorded order.
    seed : int
        Seed of the shuffling.
    max_updates : int
        Upper bound on ``n_epochs * N`` (fewer epochs are run on long logs; the count is in ``stats``).
    start : {"nominal", "centroid"}
        Starting offset: zero (the nominal sensor) or the centroid of the samples.
    """

    name = "lms"
    models = ("zhang-cheng",)
    requires_reference = True

    def __init__(
        self,
        model: str = "zhang-cheng",
        mu_matrix: float = 0.5,
        mu_offset: float = 0.5,
        n_epochs: int = 200,
        tol: float = 1e-12,
        shuffle: bool = False,
        seed: int = 0,
        max_updates: int = 1_000_000,
        start: str = "nominal",
    ) -> None:
        self.model = model
        self.mu_matrix = mu_matrix
        self.mu_offset = mu_offset
        self.n_epochs = n_epochs
        self.tol = tol
        self.shuffle = shuffle
        self.seed = seed
        self.max_updates = max_updates
        self.start = start

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        for key in ("mu_matrix", "mu_offset"):
            mu = float(getattr(self, key))
            if not 0.0 < mu < 2.0:
                raise TrimagInputError(f"lms option `{key}` must lie in (0, 2) for a stable update; got {mu}")
        if int(self.n_epochs) < 1 or int(self.max_updates) < 1:
            raise TrimagInputError("lms options `n_epochs` and `max_updates` must be positive integers")
        ref = require_magnitude(reference, len(B), units, self.name)
        assert ref.values is not None
        f_ref = float(np.sqrt(np.mean(ref.values**2)))
        report = identifiability_report(B, f_ref**2)
        check_identifiable(report, linear=False)
        u, t = B / f_ref, ref.values / f_ref
        n_epochs = max(1, min(int(self.n_epochs), int(self.max_updates) // len(u)))
        order = None
        if self.shuffle:
            rng = np.random.default_rng(self.seed)
            order = np.argsort(rng.random((n_epochs, len(u))), axis=1)
        p, epochs, history = dual_lms(
            u, t, iterative_start(u, self.start), mu_matrix=float(self.mu_matrix),
            mu_offset=float(self.mu_offset), n_epochs=n_epochs, tol=float(self.tol), order=order,
        )
        converged = bool(history) and history[-1] < float(self.tol)
        extra = {
            "epochs": epochs,
            "epochs_allowed": n_epochs,
            "epoch_rms_history": history[:: max(1, len(history) // 50)],
            "final_epoch_rms": history[-1] if history else None,
            "start": self.start,
        }
        return finish_iterative(
            self, B, p, f_ref, model=model, units=units, ref=ref, report=report,
            iterations=epochs * len(u), converged=converged, extra=extra,
        )
