"""Tolles–Lawson (TL) aircraft compensation of a scalar magnetometer (docs/method-tolles-lawson.md).

A scalar magnetometer on an aircraft reads the Earth's field plus the aircraft's own field projected on the
Earth's field direction. Tolles and Lawson (1950) write that projection as a linear combination of terms built
from the direction cosines ``u = B / |B|`` of a vector fluxgate on the same aircraft:

    B_scalar = B_earth + A(u, B, dB/dt) @ c                                   (1)

with ``A`` the design below and ``c`` the TL coefficients. The terms, their order and their scale follow
MagNav.jl's ``create_TL_A`` (so coefficients can be compared with it):

- permanent (3):  ``u_x, u_y, u_z``
- induced (6):    ``u_i * B_j / Bt_scale`` for (i, j) in xx, xy, xz, yy, yz, zz
  (``induced5`` drops zz: since ``u_x^2 + u_y^2 + u_z^2 = 1`` the diagonal terms sum to ``|B| / Bt_scale``,
  nearly a constant, collinear with a bias; ``induced3`` keeps xx, yy, zz)
- eddy (9):       ``u_i * dB_j/dt / Bt_scale`` for i, j in x, y, z (``eddy8`` drops zz; ``eddy3`` keeps the
  diagonal)
- ``fdm`` (3):    ``dB_x/dt, dB_y/dt, dB_z/dt`` (extra), and ``bias`` (1): a constant

``B`` is the fluxgate's vector (nT), ``Bt`` its magnitude (or the scalar magnetometer's reading, when chosen),
``Bt_scale`` = 50 000 nT, and ``dB/dt`` the finite difference per *sample* (MagNav's ``fdm``, central by
default), so coefficients of eddy terms depend on the sample rate: the rate is recorded with them.

This module owns the model algebra (terms, design, interference); fitting (band-pass, regression) is in
:mod:`trimag.estimators.tolles_lawson`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError

__all__ = [
    "BT_SCALE_NT",
    "DEFAULT_TERMS",
    "TERM_KINDS",
    "derivative",
    "design",
    "parse_terms",
    "term_names",
]

#: MagNav.jl's default scale of the induced and eddy terms (nT).
BT_SCALE_NT = 50_000.0

#: MagNav.jl's default term set.
DEFAULT_TERMS: tuple[str, ...] = ("permanent", "induced", "eddy")

_ALIASES = {
    "permanent": "permanent", "p": "permanent", "permanent3": "permanent", "p3": "permanent",
    "induced": "induced", "i": "induced", "induced6": "induced", "i6": "induced",
    "induced5": "induced5", "i5": "induced5", "induced3": "induced3", "i3": "induced3",
    "eddy": "eddy", "e": "eddy", "eddy9": "eddy", "e9": "eddy",
    "eddy8": "eddy8", "e8": "eddy8", "eddy3": "eddy3", "e3": "eddy3",
    "fdm": "fdm", "f": "fdm", "d": "fdm", "fdm3": "fdm",
    "bias": "bias", "b": "bias",
}
#: Canonical order of the term groups in the design (MagNav's create_TL_A).
_ORDER = ("permanent", "induced", "induced5", "induced3", "eddy", "eddy8", "eddy3", "fdm", "bias")

_AX = "xyz"
_INDUCED6 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_GROUP_PAIRS: dict[str, tuple[tuple[int, int], ...]] = {
    "induced": _INDUCED6,
    "induced5": _INDUCED6[:5],
    "induced3": ((0, 0), (1, 1), (2, 2)),
    "eddy": tuple((i, j) for i in range(3) for j in range(3)),
    "eddy8": tuple((i, j) for i in range(3) for j in range(3))[:8],
    "eddy3": ((0, 0), (1, 1), (2, 2)),
}

#: Kind of each term group (what the coefficient physically is), for reports and checks.
TERM_KINDS: dict[str, str] = {
    "permanent": "permanent", "induced": "induced", "induced5": "induced", "induced3": "induced",
    "eddy": "eddy", "eddy8": "eddy", "eddy3": "eddy", "fdm": "derivative", "bias": "bias",
}

_SCHEMES = ("central", "backward", "forward")


def parse_terms(terms: str | Sequence[str] | None) -> tuple[str, ...]:
    """Canonical term groups, in design order, from names or MagNav's aliases (``"p,i,e"``, ``"i5"``...).

    Raises
    ------
    TrimagInputError
        Unknown name, or two variants of one group (``induced`` with ``induced5``).
    """
    if terms is None:
        return DEFAULT_TERMS
    items = [t.strip().lower() for t in (terms.split(",") if isinstance(terms, str) else terms) if t.strip()]
    unknown = [t for t in items if t not in _ALIASES]
    if unknown or not items:
        raise TrimagInputError(
            f"unknown Tolles–Lawson term(s) {', '.join(map(repr, unknown)) or '(none given)'}; choose from "
            "permanent, induced, induced5, induced3, eddy, eddy8, eddy3, fdm, bias"
        )
    groups = {_ALIASES[t] for t in items}
    for family in ("induced", "eddy"):
        variants = [g for g in groups if g.startswith(family)]
        if len(variants) > 1:
            raise TrimagInputError(f"choose one of the {family} term variants, not {' and '.join(sorted(variants))}")
    return tuple(g for g in _ORDER if g in groups)


def term_names(terms: str | Sequence[str] | None = None) -> list[str]:
    """Names of the design's columns, in order (e.g. ``perm_x``, ``ind_xy``, ``eddy_zx``, ``bias``)."""
    names: list[str] = []
    for group in parse_terms(terms):
        if group == "permanent":
            names += [f"perm_{a}" for a in _AX]
        elif group == "fdm":
            names += [f"dB{a}" for a in _AX]
        elif group == "bias":
            names.append("bias")
        else:
            prefix = "ind" if group.startswith("induced") else "eddy"
            names += [f"{prefix}_{_AX[i]}{_AX[j]}" for i, j in _GROUP_PAIRS[group]]
    return names


