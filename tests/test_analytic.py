"""Accuracy against closed-form radiance (tests/analytic.py), with real kernels on PoCL."""

from __future__ import annotations

import numpy as np

from tests.analytic import FURNACE_L, point_plane
from tests.conftest import image, render
from worker.integrators.photon_mapping import GatherInputs


def test_furnace_mean_within_two_percent(make_engine) -> None:
    eng = make_engine("furnace", photons_per_pass=1 << 16, seed=3)
    state = render(eng, 24)
    mean = image(eng, state).mean()
    assert abs(mean / FURNACE_L - 1.0) < 0.02, (mean, FURNACE_L)


def test_furnace_per_pixel_error_falls_with_passes(make_engine) -> None:
    eng = make_engine("furnace", photons_per_pass=1 << 14, seed=4)
    state = eng.start()
    rms = {}
    for k in range(64):
        state.merge(eng.render_batch(state, k, 1))
        if k + 1 in (4, 16, 64):
            rel = image(eng, state) / FURNACE_L - 1.0
            rms[k + 1] = float(np.sqrt(np.mean(rel ** 2)))
    # Variance falls like passes^-alpha: 16x the passes should cut the RMS error well over 2x.
    assert rms[4] > rms[16] > rms[64], rms
    assert rms[64] < rms[4] / 2.5, rms


def test_point_plane_matches_analytic_radiance(make_engine) -> None:
    """Per pixel, with every photon gathered (exact grid)."""
    eng = make_engine("point-plane", photons_per_pass=1 << 19, seed=5, gather="exact")
    state = render(eng, 64)
    est = image(eng, state)
    rel = est[..., 0] / point_plane(eng)[0].reshape(eng.arrays.height, eng.arrays.width) - 1.0
    assert abs(rel.mean()) < 0.01, rel.mean()
    assert np.sqrt(np.mean(rel ** 2)) < 0.025, np.sqrt(np.mean(rel ** 2))
    assert np.abs(rel).max() < 0.15, np.abs(rel).max()
    assert np.array_equal(est[..., 0], est[..., 2])  # grey light on a grey plane


def test_point_plane_stochastic_hash_is_unbiased_on_average(make_engine) -> None:
    """The stochastic hash keeps one photon per cell, so it is much noisier per pixel
    here (about 500 photons share a cell; bench/ charts the cost), but not biased."""
    eng = make_engine("point-plane", photons_per_pass=1 << 17, seed=6, gather="stochastic")
    state = render(eng, 48)
    rel = image(eng, state)[..., 0] / point_plane(eng)[0].reshape(eng.arrays.height, eng.arrays.width) - 1.0
    assert abs(rel.mean()) < 0.015, rel.mean()


def test_ppm_keeps_one_set_of_measurement_points(make_engine) -> None:
    """PPM: every pass uses pass 0's points, so what the eye sees directly repeats exactly,
    and the furnace still comes out at its analytic radiance."""
    eng = make_engine("furnace", photons_per_pass=1 << 15, seed=8, method="ppm")
    r = GatherInputs(eng.start().R0)
    a, b = eng.run_batch(r, 0, 1), eng.run_batch(r, 1, 1)
    assert np.array_equal(a.H, b.H) and np.array_equal(a.Ld, b.Ld)
    sppm = make_engine("furnace", photons_per_pass=1 << 15, seed=8, method="sppm")
    c, d = sppm.run_batch(r, 0, 1), sppm.run_batch(r, 1, 1)
    assert not np.array_equal(c.X1, d.X1)  # SPPM: new points every pass
    state = render(eng, 16)
    assert abs(image(eng, state).mean() / FURNACE_L - 1.0) < 0.02


def test_thin_lens_camera_conserves_radiance(make_engine, tmp_path) -> None:
    """A thin lens samples the aperture; inside the furnace every path sees L, so the image
    mean stays analytic while the rays really start across the aperture."""
    import json

    from worker.scene import bundled_scene_path

    scene = json.loads(bundled_scene_path("furnace").read_text())
    scene["camera"].update(aperture_radius=0.3, focus_distance=0.8, position=[0.0, 0.0, 0.2])
    path = tmp_path / "lens.json"
    path.write_text(json.dumps(scene))
    eng = make_engine(path, photons_per_pass=1 << 15, seed=9)
    assert eng.arrays.camera[1, 3] == np.float32(0.3)
    state = render(eng, 16)
    assert abs(image(eng, state).mean() / FURNACE_L - 1.0) < 0.02
