"""Accuracy against closed-form radiance, with real kernels on PoCL.

furnace: a point light of power Phi at the centre of a closed diffuse sphere of albedo
rho and radius r. Every point receives the same irradiance Phi/(4 pi r^2 (1 - rho))
(direct plus all bounces; the sphere's form factor is uniform), so the radiance is
L = rho Phi / (4 pi^2 r^2 (1 - rho)) everywhere: 1/pi for the bundled scene.

point-plane: a point light of intensity I = Phi/(4 pi) at height h above a Lambertian
plane of albedo rho: L = rho/pi * I cos(theta)/d^2 = rho I h / (pi d^3). No other
surface exists, so this is the whole answer.
"""

from __future__ import annotations

import math

import numpy as np

from tests.conftest import image, render
from worker.stats import Accumulators

FURNACE_L = 0.5 * 4.0 * math.pi / (4.0 * math.pi ** 2 * 1.0 * (1.0 - 0.5))


def test_furnace_mean_within_two_percent(make_engine) -> None:
    eng = make_engine("furnace", photons_per_pass=1 << 16, seed=3)
    state = render(eng, 24)
    mean = image(eng, state).mean()
    assert abs(mean / FURNACE_L - 1.0) < 0.02, (mean, FURNACE_L)


def test_furnace_per_pixel_error_falls_with_passes(make_engine) -> None:
    eng = make_engine("furnace", photons_per_pass=1 << 14, seed=4)
    state = Accumulators.start(0.7, eng.initial_radius())
    rms = {}
    for k in range(64):
        state.merge(eng.run_batch(state.radius(), k, 1))
        if k + 1 in (4, 16, 64):
            rel = image(eng, state) / FURNACE_L - 1.0
            rms[k + 1] = float(np.sqrt(np.mean(rel ** 2)))
    # Variance falls like passes^-alpha: 16x the passes should cut the RMS error well over 2x.
    assert rms[4] > rms[16] > rms[64], rms
    assert rms[64] < rms[4] / 2.5, rms


def _point_plane_truth(eng, sub: int = 4) -> np.ndarray:
    """Pixel-averaged analytic radiance (SPPM estimates the pixel average)."""
    cam = eng.arrays.camera.astype(np.float64)
    w, h = eng.arrays.width, eng.arrays.height
    o, fwd, right, up = cam[0, :3], cam[1, :3], cam[2, :3], cam[3, :3]
    offs = (np.arange(sub) + 0.5) / sub
    xs = (np.arange(w)[:, None] + offs[None, :]).ravel()
    ys = (np.arange(h)[:, None] + offs[None, :]).ravel()
    sx = 2.0 * xs / w - 1.0
    sy = 1.0 - 2.0 * ys / h
    d = fwd[None, None, :] + sx[None, :, None] * right + sy[:, None, None] * up
    t = -o[1] / d[..., 1]
    p = o + t[..., None] * d
    rho, intensity, height = 0.5, 1.0, 1.0
    dist = np.sqrt(p[..., 0] ** 2 + p[..., 2] ** 2 + height ** 2)
    L = rho * intensity * height / (math.pi * dist ** 3)
    return L.reshape(h, sub, w, sub).mean(axis=(1, 3))


def test_point_plane_matches_analytic_radiance(make_engine) -> None:
    """Per pixel, with every photon gathered (exact grid)."""
    eng = make_engine("point-plane", photons_per_pass=1 << 19, seed=5, gather="exact")
    state = render(eng, 64)
    est = image(eng, state)
    rel = est[..., 0] / _point_plane_truth(eng) - 1.0
    assert abs(rel.mean()) < 0.01, rel.mean()
    assert np.sqrt(np.mean(rel ** 2)) < 0.025, np.sqrt(np.mean(rel ** 2))
    assert np.abs(rel).max() < 0.15, np.abs(rel).max()
    assert np.array_equal(est[..., 0], est[..., 2])  # grey light on a grey plane


def test_point_plane_stochastic_hash_is_unbiased_on_average(make_engine) -> None:
    """The stochastic hash keeps one photon per cell, so it is much noisier per pixel
    here (about 500 photons share a cell; bench/ charts the cost), but not biased."""
    eng = make_engine("point-plane", photons_per_pass=1 << 17, seed=6, gather="stochastic")
    state = render(eng, 48)
    rel = image(eng, state)[..., 0] / _point_plane_truth(eng) - 1.0
    assert abs(rel.mean()) < 0.015, rel.mean()
