"""Closed-form answers of the analytic scenes, averaged over each pixel's footprint (SPPM
estimates the pixel average).

furnace: a point light of power Phi at the centre of a closed diffuse sphere of albedo
rho and radius r. Every point receives the same irradiance Phi/(4 pi r^2 (1 - rho))
(direct plus all bounces; the sphere's form factor is uniform), so the radiance is
L = rho Phi / (4 pi^2 r^2 (1 - rho)) everywhere: 1/pi for the bundled scene.

point-plane: a point light of intensity I = Phi/(4 pi) at height h above a Lambertian
plane of albedo rho. With s the distance from the foot of the light, d^2 = h^2 + s^2 and
C = rho I h / pi:  L = C d^-3,  grad L = -3 C (x, 0, z) d^-5,
lap L = C (9 s^2 - 6 h^2) d^-7  (the Laplacian within the plane).
"""

from __future__ import annotations

import math

import numpy as np

from worker.engine import Engine

FURNACE_RHO, FURNACE_PHI, FURNACE_R = 0.5, 4.0 * math.pi, 1.0


def furnace_radiance(rho: float | np.ndarray, power: float = FURNACE_PHI, r: float = FURNACE_R) -> float | np.ndarray:
    """rho Phi / (4 pi^2 r^2 (1 - rho)), per channel for an rgb albedo."""
    return rho * power / (4.0 * math.pi ** 2 * r ** 2 * (1.0 - np.asarray(rho)))


FURNACE_L = float(furnace_radiance(FURNACE_RHO))
PLANE_RHO, PLANE_I, PLANE_H = 0.5, 1.0, 1.0


def _plane_hits(eng: Engine, sub: int):  # noqa: ANN202
    """Where sub x sub positions per pixel of `eng`'s camera meet the plane y = 0: (x, z) arrays
    of shape (h * sub, w * sub), and the function that averages such an array per pixel."""
    cam = eng.arrays.camera.astype(np.float64)
    w, h = eng.arrays.width, eng.arrays.height
    o, fwd, right, up = cam[0, :3], cam[1, :3], cam[2, :3], cam[3, :3]
    offs = (np.arange(sub) + 0.5) / sub
    sx = 2.0 * (np.arange(w)[:, None] + offs[None, :]).ravel() / w - 1.0
    sy = 1.0 - 2.0 * (np.arange(h)[:, None] + offs[None, :]).ravel() / h
    d = fwd[None, None, :] + sx[None, :, None] * right + sy[:, None, None] * up
    p = o + (-o[1] / d[..., 1])[..., None] * d

    def pixel_mean(a: np.ndarray) -> np.ndarray:
        return a.reshape(h, sub, w, sub, *a.shape[2:]).mean(axis=(1, 3)).reshape(h * w, *a.shape[2:])

    return p[..., 0], p[..., 2], pixel_mean


def point_plane(eng: Engine, sub: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L, grad L, lap L) per pixel, (pixels,), (pixels, 3), (pixels,), averaged over sub x sub
    positions in each pixel, for the bundled point-plane scene seen by `eng`'s camera."""
    x, z, pixel_mean = _plane_hits(eng, sub)
    s2 = x ** 2 + z ** 2
    d2 = PLANE_H ** 2 + s2
    c = PLANE_RHO * PLANE_I * PLANE_H / math.pi
    L = c * d2 ** -1.5
    grad = -3.0 * c * np.stack([x, np.zeros_like(x), z], axis=-1) * d2[..., None] ** -2.5
    lap = c * (9.0 * s2 - 6.0 * PLANE_H ** 2) * d2 ** -3.5
    return pixel_mean(L), pixel_mean(grad), pixel_mean(lap)


def spot_plane(eng: Engine, rho: float, power: float, height: float, cone_degrees: float, sub: int = 8) -> np.ndarray:
    """L per pixel for a spot light of `power` (uniform in solid angle within its cone) at
    `height` above the origin of the plane y = 0, pointing straight down: inside the cone
    L = rho I h / (pi d^3), I = power / (2 pi (1 - cos cone)); zero outside."""
    x, z, pixel_mean = _plane_hits(eng, sub)
    d = np.sqrt(height ** 2 + x ** 2 + z ** 2)
    cos_cone = math.cos(math.radians(cone_degrees))
    intensity = power / (2.0 * math.pi * (1.0 - cos_cone))
    return pixel_mean(np.where(height / d >= cos_cone, rho * intensity * height / (math.pi * d ** 3), 0.0))
