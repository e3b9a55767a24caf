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

glowing box: a closed box whose walls all emit Le and reflect diffusely with albedo rho.
Radiance leaves every wall point as Le + rho L_in, and L_in = L everywhere solves it:
L = Le / (1 - rho), in every direction. Lossless specular objects inside (a mirror, glass
of albedo 1) leave that field as it is: a mirror sends L on as L, and glass's reflected
and transmitted shares (its radiance n^2 L inside, L again once out) add up to L. So does a
ball that glows and reflects as the walls do (a sphere emitter).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import numpy as np

from worker.engine import Engine
from worker.scene import bundled_scene_path

FURNACE_RHO, FURNACE_PHI, FURNACE_R = 0.5, 4.0 * math.pi, 1.0


def furnace_radiance(rho: float | np.ndarray, power: float = FURNACE_PHI, r: float = FURNACE_R) -> float | np.ndarray:
    """rho Phi / (4 pi^2 r^2 (1 - rho)), per channel for an rgb albedo."""
    return rho * power / (4.0 * math.pi ** 2 * r ** 2 * (1.0 - np.asarray(rho)))


FURNACE_L = float(furnace_radiance(FURNACE_RHO))
PLANE_RHO, PLANE_I, PLANE_H = 0.5, 1.0, 1.0


def camera_rays(eng: Engine, sub: int) -> tuple[np.ndarray, np.ndarray]:
    """The pinhole camera's origin and the directions of sub x sub positions per pixel,
    shape (h * sub, w * sub, 3) (kernels/eye_pass.cl's camera, without jitter)."""
    cam = eng.arrays.camera.astype(np.float64)
    w, h = eng.arrays.width, eng.arrays.height
    o, fwd, right, up = cam[0, :3], cam[1, :3], cam[2, :3], cam[3, :3]
    offs = (np.arange(sub) + 0.5) / sub
    sx = 2.0 * (np.arange(w)[:, None] + offs[None, :]).ravel() / w - 1.0
    sy = 1.0 - 2.0 * (np.arange(h)[:, None] + offs[None, :]).ravel() / h
    return o, fwd[None, None, :] + sx[None, :, None] * right + sy[:, None, None] * up


def _plane_hits(eng: Engine, sub: int):
    """Where sub x sub positions per pixel of `eng`'s camera meet the plane y = 0: (x, z) arrays
    of shape (h * sub, w * sub), and the function that averages such an array per pixel."""
    w, h = eng.arrays.width, eng.arrays.height
    o, d = camera_rays(eng, sub)
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


def shadowed_plane(eng: Engine, rho: float, power: float, light: tuple[float, float, float],
                   centre: tuple[float, float, float], radius: float, extent: float, sub: int = 8) -> np.ndarray:
    """L per pixel for a point light of `power` over the square |x|, |z| <= extent of the
    plane y = 0 (albedo rho) with a black sphere (albedo 0: it reflects nothing) casting a
    hard shadow: on the square L = rho I cos(theta) / (pi d^2) where the light is visible,
    I = power / (4 pi); zero where the sphere hides the light, the camera sees the sphere, or
    its ray passes the square (the far edge is in view)."""
    x, z, pixel_mean = _plane_hits(eng, sub)
    on_square = (np.abs(x) <= extent) & (np.abs(z) <= extent)
    cam = eng.arrays.camera.astype(np.float64)[0, :3]
    p = np.stack([x, np.zeros_like(x), z], axis=-1)
    c, lp = np.asarray(centre, np.float64), np.asarray(light, np.float64)

    def blocked(o: np.ndarray, e: np.ndarray) -> np.ndarray:
        """Whether the segment o -> e (per element) passes through the sphere."""
        d = e - o
        oc = o - c
        a, b, cc = np.sum(d * d, -1), np.sum(oc * d, -1), np.sum(oc * oc, -1) - radius ** 2
        disc = b * b - a * cc
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
        return (disc > 0.0) & (t > 0.0) & (t < 1.0)

    to_light = lp - p
    d2 = np.sum(to_light ** 2, -1)
    L = rho * power / (4.0 * math.pi) * to_light[..., 1] / np.sqrt(d2) / (math.pi * d2)
    seen = ~blocked(np.broadcast_to(cam, p.shape), p)
    return pixel_mean(np.where(on_square & seen & ~blocked(p, np.broadcast_to(lp, p.shape)), L, 0.0))


