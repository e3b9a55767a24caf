"""A validated scene flattened into the arrays the kernels read (layouts in kernels/*.cl)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kernels.contract import EMITTERS
from worker.adjacency import triangle_neighbours
from worker.bvh import build_bvh
from worker.env_light import env_map
from worker.scene import (
    SCENES_DIR,
    DirectionalLight,
    EnvironmentLight,
    PointLight,
    Scene,
    Sphere,
    SpotLight,
    shape_geometry,
)
from worker.surfaces import int_bits, surface_records, texture_table

EMIT_TRIANGLE, EMIT_SPHERE, EMIT_POINT, EMIT_SPOT, EMIT_DIRECTIONAL, EMIT_ENVIRONMENT = (
    EMITTERS[k] for k in ("triangle", "sphere", "point", "spot", "directional", "environment"))


@dataclass(frozen=True)
class SceneArrays:
    width: int
    height: int
    tri_v0: np.ndarray  # (T, 4) float32, w = surface index bits
    tri_e1: np.ndarray  # w = 1 where the triangle has shading normals
    tri_e2: np.ndarray
    tri_nrm: np.ndarray  # (3 T, 4) float32 corner normals where tri_e1.w = 1; empty if no triangle has any
    tri_adj: np.ndarray  # (T, 4) int32 neighbours across the edges on the same surface (worker/adjacency.py)
    node_lo: np.ndarray  # (nodes, 4) float32, see worker/bvh.py
    node_hi: np.ndarray
    spheres: np.ndarray  # (S, 4) float32 centre + radius
    sphere_surf: np.ndarray  # (S,) int32
    surfaces: np.ndarray  # (SURF_ROWS * shapes + table rows, 4) float32 (worker/surfaces.py)
    tex_info: np.ndarray  # (TEX_ROWS * textures, 4) float32 texture records (kernels/textures.cl)
    tex_texels: np.ndarray  # (bytes,) uint8, every texture's texels (surfaces.py texture_table)
    tex_uv: np.ndarray  # (3 T, 2) float32 corner texture coordinates; empty if no material is textured
    emitters: np.ndarray  # (4 * E + map rows, 4) float32 rows, see kernels/lights.cl, environment.cl
    emitter_cdf: np.ndarray  # (E,) float32, last entry exactly 1
    camera: np.ndarray  # (4, 4) float32, see CameraDesc in kernels/eye_pass.cl
    pixel_angle: float  # pixel footprint per unit distance along the view axis
    scene_diagonal: float
    eps_floor: float  # the ray offset's scale near the origin (kernels/geometry.cl, ray_eps)
    radiance_scale: float  # the brightest light's radiance, or what a delta light gives a white surface

    @property
    def n_pixels(self) -> int:
        return self.width * self.height


def compile_scene(scene: Scene, base_dir: Path, resolution: tuple[int, int] | None = None,
                  root: Path = SCENES_DIR) -> SceneArrays:
    width, height = resolution or scene.camera.resolution
    geometry = shape_geometry(scene, base_dir, root)
    per_shape = [None if g is None else g.triangles for g in geometry]

    tri_list = [t for t in per_shape if t is not None]
    tris = np.concatenate(tri_list) if tri_list else np.zeros((0, 3, 3))
    tri_surf = np.concatenate([np.full(len(t), i, np.int32) for i, t in enumerate(per_shape) if t is not None]) \
        if tri_list else np.zeros(0, np.int32)
    node_lo, node_hi, order = build_bvh(tris)
    tris, tri_surf = tris[order], tri_surf[order]
    tri_v0 = np.zeros((len(tris), 4), np.float32)
    tri_e1 = np.zeros((len(tris), 4), np.float32)
    tri_e2 = np.zeros((len(tris), 4), np.float32)
    tri_v0[:, :3] = tris[:, 0]
    tri_v0[:, 3] = int_bits(tri_surf)
    tri_e1[:, :3] = tris[:, 1] - tris[:, 0]
    tri_e2[:, :3] = tris[:, 2] - tris[:, 0]

    # Shading normals, per corner, for the triangles of meshes that have them.
    tri_nrm = np.zeros((0, 4), np.float32)
    if any(g is not None and g.normals is not None for g in geometry):
        corner = np.concatenate([g.normals if g.normals is not None else np.zeros_like(g.triangles)
                                 for g in geometry if g is not None])[order]
        smooth = np.concatenate([np.full(len(g.triangles), g.normals is not None)
                                 for g in geometry if g is not None])[order]
        tri_e1[:, 3] = smooth
        tri_nrm = np.zeros((3 * len(tris), 4), np.float32)
        tri_nrm[:, :3] = corner.reshape(-1, 3)

    # Texture coordinates, per corner, where a texture is looked up at all: a mesh's own, a
    # quad's (s, t), else the barycentric (b1, b2) (as Mitsuba 3 for a mesh without them).
    tex_info, tex_texels = texture_table(scene)
    tex_uv = np.zeros((0, 2), np.float32)
    if len(tex_info) and len(tris):
        barycentric = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        corner_uv = np.concatenate([np.broadcast_to(barycentric, (len(g.triangles), 3, 2)) if g.uvs is None else g.uvs
                                    for g in geometry if g is not None])[order]
        tex_uv = corner_uv.reshape(-1, 2).astype(np.float32)

    sphere_idx = [i for i, s in enumerate(scene.shapes) if isinstance(s, Sphere)]
    sphere_list = [s for s in scene.shapes if isinstance(s, Sphere)]
    spheres = np.array([[*s.center, s.radius] for s in sphere_list], np.float32).reshape(-1, 4)
    sphere_surf = np.array(sphere_idx, np.int32)

    # Bounding sphere of everything: directional and environment lights emit from a disc that covers it.
    placed = [light for light in scene.lights if isinstance(light, PointLight | SpotLight)]
    points = [tris.reshape(-1, 3)]
    points += [np.array([np.subtract(s.center, s.radius), np.add(s.center, s.radius)]) for s in sphere_list]
    points += [np.array([light.position]) for light in placed]
    points += [np.array([scene.camera.position])]
    allp = np.concatenate([p.reshape(-1, 3) for p in points])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    centre = 0.5 * (lo + hi)
    bound_radius = 0.5 * float(np.linalg.norm(hi - lo)) * 1.001 + 1e-6
    # The ray offset's scale where coordinates are small, so that a scene's image does not depend
    # on its unit: the largest coordinate of where rays start and land (triangle corners, lights,
    # the camera, and each sphere's point nearest the origin: a wall made of a sphere of radius
    # 1e5, as in smallppm, is where its surface is, not where its centre is), at most 1 (the
    # offset is relative beyond).
    reach = [np.abs(tris).max(initial=0.0), np.abs(scene.camera.position).max(), np.abs(scene.camera.look_at).max()]
    reach += [abs(float(np.linalg.norm(s.center)) - s.radius) for s in scene.shapes if isinstance(s, Sphere)]
    reach += [np.abs(light.position).max() for light in placed]
    extent = float(max(reach))
    eps_floor = min(1.0, extent) if extent > 0.0 else 1.0

    # Emitters, each with its power (flux) for selection in proportion to power, and each light's
    # radiance scale (SceneArrays.radiance_scale): an area light's radiance; a point or spot
    # light's intensity, and a directional light's irradiance, as the radiance of a white
    # surface they light face on, at the camera's or its look-at point's distance from the light
    # (whichever is larger: furnace's light is at the camera) for the first two (not the scene's
    # size: smallppm's walls are spheres of radius 1e5).
    rows: list[np.ndarray] = []
    powers: list[np.ndarray] = []
    radiances: list[float] = []

    def delta_radiance(intensity: float, position: tuple[float, float, float]) -> float:
        d = max(float(np.linalg.norm(np.subtract(position, p))) for p in (scene.camera.position, scene.camera.look_at))
        return intensity / (math.pi * d ** 2)

    def add(kind: int, r0: tuple, r1: tuple, r2: tuple, power: np.ndarray) -> None:
        rec = np.zeros((4, 4), np.float32)
        rec[0, :3], rec[1], rec[2] = r0, r1, r2
        rec[0, 3] = int_bits([kind])[0]
        rec[3, :3] = power
        rows.append(rec)
        powers.append(power)

    for i, shape in enumerate(scene.shapes):
        if shape.emission is None or max(shape.emission) <= 0.0:
            continue
        le = np.array(shape.emission, np.float64)
        radiances.append(float(le.mean()))
        if isinstance(shape, Sphere):
            area = 4.0 * math.pi * shape.radius ** 2
            add(EMIT_SPHERE, tuple(shape.center), (0, 0, 0, 0), (0, 0, 0, shape.radius), math.pi * le * area)
            continue
        t = per_shape[i]
        assert t is not None, "every shape but a sphere has triangles"
        e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        areas = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
        for k in np.nonzero(areas > 0.0)[0]:  # Lambertian emitter: flux = pi * Le * area
            add(EMIT_TRIANGLE, tuple(t[k, 0]), (*e1[k], 0.0), (*e2[k], 0.0), math.pi * le * areas[k])
    for light in scene.lights:
        power = np.array(getattr(light, "power", (0, 0, 0)), np.float64)
        if isinstance(light, PointLight):
            add(EMIT_POINT, tuple(light.position), (0, 0, 0, 0), (0, 0, 0, 0), power)
            radiances.append(delta_radiance(float(power.mean()) / (4.0 * math.pi), light.position))
        elif isinstance(light, SpotLight):
            axis = np.array(light.direction) / np.linalg.norm(light.direction)
            cos_cone = math.cos(math.radians(light.cone_angle))
            add(EMIT_SPOT, tuple(light.position), (*axis, cos_cone), (0, 0, 0, 0), power)
            radiances.append(delta_radiance(float(power.mean()) / (2.0 * math.pi * (1.0 - cos_cone)), light.position))
        elif isinstance(light, DirectionalLight):
            axis = np.array(light.direction) / np.linalg.norm(light.direction)
            power = np.array(light.irradiance, np.float64) * math.pi * bound_radius ** 2
            add(EMIT_DIRECTIONAL, tuple(centre - axis * bound_radius), (*axis, bound_radius), (0, 0, 0, 0), power)
            radiances.append(float(np.mean(light.irradiance)) / math.pi)
    # The environment, last (kernels/environment.cl): its power as a directional light's over
    # the same disc, from every direction; its radiance scale its mean radiance.
    sky = next((env_map(scene, light, base_dir, root) for light in scene.lights
                if isinstance(light, EnvironmentLight)), None)
    if sky is not None:
        integral = sky.integral()
        add(EMIT_ENVIRONMENT, tuple(centre), (*sky.radiance, bound_radius), (0, 0, 0, 0),
            math.pi * bound_radius ** 2 * integral)
        radiances.append(float(integral.mean()) / (4.0 * math.pi))
    radiance_scale = max((r for r in radiances if r > 0.0), default=1.0)

    weights = np.array([p.sum() for p in powers], np.float64)
    keep = weights > 0.0
    rows = [r for r, k in zip(rows, keep, strict=True) if k]
    weights = weights[keep]
    emitters = np.concatenate(rows) if rows else np.zeros((4, 4), np.float32)
    if rows:
        pdf = weights / weights.sum()
        emitters[3::4, 3] = pdf
        cdf = np.cumsum(pdf).astype(np.float32)
        cdf[-1] = 1.0
    else:
        cdf = np.ones(1, np.float32)
    if sky is not None and keep[-1] and sky.texels is not None:  # the map's rows follow the records
        emitters[-2, 0] = int_bits([len(emitters)])[0]
        emitters = np.concatenate([emitters, sky.rows()])

    cam = scene.camera
    pos = np.array(cam.position, np.float64)
    forward = np.array(cam.look_at, np.float64) - pos
    focus = cam.focus_distance or float(np.linalg.norm(forward))
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.array(cam.up, np.float64))
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    tan_y = math.tan(math.radians(cam.fov) / 2.0)
    tan_x = tan_y * width / height
    camera = np.array([[*pos, cam.near_clip], [*forward, cam.aperture_radius],
                       [*(right * tan_x), focus], [*(up * tan_y), 0.0]], np.float32)

    # Each triangle's neighbours on its surface, from its corners rounded once to float32: a
    # mesh's shared vertex is then the same corner in every triangle. (Corners made as the
    # kernels make them, v0 + e1 in float32, differ in their last bit from triangle to
    # triangle: a 500 x 500 sheet in [-1, 1] had 222,000 of its edges taken for its rim.)
    tri_adj = triangle_neighbours(tris.astype(np.float32))

    return SceneArrays(
        width=width, height=height, tri_v0=tri_v0, tri_e1=tri_e1, tri_e2=tri_e2, tri_nrm=tri_nrm,
        tri_adj=tri_adj,
        node_lo=node_lo, node_hi=node_hi, spheres=spheres, sphere_surf=sphere_surf,
        surfaces=surface_records(scene), tex_info=tex_info, tex_texels=tex_texels, tex_uv=tex_uv,
        emitters=emitters, emitter_cdf=cdf,
        camera=camera, pixel_angle=2.0 * tan_y / height,
        scene_diagonal=float(np.linalg.norm(hi - lo)), eps_floor=eps_floor, radiance_scale=radiance_scale,
    )
