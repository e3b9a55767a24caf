"""The error bound at light discontinuities (issue 11): 90% bounds must cover the actual
error at edge pixels within 10 points of nominal from 16 to 256 passes, and stay
calibrated at smooth pixels, on a spot light's cone edge and a hard shadow (both analytic,
tests/analytic.py). Before the discontinuity bias (worker/error_estimate.py) the edge
coverage fell to 76-80% here; the issue saw 27% with its own edge definition. A texture's
edges (a checkerboard of albedos 0.8 and 0.1, issue 48) are discontinuities too: there the
bounds cover the error within 5 points of nominal at edge and at smooth pixels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.analytic import EDGE_CASES, edge_pixels
from worker.error_estimate import estimate
from worker.render_loop import render

CASES = ("spot cone edge", "hard shadow", "texture edge")  # EDGE_CASES with an edge
EDGE_SLACK = {"texture edge": 0.05}  # how far below (or above) 90% edge coverage may be; else 10 points below


@pytest.mark.parametrize("case", CASES)
def test_ninety_percent_bounds_cover_edge_pixels_from_16_to_256_passes(make_engine, tmp_path: Path, case) -> None:
    scene, truth_of = EDGE_CASES[case]
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene()))
    eng = make_engine(path, photons_per_pass=1 << 14, seed=41)
    truth = truth_of(eng)
    edge = edge_pixels(truth.reshape(eng.arrays.height, eng.arrays.width)).ravel()
    coverage = {}

    def observe(st: object, _: float) -> None:
        if st.passes in (16, 64, 256):
            est = estimate(st, 0.9)
            covered = est.bound >= np.abs(est.luminance - truth)
            coverage[st.passes] = (float(covered[est.known & edge].mean()), float(covered[est.known & ~edge].mean()))

    render(eng, passes=256, progress=observe)
    assert len(coverage) == 3
    for passes, (at_edges, smooth) in coverage.items():
        if case in EDGE_SLACK:
            assert abs(at_edges - 0.9) <= EDGE_SLACK[case], (passes, coverage)
        else:
            assert at_edges >= 0.80, (passes, coverage)
        assert abs(smooth - 0.9) <= 0.05, (passes, coverage)