# Scenes written independently of the bundled ones (as JSON dicts), with their answers above.
SPOT = {"rho": 0.5, "power": 10.0, "height": 1.0, "cone_degrees": 40.0}
SHADOW = {"rho": 0.5, "power": 4.0 * math.pi, "light": (0.0, 2.0, 0.0), "centre": (0.0, 1.0, 0.0), "radius": 0.3,
          "extent": 5.0}
PATCH = {"rho": 0.5, "power": 10.0, "height": 1.0}
CHECKER = {"rho0": 0.8, "rho1": 0.1, "cell": 1.0}


def closed_sphere_scene(albedo: tuple[float, float, float], power: float = FURNACE_PHI) -> dict:
    """A point light at the centre of a closed unit sphere, seen from the centre (furnace_radiance)."""
    return {
        "camera": {"position": [0, 0, 0], "look_at": [0, 0, -1], "up": [0, 1, 0], "fov": 120, "resolution": [32, 32]},
        "materials": {"wall": {"type": "diffuse", "albedo": list(albedo)}},
        "shapes": [{"type": "sphere", "center": [0, 0, 0], "radius": 1.0, "material": "wall"}],
        "lights": [{"type": "point", "position": [0, 0, 0], "power": [power] * 3}],
    }


GLOW = {"le": 1.0, "rho": 0.5}
# Centre, radius, material: a mirror ball, a glass ball, and a ball that glows and reflects as the walls do.
GLOW_SPHERES = (((-0.4, -0.4, -0.2), 0.3, "mirror"), ((0.4, -0.3, -0.3), 0.35, "glass"),
                ((0.0, 0.45, -0.4), 0.25, "glow"))


def glowing_box_scene(resolution: tuple[int, int] = (48, 48)) -> dict:
    """GLOW: the cube [-1, 1]^3 of six inward-facing glowing walls, a mirror ball, a glass ball
    and a glowing ball inside (GLOW_SPHERES), seen from inside: Le / (1 - rho) at every pixel."""
    # Each wall: corner, edge1, edge2 with edge1 x edge2 pointing into the box (the front side).
    walls = [((-1, -1, -1), (0, 0, 2), (2, 0, 0)), ((-1, 1, -1), (2, 0, 0), (0, 0, 2)),
             ((-1, -1, -1), (0, 2, 0), (0, 0, 2)), ((1, -1, -1), (0, 0, 2), (0, 2, 0)),
             ((-1, -1, -1), (2, 0, 0), (0, 2, 0)), ((-1, -1, 1), (0, 2, 0), (2, 0, 0))]
    return {
        "camera": {"position": [0, 0, 0.9], "look_at": [0, -0.2, 0], "fov": 70, "resolution": list(resolution)},
        "materials": {"wall": {"type": "diffuse", "albedo": [GLOW["rho"]] * 3},
                      "glow": {"type": "diffuse", "albedo": [GLOW["rho"]] * 3}, "mirror": {"type": "mirror"},
                      "glass": {"type": "glass", "ior": 1.5}},
        "shapes": [{"type": "quad", "corner": list(c), "edge1": list(e1), "edge2": list(e2), "material": "wall",
                    "emission": [GLOW["le"]] * 3} for c, e1, e2 in walls]
                  + [{"type": "sphere", "center": list(c), "radius": r, "material": m}
                     | ({"emission": [GLOW["le"]] * 3} if m == "glow" else {}) for c, r, m in GLOW_SPHERES],
        "lights": [],
    }


