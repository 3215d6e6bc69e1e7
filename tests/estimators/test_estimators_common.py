"""Generic estimator checks (``trimag.testing``) on every estimator from ``all_estimators()``."""

from __future__ import annotations

import pytest

from trimag.estimators import all_estimators
from trimag.testing import check_estimator, estimator_checks

#: Checks that fail for a documented reason (reported to the lead; not this file's to fix).
KNOWN_FAILURES = {
    ("wen2008", "check_recovers_parameters"): (
        "wen2008 is paper A's reconstructed baseline: its parametrisation cannot represent the ortho-gain "
        "model's psi (methods.md, paper A), so it cannot recover ortho-gain parameters exactly"
    ),
}

CASES = [
    pytest.param(
        run,
        id=f"{name}-{check}",
        marks=[pytest.mark.xfail(reason=KNOWN_FAILURES[(name, check)], strict=True)]
        if (name, check) in KNOWN_FAILURES else [],
    )
    for name, cls in all_estimators()
    for check, run in estimator_checks(cls)
]


@pytest.mark.parametrize("run", CASES)
def test_estimator_check(run):
    run()


def test_check_estimator_reports_failures():
    """``check_estimator`` must fail on an estimator that breaks the contract (the checks can fail)."""
    from trimag.estimators.ml import MaximumLikelihood

    class Broken(MaximumLikelihood):
        def __init__(self, model="ellipsoid", form="upper", loss="linear", max_iter=100, bias_correction=True,
                     noise_std=None):
            super().__init__(model, form, loss, max_iter, bias_correction, noise_std)
            self.calibration_ = None  # fitted state set in __init__

        def fit(self, B, reference=None, *, units="unknown", attitude=None):
            super().fit(B, reference, units=units, attitude=attitude)
            return None  # does not return self

    with pytest.raises(AssertionError, match="before fit"):
        check_estimator(Broken)
    with pytest.raises(AssertionError, match="must return self"):
        check_estimator(Broken)
