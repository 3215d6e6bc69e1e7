"""The fit report's figure (issue 32, item 8)."""

from __future__ import annotations

import re
import warnings

import numpy as np
from matplotlib.colors import to_rgba
from test_verdicts import flight

import trimag
from trimag.quality.report import fit_report


def test_coverage_title_is_the_share_of_the_cells_drawn_covered():
    """Finding: the report's coverage title ("68 % of cells") contradicted its mostly grey picture: the number was
    counted on 100 equal-area cells, the picture on 648 azimuth x elevation bins with another threshold."""
    B = flight(seed=0, tilts_deg=(25.0,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = trimag.fit(B, model="ellipsoid", units="mG")
    fig = fit_report(B, cal)
    ax = next(a for a in fig.axes if "coverage" in a.get_title())
    title = ax.get_title()
    found = re.search(r"(\d+)% of the (\d+) equal-area cells", title)
    assert found is not None, title
    percent, n_cells = int(found.group(1)), int(found.group(2))
    cells = next(c for c in ax.collections if len(c.get_offsets()) == n_cells)
    covered = np.all(np.isclose(cells.get_facecolors()[:, :3], to_rgba("#1b7f3b")[:3]), axis=1)
    assert round(100 * covered.mean()) == percent == round(100 * cal.diagnostics["coverage"]["fraction"])


def test_the_after_histogram_shows_its_shape_beside_a_far_wider_before():
    """The demo's after-histogram sat in 3 of 80 bins shared with a before 100x wider (issue 42, item 6): each is drawn
    on axes of its own, with its own bins, so both show their shape."""
    from pathlib import Path

    raw = np.loadtxt(Path(trimag.__file__).parent / "data" / "qmc5883l_noisy_raw_data.csv", delimiter=",",
                     skiprows=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = trimag.fit(raw, model="ellipsoid", units="counts")
    fig = fit_report(raw, cal)
    for label in ("before", "after"):
        shape = next(p for a in fig.axes for p in a.patches if p.get_label().startswith(label))
        if hasattr(shape, "get_height"):  # bars: one per bin
            bins = [p for a in fig.axes for c in a.containers for p in c.patches
                    if c.patches[0].get_label().startswith(label) and p.get_height() > 0]
            filled = len(bins)
        else:  # one outline: its steps above zero
            xy = shape.get_xy()
            filled = len(np.unique(xy[xy[:, 1] > 0, 0])) - 1
        assert filled >= 20, (label, filled)


def test_before_and_after_histograms_are_on_axes_of_their_own():
    """The demo's after-histogram was a sliver at one end of axes that spanned the before's range (a 100x wider
    distribution; issue 42, item 6): each histogram gets axes of its own whose x range is its own distribution's,
    so that the after's shape fills its axes as the before's does."""
    from pathlib import Path

    raw = np.loadtxt(Path(trimag.__file__).parent / "data" / "qmc5883l_noisy_raw_data.csv", delimiter=",",
                     skiprows=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = trimag.fit(raw, model="ellipsoid", units="counts")
    fig = fit_report(raw, cal)
    F = float(cal.reference["value"])
    errors = {"before": np.linalg.norm(raw, axis=1) - F, "after": np.linalg.norm(cal.apply(raw), axis=1) - F}
    holders = {}
    for label, err in errors.items():
        holders[label] = [a for a in fig.axes if any(p.get_label().startswith(label) for p in a.patches)]
        assert len(holders[label]) == 1, (label, len(holders[label]))
        lo, hi = holders[label][0].get_xlim()
        spread = np.percentile(err, 99.5) - np.percentile(err, 0.5)
        assert spread > 0.5 * (hi - lo), (label, spread, hi - lo)
    assert holders["before"][0] is not holders["after"][0]