def derivative(x: ArrayLike, scheme: str = "central") -> NDArray[np.float64]:
    """Finite difference per sample along axis 0 (MagNav.jl's ``fdm``): central inside, one-sided at the ends.

    Parameters
    ----------
    x : array_like, shape (N,) or (N, k)
    scheme : {"central", "backward", "forward"}

    Returns
    -------
    ndarray, shape like ``x``
        Change per sample (not per second).
    """
    a = np.asarray(x, dtype=np.float64)
    if scheme not in _SCHEMES:
        raise TrimagInputError(f"unknown derivative scheme {scheme!r}; choose one of {', '.join(_SCHEMES)}")
    out = np.zeros_like(a)
    if len(a) < 2:
        return out
    if scheme == "central" and len(a) > 2:
        out[1:-1] = (a[2:] - a[:-2]) / 2.0
        out[0] = a[1] - a[0]
        out[-1] = a[-1] - a[-2]
    elif scheme == "forward":
        out[:-1] = a[1:] - a[:-1]
        out[-1] = out[-2]
    else:  # backward (and central with 2 samples)
        out[1:] = a[1:] - a[:-1]
        out[0] = out[1]
    return out


def design(
    vector_nT: ArrayLike,
    terms: str | Sequence[str] | None = None,
    *,
    Bt: ArrayLike | None = None,
    Bt_scale: float = BT_SCALE_NT,
    scheme: str = "central",
) -> NDArray[np.float64]:
    """The TL design ``A`` of equation (1) for one contiguous segment.

    Parameters
    ----------
    vector_nT : array_like, shape (N, 3)
        Vector magnetometer (fluxgate) readings, nT, in time order with no gaps.
    terms : str or sequence of str, optional
        Term groups (:func:`parse_terms`); default permanent, induced, eddy (18 columns).
    Bt : array_like, shape (N,), optional
        Total field used for the direction cosines; default ``|vector|``.
    Bt_scale : float
        Scale of the induced and eddy terms, nT (MagNav: 50 000).
    scheme : {"central", "backward", "forward"}
        Finite-difference scheme of the eddy and ``fdm`` terms.

    Returns
    -------
    ndarray, shape (N, p)
        Columns named by :func:`term_names`.
    """
    B = np.asarray(vector_nT, dtype=np.float64)
    if B.ndim != 2 or B.shape[1] != 3:
        raise TrimagInputError(f"the vector magnetometer must have shape (N, 3); got {B.shape}")
    total = np.sqrt(np.einsum("ij,ij->i", B, B)) if Bt is None else np.asarray(Bt, dtype=np.float64)
    if total.shape != (len(B),):
        raise TrimagInputError(f"`Bt` must have shape ({len(B)},); got {total.shape}")
    if np.any(total <= 0) or not np.isfinite(total).all():
        raise TrimagInputError("the total field must be positive and finite in every sample")
    u = B / total[:, None]
    groups = parse_terms(terms)
    dB = derivative(B, scheme) if any(g.startswith("eddy") or g == "fdm" for g in groups) else None
    cols: list[NDArray[np.float64]] = []
    for group in groups:
        if group == "permanent":
            cols.append(u)
        elif group == "fdm":
            assert dB is not None
            cols.append(dB)
        elif group == "bias":
            cols.append(np.ones((len(B), 1)))
        else:
            pairs = _GROUP_PAIRS[group]
            other = B if group.startswith("induced") else dB
            assert other is not None
            i_idx = [i for i, _ in pairs]
            j_idx = [j for _, j in pairs]
            cols.append(u[:, i_idx] * other[:, j_idx] / Bt_scale)
    return np.hstack(cols)


@dataclass(frozen=True)
class TollesLawsonTerms:
    """The term set of a TL model and how its design is built (what a compensation file records)."""

    terms: tuple[str, ...] = DEFAULT_TERMS
    Bt_scale: float = BT_SCALE_NT
    derivative_scheme: str = "central"
    Bt_source: str = "vector"

    @property
    def names(self) -> list[str]:
        """Column names of the design."""
        return term_names(self.terms)

    def design(self, vector_nT: ArrayLike, scalar_nT: ArrayLike | None = None) -> NDArray[np.float64]:
        """Design of one contiguous segment; ``scalar_nT`` is used for ``Bt`` when ``Bt_source == "scalar"``."""
        Bt = scalar_nT if self.Bt_source == "scalar" else None
        return design(vector_nT, self.terms, Bt=Bt, Bt_scale=self.Bt_scale, scheme=self.derivative_scheme)


__all__ += ["TollesLawsonTerms"]
