"""The solvers under the estimators, on arrays: a deliberately public API for work below the estimator level.

An estimator (:mod:`trimag.estimators`) validates its input, calls one of these, and turns the solution into a
:class:`~trimag.calibration.Calibration` with uncertainty and diagnostics. These functions skip the first and last
steps: they take samples as float64 arrays in one unit and return the method's raw solution, for studies that need
it (the paper reproductions of :mod:`trimag.experiments`, which use only public names, are built on them).

===========================  =================================================================================
function                     solves
===========================  =================================================================================
:func:`solve_pairs`          paper A's pairwise criterion ``Phi`` over sample pairs (docs/method-pairwise.md)
:func:`pair_samples`         the pairs of that design from a log (halves, random, adjacent)
:func:`solve_geometric`      ``|Gamma^-1 (B - b)| = h`` by Gauss-Newton on all samples (paper A's reference method)
:func:`solve_wen_pairs`      the reconstructed Wen (2008) pair model (the "old method" of paper A's Fig. 5)
:func:`solve_interference`   paper C's ``H_m = K H_b + c`` by three 4-unknown linear least squares
:func:`fit_with_background`  ``K``, ``c`` and the background field jointly, ``|H_n|`` given (paper C, real data)
:func:`identifiability_report` paper D's quadric design: rank, condition, undetermined parameters
===========================  =================================================================================
"""

from __future__ import annotations

from .estimators._pairs import pair_samples
from .estimators._quadric import identifiability_report
from .estimators.geometric import solve_geometric
from .estimators.linear_vector import fit_with_background, solve_interference
from .estimators.pairwise import solve_pairs
from .estimators.wen2008 import solve_wen_pairs

__all__ = [
    "fit_with_background",
    "identifiability_report",
    "pair_samples",
    "solve_geometric",
    "solve_interference",
    "solve_pairs",
    "solve_wen_pairs",
]
