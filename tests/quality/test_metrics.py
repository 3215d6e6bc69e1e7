"""Figures of merit: the blocked statistics pass and the row-wise products against their plain forms."""

from __future__ import annotations

import numpy as np
import pytest

import trimag._core.rowwise as rowwise
from trimag.quality.metrics import before_after_stats, norm_stats, row_dot, row_norms


def test_row_dot_matches_einsum():
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((2, 1000, 3))
    np.testing.assert_allclose(row_dot(a, b), np.einsum("ij,ij->i", a, b), rtol=1e-14, atol=1e-14)
    a4, b4 = rng.standard_normal((2, 10, 4))  # other shapes: the einsum fallback
    np.testing.assert_allclose(row_dot(a4, b4), np.einsum("ij,ij->i", a4, b4), rtol=1e-14)
    np.testing.assert_allclose(row_norms(a[:, ::-1]), np.linalg.norm(a, axis=1), rtol=1e-14)  # strided input


@pytest.mark.parametrize("with_reference", [False, True], ids=["mean-F", "per-sample-F"])
def test_before_after_stats_equals_norm_stats_over_blocks(small_chunks, with_reference):
    """Over several blocks (block size forced to 1000 rows, 4321 samples) the one-pass statistics equal
    ``norm_stats`` on the whole arrays; large magnitudes with a tiny spread do not cancel."""
    small_chunks(1000)
    rng = np.random.default_rng(1)
    n = 4321
    B = 5e4 * rng.standard_normal((n, 3)) + 2e4
    M = np.eye(3) + 0.1 * rng.standard_normal((3, 3))
    offset = np.array([2e4, 1e4, -3e3])
    reference = rng.uniform(4.8e4, 5.2e4, n) if with_reference else None
    before, after, F = before_after_stats(B, M, offset, reference)
    corrected = (B - offset) @ M.T
    F_plain = reference if reference is not None else row_norms(corrected).mean()
    expect_before = norm_stats(row_norms(B), F_plain)
    expect_after = norm_stats(row_norms(corrected), F_plain)
    assert F == pytest.approx(float(np.mean(F_plain)), rel=1e-14)
    for got, expect in ((before, expect_before), (after, expect_after)):
        assert set(got) == set(expect)
        for key in expect:
            assert got[key] == pytest.approx(expect[key], rel=1e-10, abs=1e-9 * abs(F)), key


def test_before_after_stats_tiny_spread_on_a_large_magnitude():
    """Samples on a sphere of radius 5e4 with a 1e-6 spread: the RMS is the spread, not rounding noise."""
    rng = np.random.default_rng(2)
    u = rng.standard_normal((200_000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    radius = 5e4 + 1e-6 * rng.standard_normal(200_000)
    B = u * radius[:, None]
    _, after, F = before_after_stats(B, np.eye(3), np.zeros(3))
    assert F == pytest.approx(5e4, rel=1e-12)
    assert after["rms"] == pytest.approx(float(np.std(radius)), rel=1e-3)
    assert after["bias"] == pytest.approx(0.0, abs=1e-9)


def test_scratch_buffers_are_reused_distinct_when_nested_and_bounded():
    """``_rowwise.scratch`` lends C-contiguous buffers of the asked shape, reuses them after the ``with`` block,
    never lends the same memory twice at once, and keeps a bounded pool."""
    with rowwise.scratch(3, 1000) as a:
        assert a.shape == (3, 1000) and a.flags["C_CONTIGUOUS"] and a.dtype == np.float64
        with rowwise.scratch(3, 1000) as b:
            assert not np.shares_memory(a, b)
        a_mem = a.__array_interface__["data"][0]
    with rowwise.scratch(2, 1500) as c:  # fits in a freed buffer: reused, not allocated
        assert c.__array_interface__["data"][0] in (a_mem, b.__array_interface__["data"][0])
    held = []
    for k in range(3 * rowwise.SCRATCH_POOL):  # many sizes, several held at once: the pool stays bounded
        ctx = rowwise.scratch(3 * rowwise.SCRATCH_POOL - k, 1000)
        ctx.__enter__()
        held.append(ctx)
    for ctx in held:  # the largest first: the smallest, dropped, is the last in the pool
        ctx.__exit__(None, None, None)
    assert len(rowwise._pool.free) <= rowwise.SCRATCH_POOL
    with rowwise.scratch(rowwise.SCRATCH_KEEP + 1) as big:  # larger than kept: freed after use
        big_mem = big.__array_interface__["data"][0]
    assert all(buf.__array_interface__["data"][0] != big_mem for buf in rowwise._pool.free)
