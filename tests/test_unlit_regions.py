"""Pixels no light reaches: their zero photon count bounds their radiance, and the image's
average relative error (worker/error_estimate.py) lets a mostly dark image converge
without letting the dark part dilute the error of the lit part."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests.analytic import SPOT, spot_plane, spot_plane_scene
from tests.conftest import render_until
from tests.helpers import spot_scene
from worker.error_estimate import actual_average, estimate, image_average
from worker.integrators.photon_mapping import sum_layout
from worker.stats import Accumulators


def _two_pixels(emitted: int) -> Accumulators:
    """Pixel 0 found photons (density D, luminance 1 per unit density), pixel 1 none."""
    st = Accumulators.start(0.7, np.full(2, 0.5), sum_layout(error_estimation=True))
    st.passes, st.emitted = 10, emitted
    st.sums["H"][:] = 10
    st.sums["D"][0] = 1000.0
    st.N[0] = math.pi * 0.1 ** 2 * 1000.0  # radius 0.1
    st.sums["S"][0] = 1000.0  # grey, so Y(S) = 1000 and Y(S) / D = 1
    st.sums["X1"][0], st.sums["X2"][0] = 10.0, 10.1
    return st


def test_a_zero_count_bounds_the_radiance_and_the_bound_falls_as_photons_are_emitted() -> None:
    a, b = estimate(_two_pixels(10_000), 0.9), estimate(_two_pixels(40_000), 0.9)
    # q = 1 per unit density, R = 0.1 (the dark pixel takes the largest lit radius): -ln(0.1) / (pi R^2 E)
    assert a.noise[1] == pytest.approx(-math.log(0.1) / (math.pi * 0.01 * 10_000))
    assert b.noise[1] == pytest.approx(a.noise[1] / 4)
    assert a.bias[1] == 0.0 and a.bound[1] == a.noise[1]
    assert not a.known[1] and a.measured[1]


def test_the_average_is_the_larger_of_the_lit_mean_and_the_mean_over_every_measured_pixel() -> None:
    rel = np.array([0.4, 0.2, 0.01, 0.01, 0.01, 0.01])
    known = np.array([True, True, False, False, False, False])
    measured = np.ones_like(known)
    ones = np.ones(len(rel))
    assert image_average(rel, ones, known, measured) == pytest.approx(0.3)  # 4 dark pixels do not dilute it
    # a dark half raises it by its share: the mean over all four
    assert image_average(np.array([0.02, 0.02, 0.5, 0.5]), ones[:4], known[:4], measured[:4]) == pytest.approx(0.26)


def test_one_never_lit_pixel_does_not_set_the_image_at_100_percent() -> None:
    """The corner of cornell-box (2^18 photons a pass): one pixel of 62,500 measured in a
    pass without a photon held the job's error at 1.0 from pass 15 to 30, where the lit
    pixels' mean was 0.21-0.16, when the average was the larger of the lit and the dark means."""
    rel = np.full(62_500, 0.2)
    rel[-1] = 1.0
    known = np.ones(62_500, bool)
    known[-1] = False
    assert image_average(rel, np.ones(62_500), known, np.ones_like(known)) == pytest.approx(0.2 + 0.8 / 62_500)


def test_pixels_weigh_by_their_light() -> None:
    """90 lit pixels at 5% and a ring of 10 dim ones (at the floor, a twentieth of the light)
    at 150%: the ring barely moves the average; the same 10 pixels as bright as the rest and
    50% off (a wrong edge where the light is) count in full."""
    known = np.ones(100, bool)
    ring = np.r_[np.full(90, 0.05), np.full(10, 1.5)]
    weight = np.r_[np.ones(90), np.full(10, 0.05)]
    assert image_average(ring, weight, known, known) == pytest.approx((90 * 0.05 + 10 * 1.5 * 0.05) / 90.5)
    edge = np.r_[np.full(90, 0.05), np.full(10, 0.5)]
    assert image_average(edge, np.ones(100), known, known) == pytest.approx(0.095)


def test_a_small_lit_region_converges_at_its_threshold(make_engine, tmp_path) -> None:
    """A spot light lighting 7% of a 64 px view (its foot 0.48 wide on the plane), default
    settings, threshold 0.1: the ring of pixels at the cone's edge, large relative bounds on
    a small share of the light, does not hold the job; its actual error by the same
    definition is at most the threshold when it stops."""
    cone = math.degrees(math.atan(0.48 / SPOT["height"]))
    data = spot_plane_scene((64, 64))
    data["lights"][0]["cone_angle"] = cone
    path = tmp_path / "spot.json"
    path.write_text(json.dumps(data))
    eng = make_engine(path, seed=12)
    truth = spot_plane(eng, **{**SPOT, "cone_degrees": cone})
    assert 0.05 < np.mean(truth > 0.0) < 0.08
    state, est = render_until(eng, 0.1, max_passes=200)
    assert est.average <= 0.1, (state.passes, est.average)
    assert actual_average(est, truth) <= 0.1, (state.passes, est.average, actual_average(est, truth))


def test_a_mostly_dark_spot_light_image_converges_with_its_actual_error_below_the_threshold(make_engine,
                                                                                           tmp_path) -> None:
    eng = make_engine(spot_scene(tmp_path), photons_per_pass=1 << 14, seed=12)
    truth = spot_plane(eng, **SPOT)
    assert np.mean(truth == 0.0) > 0.75  # the case of issue 11: most pixels outside the cone
    state, est = render_until(eng, 0.1, max_passes=600)  # at the default confidence, 0.9
    assert est.average <= 0.1, (state.passes, est.average)
    actual = actual_average(est, truth)  # the same definition, against the analytic radiance
    assert actual <= 0.1, (state.passes, est.average, actual)