def glowing_box_views(eng: Engine, sub: int = 4) -> dict[str, np.ndarray]:
    """Boolean masks (pixels,) for glowing_box_scene, by the ball's material: the pixels whose
    sub x sub camera rays, and those of the 8 pixels around them, all first meet that ball,
    or none (the box's walls: "walls"). The neighbours keep a pixel's jittered rays, which
    reach its edges, and light tracing's splats, which land anywhere in it, off the other
    views."""
    w, h = eng.arrays.width, eng.arrays.height
    o, d = camera_rays(eng, sub)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    nearest = np.full(d.shape[:2], np.inf)
    first = np.full(d.shape[:2], -1)
    for k, (c, r, _) in enumerate(GLOW_SPHERES):
        oc = o - np.asarray(c)
        b = (d @ oc)
        disc = b * b - (oc @ oc - r * r)
        t = np.where(disc > 0.0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        closer = (t > 0.0) & (t < nearest)
        nearest, first = np.where(closer, t, nearest), np.where(closer, k, first)
    per_pixel = first.reshape(h, sub, w, sub).transpose(0, 2, 1, 3).reshape(h * w, sub * sub)
    def wholly(k: int) -> np.ndarray:
        full = np.pad((per_pixel == k).all(axis=1).reshape(h, w), 1)
        around = np.stack([full[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
        return around.all(axis=0).ravel()

    views = {m: wholly(k) for k, (_, _, m) in enumerate(GLOW_SPHERES)}
    views["walls"] = wholly(-1)
    return views


def spot_plane_scene(resolution: tuple[int, int] = (64, 64)) -> dict:
    """SPOT straight down over a plane; the camera sees 1.7 units either side of the light's
    foot, the cone lights 0.84 of it: 75% of the pixels are never lit (spot_plane)."""
    return {
        "camera": {"position": [0, 3, 0], "look_at": [0, 0, 0], "up": [0, 0, -1], "fov": 60,
                   "resolution": list(resolution)},
        "materials": {"plane": {"type": "diffuse", "albedo": [SPOT["rho"]] * 3}},
        "shapes": [{"type": "quad", "corner": [-5, 0, -5], "edge1": [0, 0, 10], "edge2": [10, 0, 0],
                    "material": "plane"}],
        "lights": [{"type": "spot", "position": [0, SPOT["height"], 0], "direction": [0, -1, 0],
                    "cone_angle": SPOT["cone_degrees"], "power": [SPOT["power"]] * 3}],
    }


def patch_scene(fov: float, resolution: tuple[int, int] = (24, 24)) -> dict:
    """PATCH: a point light 1 above a large plane, seen from 3 above through `fov` degrees:
    only paths leaving the light toward the seen patch are visible (V_c ~ its solid angle /
    4 pi; the plane's bounce escapes upward). Its radiance: patch_plane."""
    return {
        "camera": {"position": [0, 3, 0], "look_at": [0, 0, 0], "up": [0, 0, -1], "fov": fov,
                   "resolution": list(resolution)},
        "materials": {"plane": {"type": "diffuse", "albedo": [PATCH["rho"]] * 3}},
        "shapes": [{"type": "quad", "corner": [-50, 0, -50], "edge1": [0, 0, 100], "edge2": [100, 0, 0],
                    "material": "plane"}],
        "lights": [{"type": "point", "position": [0, PATCH["height"], 0], "power": [PATCH["power"]] * 3}],
    }


def checker_plane_scene(resolution: tuple[int, int] = (64, 64)) -> dict:
    """point-plane with its plane a grey checkerboard (CHECKER: albedos rho0 and rho1, cells
    of `cell` units; the quad's (s, t) run along z and x over 20 units from -10)."""
    data = json.loads(bundled_scene_path("point-plane").read_text())
    k = 20.0 / CHECKER["cell"]
    data["textures"] = {"checks": {"type": "checkerboard", "color0": [CHECKER["rho0"]] * 3,
                                   "color1": [CHECKER["rho1"]] * 3, "to_uv": [[k, 0.0, 0.0], [0.0, k, 0.0]]}}
    data["materials"]["plane"] = {"type": "diffuse", "albedo": {"texture": "checks"}}
    data["camera"]["resolution"] = list(resolution)
    return data


def checker_plane(eng: Engine, rho0: float, rho1: float, cell: float, sub: int = 8) -> np.ndarray:
    """L per pixel for checker_plane_scene: point-plane's L = rho I h / (pi d^3) with rho the
    albedo of the cell each point lies in (rho0 where the cell indices along z and x add to
    an even number)."""
    x, z, pixel_mean = _plane_hits(eng, sub)
    odd = (np.floor((z + 10.0) / cell) + np.floor((x + 10.0) / cell)) % 2
    d2 = PLANE_H ** 2 + x ** 2 + z ** 2
    return pixel_mean(np.where(odd == 0, rho0, rho1) * PLANE_I * PLANE_H / (math.pi * d2 ** 1.5))


def patch_plane(eng: Engine) -> np.ndarray:
    """L per pixel for patch_scene: the point light's lower half is a spot of cone 90 degrees
    with half its power (spot_plane)."""
    return spot_plane(eng, PATCH["rho"], PATCH["power"] / 2.0, PATCH["height"], 90.0)


def shadow_scene(resolution: tuple[int, int] = (64, 64)) -> dict:
    """SHADOW: a black sphere between a point light and a plane, seen obliquely (shadowed_plane)."""
    return {
        "camera": {"position": [0, 2.5, 3], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 50,
                   "resolution": list(resolution)},
        "materials": {"plane": {"type": "diffuse", "albedo": [SHADOW["rho"]] * 3},
                      "black": {"type": "diffuse", "albedo": [0, 0, 0]}},
        "shapes": [{"type": "quad", "corner": [-SHADOW["extent"], 0, -SHADOW["extent"]],
                    "edge1": [0, 0, 2 * SHADOW["extent"]], "edge2": [2 * SHADOW["extent"], 0, 0], "material": "plane"},
                   {"type": "sphere", "center": list(SHADOW["centre"]), "radius": SHADOW["radius"],
                    "material": "black"}],
        "lights": [{"type": "point", "position": list(SHADOW["light"]), "power": [SHADOW["power"]] * 3}],
    }


def edge_pixels(ref: np.ndarray, within: int = 1) -> np.ndarray:
    """(H, W) mask of the pixels within `within` pixels of a jump in the reference image
    `ref` (H, W): a pixel whose 4-neighbours differ from it by more than a quarter of
    max(its value, 5% of the mean lit value)."""
    floor = 0.05 * ref[ref > 0].mean()
    pad = np.pad(ref, 1, mode="edge")
    jumps = np.max([np.abs(pad[1:-1, 1:-1] - pad[:-2, 1:-1]), np.abs(pad[1:-1, 1:-1] - pad[2:, 1:-1]),
                    np.abs(pad[1:-1, 1:-1] - pad[1:-1, :-2]), np.abs(pad[1:-1, 1:-1] - pad[1:-1, 2:])], axis=0)
    ys, xs = np.nonzero(jumps > 0.25 * np.maximum(ref, floor))
    if len(ys) == 0:
        return np.zeros(ref.shape, bool)
    yy, xx = np.mgrid[0:ref.shape[0], 0:ref.shape[1]]
    return np.min(np.hypot(yy[..., None] - ys, xx[..., None] - xs), axis=-1) <= within


# The analytic cases with a discontinuity in view, where error bounds are checked at edge and
# at smooth pixels: the scene's builder (of a resolution; None: the bundled point-plane,
# smooth everywhere) and the luminance per pixel for an engine of it.
EdgeCase = tuple[Callable[[tuple[int, int]], dict] | None, Callable[[Engine], np.ndarray]]
EDGE_CASES: dict[str, EdgeCase] = {
    "spot cone edge": (spot_plane_scene, lambda eng: spot_plane(eng, **SPOT)),
    "hard shadow": (shadow_scene, lambda eng: shadowed_plane(eng, **SHADOW)),
    "texture edge": (checker_plane_scene, lambda eng: checker_plane(eng, **CHECKER)),
    "point-plane": (None, lambda eng: point_plane(eng)[0]),
}
