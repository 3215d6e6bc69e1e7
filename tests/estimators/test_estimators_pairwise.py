"""``pairwise`` (paper A's reference-free objective) and ``geometric`` (all samples, free magnitude)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import trimag
from trimag.errors import IdentifiabilityError, NotFittedError, TrimagInputError
from trimag.estimators import get_estimator
from trimag.estimators._pairs import closed_form_pairs, pairwise_design
from trimag.estimators.geometric import Geometric, solve_geometric
from trimag.estimators.pairwise import Pairwise, pair_samples, q_to_matrix, solve_pairs
from trimag.experiments.wu2013 import FIELD, attitudes_for
from trimag.models.ortho_gain import OrthoGain, OrthoGainBias, params_from_q
from trimag.quality.metrics import j_index

PAPER = OrthoGain(theta=0.06, phi=0.08, psi=-0.04, kxz=0.95, kyz=1.05)


def paper_raw(n_pairs: int, sigma: float, seed: int, model=PAPER, kind: str = "axes") -> np.ndarray:
    rng = np.random.default_rng(seed)
    raw = model.distort(attitudes_for(2 * n_pairs, kind, rng).inv().apply(FIELD))
    return raw + rng.normal(scale=sigma, size=raw.shape) if sigma else raw


def test_registered():
    assert get_estimator("pairwise") is Pairwise
    assert get_estimator("geometric") is Geometric
    assert set(Pairwise.models) == set(Geometric.models) == {"ortho-gain", "ortho-gain-bias"}


def test_design_expansion_matches_magnitudes():
    """|Gamma^-1 B1|^2 - |Gamma^-1 B2|^2 = W . (M11, M22, M33, M12, M23, M13) (methods.md, paper A)."""
    rng = np.random.default_rng(0)
    B1, B2 = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
    C = PAPER.gamma_inv()
    M = C.T @ C
    m = np.array([M[0, 0], M[1, 1], M[2, 2], M[0, 1], M[1, 2], M[0, 2]])
    diff = np.linalg.norm(B1 @ C.T, axis=1) ** 2 - np.linalg.norm(B2 @ C.T, axis=1) ** 2
    np.testing.assert_allclose(pairwise_design(B1, B2) @ m, diff, atol=1e-13)


@pytest.mark.parametrize("pairing", ["halves", "random"])
@pytest.mark.parametrize("kind", ["axes", "random"])
def test_noise_free_recovery_1e9(pairing, kind):
    raw = paper_raw(200, 0.0, 1, kind=kind)
    cal = trimag.fit(raw, model="ortho-gain", method="pairwise", pairing=pairing, seed=4)
    assert list(cal.params) == ["theta", "phi", "psi", "kxz", "kyz"]
    est = np.array([cal.params[k] for k in cal.params])
    np.testing.assert_allclose(est, PAPER.as_vector(), rtol=1e-9)
    assert cal.stats["n_pairs"] == 200 and cal.stats["pairing"] == pairing


def test_noise_free_recovery_with_offsets():
    truth = OrthoGainBias(**PAPER.as_dict(), bx=0.3, by=-0.25, bz=0.4)
    raw = paper_raw(150, 0.0, 2, model=truth, kind="random")
    for method in ("pairwise", "geometric"):
        cal = trimag.fit(raw, model="ortho-gain-bias", method=method)
        est = np.array([cal.params[k] for k in OrthoGainBias.param_names()])
        np.testing.assert_allclose(est, truth.as_vector(), rtol=1e-9, err_msg=method)


def test_closed_form_exact_and_lm_minimises_phi():
    B1, B2, _ = pair_samples(paper_raw(100, 0.0, 3))
    C, _, cond = closed_form_pairs(B1, B2)
    np.testing.assert_allclose(C, PAPER.gamma_inv(), atol=1e-10)
    assert np.isfinite(cond)
    # with noise: LM lowers Phi below the closed-form start, and the gradient vanishes at the solution
    B1, B2, _ = pair_samples(paper_raw(300, 1e-2, 4))
    C0, _, _ = closed_form_pairs(B1, B2)
    sol = solve_pairs(B1, B2)

    def phi(C):
        return float(np.sum((np.linalg.norm(B1 @ C.T, axis=1) ** 2 - np.linalg.norm(B2 @ C.T, axis=1) ** 2) ** 2))

    assert sol.phi == pytest.approx(phi(sol.C), rel=1e-10)
    assert sol.phi < phi(C0)
    grad = sol.result.jac.T @ sol.result.fun
    assert np.max(np.abs(grad)) < 1e-9 * np.linalg.norm(sol.result.jac) * np.linalg.norm(sol.result.fun)
    for k in range(5):  # a local minimum: no coordinate step lowers Phi
        for h in (1e-6, -1e-6):
            dq = sol.q.copy()
            dq[k] += h
            assert phi(q_to_matrix(dq)) >= sol.phi


def test_strong_noise_accuracy_and_geometric_comparison():
    """sigma = 1e-2, N = 720 pairs: median J of pairwise <= 0.035 (the issue); the all-samples geometric fit
    is more accurate on the same data (measured ratio ~0.55 over 50 trials; here 12 trials, bound 0.8)."""
    jp, jg = [], []
    for seed in range(12):
        raw = paper_raw(720, 1e-2, 100 + seed)
        jp.append(j_index(PAPER.as_vector(), params_from_q(solve_pairs(*pair_samples(raw)[:2]).q)))
        jg.append(j_index(PAPER.as_vector(), params_from_q(solve_geometric(raw).q)))
    assert np.median(jp) <= 0.035
    assert np.median(jg) / np.median(jp) < 0.8


def test_j_falls_with_n_and_grows_with_sigma():
    def med_j(n, sigma):
        return np.median([
            j_index(PAPER.as_vector(), params_from_q(solve_pairs(*pair_samples(paper_raw(n, sigma, s))[:2]).q))
            for s in range(8)
        ])

    assert med_j(50, 1e-3) > med_j(800, 1e-3)
    assert med_j(200, 1e-4) < med_j(200, 1e-3) < med_j(200, 1e-2)


def test_estimator_contract():
    raw = paper_raw(60, 1e-3, 5)
    est = Pairwise()
    assert not any(k.endswith("_") for k in vars(est))
    with pytest.raises(NotFittedError):
        est.transform(raw)
    copy = raw.copy()
    assert est.fit(raw) is est
    np.testing.assert_array_equal(raw, copy)
    first = est.calibration_.matrix.copy()
    est.fit(raw)
    np.testing.assert_array_equal(first, est.calibration_.matrix)
    assert est.transform(raw).shape == raw.shape
    assert est.calibration_.uncertainty["param_std"]["theta"] > 0
    assert Geometric().fit(raw).calibration_.stats["fitted_magnitude"] == pytest.approx(2.0, rel=1e-3)


def test_bad_input_and_unidentifiable_data():
    raw = paper_raw(60, 1e-3, 6)
    with pytest.raises(TrimagInputError, match="pairing"):
        Pairwise(pairing="odd-even").fit(raw)
    bad = raw.copy()
    bad[3, 1] = np.nan
    with pytest.raises(TrimagInputError, match="NaN"):
        Pairwise().fit(bad)
    with pytest.raises(IdentifiabilityError, match="too few"):
        Pairwise().fit(raw[:9])
    with pytest.raises(IdentifiabilityError, match="too few"):
        Pairwise(model="ortho-gain-bias").fit(raw[:15])
    # a single turn about one axis: the field component along it is never varied
    one_axis = PAPER.distort(attitudes_for(600, "axes")[:200].inv().apply(FIELD))
    for est in (Pairwise(), Geometric(), Pairwise(model="ortho-gain-bias"), Geometric(model="ortho-gain-bias")):
        with pytest.raises(IdentifiabilityError):
            est.fit(one_axis)


def test_method_model_mismatch():
    with pytest.raises(TrimagInputError, match="cannot identify"):
        trimag.fit(paper_raw(30, 0, 0), model="ellipsoid", method="pairwise")


def test_reported_uncertainty_matches_monte_carlo_spread():
    """param_std (from the Jacobian) agrees with the spread over repeated noisy logs (within 40 %)."""
    truth = OrthoGainBias(**PAPER.as_dict(), bx=0.3, by=-0.25, bz=0.4)
    for method in ("pairwise", "geometric"):
        est, reported = [], []
        for seed in range(30):
            cal = trimag.fit(paper_raw(300, 2e-3, 200 + seed, model=truth, kind="random"),
                             model="ortho-gain-bias", method=method)
            est.append([cal.params[k] for k in ("theta", "kxz", "bx")])
            reported.append([cal.uncertainty["param_std"][k] for k in ("theta", "kxz", "bx")])
        ratio = np.std(est, axis=0) / np.mean(reported, axis=0)
        assert np.all((ratio > 0.6) & (ratio < 1.4)), (method, ratio)


def test_cli_fit_reports_paper_parameters(tmp_path, capsys):
    from trimag.cli import main

    path = tmp_path / "log.csv"
    np.savetxt(path, paper_raw(150, 1e-4, 9), delimiter=",", header="x,y,z", comments="")
    assert main(["fit", str(path), "--model", "ortho-gain", "--method", "pairwise", "--json", "-q"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert list(out["params"]) == ["theta", "phi", "psi", "kxz", "kyz"]
    np.testing.assert_allclose([out["params"][k] for k in out["params"]], PAPER.as_vector(), rtol=0.02)


def test_pairing_rules_and_odd_count():
    B = np.arange(21 * 3, dtype=float).reshape(21, 3)
    B1, B2, _ = pair_samples(B, "halves")
    np.testing.assert_array_equal(B1, B[:10])
    np.testing.assert_array_equal(B2, B[10:20])
    R1, R2, ridx = pair_samples(B, "random", seed=1)
    assert len(R1) == len(R2) == 10 and len(set(ridx.tolist())) == 20
    np.testing.assert_array_equal(pair_samples(B, "random", seed=1)[2], ridx)  # seeded: reproducible
    cal = trimag.fit(paper_raw(50, 0.0, 1)[:-1], model="ortho-gain", method="pairwise")
    assert cal.stats["n_pairs"] == 49 and cal.stats["n_used"] == 98 and cal.stats["n_samples"] == 99


def _full_phi(B1, B2, C, b):
    e1, e2 = (B1 - b) @ C.T, (B2 - b) @ C.T
    return float(np.sum((np.sum(e1 * e1, axis=1) - np.sum(e2 * e2, axis=1)) ** 2))


@pytest.mark.parametrize("bias", [False, True])
def test_reduced_residuals_carry_the_whole_objective(bias):
    """|R m|^2 of the design's factor equals the sum over every pair, for any (C, b); R's Gram matrix is W^T W."""
    from trimag.estimators.pairwise import pair_factor, quadric_entries

    rng = np.random.default_rng(5)
    B1, B2 = rng.normal(size=(300, 3)), rng.normal(size=(300, 3))
    R = pair_factor(B1, B2, bias=bias)
    W = pairwise_design(B1, B2, bias=bias)
    np.testing.assert_allclose(R.T @ R, W.T @ W, rtol=1e-12, atol=1e-12 * np.abs(W.T @ W).max())
    for _ in range(3):
        C = q_to_matrix(rng.normal(size=5))
        b = rng.normal(size=3) if bias else np.zeros(3)
        m, _ = quadric_entries(C, b if bias else None)
        assert float(np.sum((R @ m) ** 2)) == pytest.approx(_full_phi(B1, B2, C, b), rel=1e-10)


@pytest.mark.parametrize("bias", [False, True])
def test_quadric_entries_jacobian_matches_finite_differences(bias):
    from trimag.estimators.pairwise import quadric_entries

    rng = np.random.default_rng(6)
    q, b = rng.normal(size=5), rng.normal(size=3)
    _, dm = quadric_entries(q_to_matrix(q), b if bias else None)
    h = 1e-6
    fd = np.column_stack([
        (quadric_entries(q_to_matrix(q + h * e), b if bias else None)[0]
         - quadric_entries(q_to_matrix(q - h * e), b if bias else None)[0]) / (2 * h)
        for e in np.eye(5)
    ])
    np.testing.assert_allclose(dm, fd, atol=1e-8)


@pytest.mark.parametrize("bias", [False, True])
def test_blocked_factor_gives_the_one_block_fit(small_chunks, bias):
    """Blocks of 97 pairs give the fit, phi, condition numbers and uncertainty of one block, to rounding."""

    truth = OrthoGainBias(**PAPER.as_dict(), bx=0.3, by=-0.25, bz=0.4) if bias else PAPER
    raw = paper_raw(1500, 1e-2, 7, model=truth, kind="random")
    model = "ortho-gain-bias" if bias else "ortho-gain"
    one = trimag.fit(raw, model=model, method="pairwise")
    small_chunks(97)
    blocked = trimag.fit(raw, model=model, method="pairwise")
    np.testing.assert_allclose(blocked.matrix, one.matrix, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(blocked.offset, one.offset, atol=1e-10)
    assert blocked.stats["phi"] == pytest.approx(one.stats["phi"], rel=1e-9)
    assert blocked.diagnostics["condition_number"] == pytest.approx(one.diagnostics["condition_number"], rel=1e-8)
    for k, v in one.uncertainty["param_std"].items():
        assert blocked.uncertainty["param_std"][k] == pytest.approx(v, rel=1e-8)


def test_fit_memory_does_not_grow_with_the_number_of_pairs(small_chunks):
    """With blocks of 4096 pairs, 400 000 pairs peak at about what 100 000 do: memory is set by the blocks (and
    by the 65 536-row blocks of the column means), not by N."""
    import tracemalloc

    import trimag.estimators.pairwise as pw

    small_chunks(4096)
    peaks = []
    for n_pairs in (100_000, 400_000):
        B1, B2, _ = pair_samples(np.ascontiguousarray(paper_raw(n_pairs, 1e-2, 8, kind="random")))
        tracemalloc.start()
        try:
            pw.solve_pairs(B1, B2, bias=True)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    assert peaks[1] < 1.1 * peaks[0], peaks
    assert peaks[1] < 0.1 * 400_000 * 9 * 8, peaks  # one (N, 9) design would be 28.8 MB
