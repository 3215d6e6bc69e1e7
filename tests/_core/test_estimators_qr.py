"""The blocked QR least squares (``trimag._core.qr``) against numpy's whole-matrix solvers."""

from __future__ import annotations

import numpy as np
import pytest

from trimag._core.qr import BlockedQR


@pytest.mark.parametrize("block", [1, 4, 97, 5000])
def test_blocked_qr_equals_lstsq(block: int) -> None:
    """Fed in blocks of any size (even smaller than the number of columns), the factorisation gives numpy's
    least-squares solution, residual, singular values and column norms of the whole matrix."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(2000, 6)) * [1.0, 10.0, 0.1, 3.0, 1.0, 100.0]
    b = A @ rng.normal(size=6) + rng.normal(scale=0.1, size=2000)
    qr = BlockedQR(6)
    for s in range(0, len(b), block):
        qr.add(A[s : s + block], b[s : s + block])
    x, res, _, sv = np.linalg.lstsq(A, b, rcond=None)
    assert qr.rows == 2000
    np.testing.assert_allclose(qr.solve(), x, rtol=1e-10)
    np.testing.assert_allclose(qr.residual_sum_squares, res[0], rtol=1e-9)
    np.testing.assert_allclose(np.linalg.svd(qr.R, compute_uv=False), sv, rtol=1e-10)
    np.testing.assert_allclose(np.linalg.norm(qr.R, axis=0), np.linalg.norm(A, axis=0), rtol=1e-12)


def test_rank_deficient_system_gives_the_minimum_norm_solution() -> None:
    rng = np.random.default_rng(2)
    A = rng.normal(size=(300, 3))
    A = np.column_stack([A, A[:, 0] + A[:, 1]])  # rank 3
    b = rng.normal(size=300)
    qr = BlockedQR(4)
    for s in range(0, 300, 64):
        qr.add(A[s : s + 64], b[s : s + 64])
    np.testing.assert_allclose(qr.solve(), np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-10)


def test_fewer_rows_than_columns_so_far() -> None:
    qr = BlockedQR(3)
    qr.add([[1.0, 2.0, 3.0]], [1.0])
    assert qr.R.shape == (3, 3) and qr.residual_sum_squares == 0.0


def test_blocks_are_factored_in_panels_with_the_same_result(small_chunks):
    """A block larger than a panel is factored panel by panel (here 64 rows): the same R (up to row signs),
    solution and residual as a QR of the whole system."""
    import trimag._core.qr as qr_module

    rng = np.random.default_rng(4)
    A = rng.normal(size=(1000, 5)) * [1.0, 1e3, 1e-3, 10.0, 1.0]
    b = A @ [1.0, -2.0, 3.0, 0.5, 4.0] + rng.normal(size=1000)
    small_chunks(12 * 64 * 6 // 3)  # a QR panel is 1/12 of the working memory: 64 rows of 6 columns
    qr = qr_module.BlockedQR(5)
    assert qr.rows_per_qr == 64
    qr.add(A[:700], b[:700])
    qr.add(A[700:], b[700:])
    assert qr.rows == 1000
    R_whole = np.linalg.qr(A, mode="r")
    np.testing.assert_allclose(np.abs(qr.R), np.abs(R_whole), rtol=1e-10, atol=1e-10 * np.abs(R_whole).max())
    x, res, *_ = np.linalg.lstsq(A, b, rcond=None)
    np.testing.assert_allclose(qr.solve(), x, rtol=1e-10)
    assert qr.residual_sum_squares == pytest.approx(float(res[0]), rel=1e-10)
