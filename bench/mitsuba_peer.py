"""A peer renderer: our scene format converted to Mitsuba 3 (`scalar_rgb`), rendered with its
path tracer (`path`) or particle tracer (`ptracer`).

The conversion is exact but for one material: Mitsuba 3 has no modified Phong, so `glossy`
becomes a Beckmann rough conductor with the matching roughness (`beckmann_alpha`) and no
Fresnel falloff: close, not identical, so on the `glossy` scene the peer converges to a
slightly different image. Every other material is the Mitsuba plugin that the importer
(worker/mitsuba_scene.py) reads into it, with the same parameters. Units match ours:
emission is radiance, point and spot `power` is flux (intensity = power / solid angle),
directional `irradiance` is irradiance, an environment's map is radiance (Mitsuba's
`envmap` reads a lat-long map as ours does). Pixels are box-filtered, as SPPM averages them.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np

from worker.env_light import env_map
from worker.scene import (
    Conductor,
    Diffuse,
    DirectionalLight,
    EnvironmentLight,
    Glass,
    Glossy,
    Mesh,
    Mirror,
    Plastic,
    PointLight,
    Quad,
    RoughConductor,
    RoughGlass,
    RoughPlastic,
    Scene,
    Sphere,
    SpotLight,
    ThinGlass,
    shape_triangles,
)

_mi: Any = None


def mitsuba() -> Any:
    """The mitsuba module, with the CPU variant that works here (llvm variants crash in
    this machine's LLVM; stack notes)."""
    global _mi
    if _mi is None:
        import mitsuba as mi

        mi.set_variant("scalar_rgb")
        mi.set_log_level(mi.LogLevel.Warn)  # no progress bars in logs
        _mi = mi
    return _mi


def _rgb(value: tuple[float, float, float] | np.ndarray) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(v) for v in value]}


def beckmann_alpha(exponent: float) -> float:
    """The Beckmann roughness alpha whose lobe matches our Phong exponent n: alpha = sqrt(2 / (4 n + 2)).

    Walter et al. 2007 match Beckmann's alpha to the exponent m = 2 / alpha^2 - 2 of a Phong
    lobe about the half vector. Our lobe is about the mirror direction, which turns twice as
    fast as the half vector: cos^m(psi / 2) ~ cos^(m/4)(psi) for small angles, so n = m / 4.
    """
    return math.sqrt(2.0 / (4.0 * exponent + 2.0))


def _metal(material: Conductor | RoughConductor) -> dict[str, Any]:
    """A conductor's Mitsuba properties: eta and k, or material "none" (Mitsuba's eta = 0,
    k = 1: Fresnel reflectance 1) where ours has none."""
    out: dict[str, Any] = {"specular_reflectance": _rgb(material.specular)}
    if material.eta is None or material.k is None:
        return {**out, "material": "none"}
    return {**out, "eta": _rgb(material.eta), "k": _rgb(material.k)}


def _coat(material: Plastic) -> dict[str, Any]:
    return {"diffuse_reflectance": _rgb(material.albedo), "specular_reflectance": _rgb(material.specular),
            "int_ior": material.ior, "ext_ior": 1.0, "nonlinear": material.nonlinear}


def _opaque(material: Any) -> dict[str, Any]:
    """The Mitsuba bsdf of one of our opaque materials (one-sided, as Mitsuba's are)."""
    if isinstance(material, Mirror):
        return {"type": "conductor", "material": "none", "specular_reflectance": _rgb(material.albedo)}
    if isinstance(material, Glossy):
        return {"type": "roughconductor", "material": "none", "distribution": "beckmann",
                "alpha": beckmann_alpha(material.exponent), "specular_reflectance": _rgb(material.albedo)}
    if isinstance(material, Conductor):
        return {"type": "conductor", **_metal(material)}
    if isinstance(material, RoughConductor):
        return {"type": "roughconductor", "alpha": material.alpha, "distribution": material.distribution,
                **_metal(material)}
    if isinstance(material, RoughPlastic):
        return {"type": "roughplastic", "alpha": material.alpha, "distribution": material.distribution,
                **_coat(material)}
    if isinstance(material, Plastic):
        return {"type": "plastic", **_coat(material)}
    assert isinstance(material, Diffuse), material
    return {"type": "diffuse", "reflectance": _rgb(material.albedo)}


def _bsdf(material: Any) -> dict[str, Any]:
    """Our opaque surfaces reflect on both sides (the furnace is seen from inside); Mitsuba's
    are one-sided unless wrapped in `twosided`. Glass and thin glass are two-sided by nature
    (Mitsuba refuses them in `twosided`)."""
    if isinstance(material, Glass):
        transmittance = material.albedo if material.transmittance is None else material.transmittance
        out = {"type": "dielectric", "int_ior": material.ior, "ext_ior": 1.0,
               "specular_reflectance": _rgb(material.albedo), "specular_transmittance": _rgb(transmittance)}
        if isinstance(material, RoughGlass):
            out.update(type="roughdielectric", alpha=material.alpha, distribution=material.distribution)
        return out
    if isinstance(material, ThinGlass):
        return {"type": "thindielectric", "int_ior": material.ior, "ext_ior": 1.0,
                "specular_reflectance": _rgb(material.albedo),
                "specular_transmittance": _rgb(material.transmittance)}
    return {"type": "twosided", "bsdf": _opaque(material)}


def _frame(axis: np.ndarray) -> np.ndarray:
    """Any vector not parallel to `axis` (an up vector for look_at)."""
    return np.array([0.0, 1.0, 0.0]) if abs(axis[1]) < 0.9 else np.array([1.0, 0.0, 0.0])


def scene_dict(scene: Scene, base_dir: Path, resolution: tuple[int, int], spp: int,
               integrator: Literal["path", "ptracer"], workdir: Path) -> dict[str, Any]:
    mi = mitsuba()
    T = mi.ScalarTransform4f
    cam = scene.camera
    width, height = resolution
    sensor: dict[str, Any] = {
        "type": "thinlens" if cam.aperture_radius > 0 else "perspective",
        "fov": cam.fov, "fov_axis": "y", "near_clip": max(cam.near_clip, 1e-4), "far_clip": 1e7,
        "to_world": T().look_at(origin=list(cam.position), target=list(cam.look_at), up=list(cam.up)),
        "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                 "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp},
    }
    if cam.aperture_radius > 0:
        forward = np.subtract(cam.look_at, cam.position)
        sensor.update(aperture_radius=cam.aperture_radius,
                      focus_distance=cam.focus_distance or float(np.linalg.norm(forward)))
    out: dict[str, Any] = {"type": "scene", "integrator": {"type": integrator, "max_depth": -1}, "sensor": sensor}
    triangles = shape_triangles(scene, base_dir)
    for i, shape in enumerate(scene.shapes):
        entry: dict[str, Any]
        if isinstance(shape, Sphere):
            entry = {"type": "sphere", "center": list(shape.center), "radius": shape.radius}
        elif isinstance(shape, Quad):
            e1, e2 = np.array(shape.edge1), np.array(shape.edge2)
            n = np.cross(e1, e2)
            n /= np.linalg.norm(n)
            matrix = np.eye(4)
            matrix[:3, 0], matrix[:3, 1], matrix[:3, 2] = e1 / 2, e2 / 2, n
            matrix[:3, 3] = np.array(shape.corner) + (e1 + e2) / 2  # rectangle is [-1, 1]^2, normal +z
            entry = {"type": "rectangle", "to_world": T(matrix.tolist())}
        else:
            assert isinstance(shape, Mesh)
            tris = triangles[i]
            path = workdir / f"mesh{i}.obj"
            lines = [f"v {x} {y} {z}" for x, y, z in tris.reshape(-1, 3)]
            lines += [f"f {3 * k + 1} {3 * k + 2} {3 * k + 3}" for k in range(len(tris))]
            path.write_text("\n".join(lines) + "\n")
            entry = {"type": "obj", "filename": str(path), "face_normals": True}
        entry["bsdf"] = _bsdf(scene.materials[shape.material])
        if shape.emission is not None and max(shape.emission) > 0:
            entry["emitter"] = {"type": "area", "radiance": _rgb(shape.emission)}
        out[f"shape{i}"] = entry
    for i, light in enumerate(scene.lights):
        if isinstance(light, PointLight):
            out[f"light{i}"] = {"type": "point", "position": list(light.position),
                                "intensity": _rgb(np.array(light.power) / (4 * math.pi))}
        elif isinstance(light, SpotLight):
            axis = np.array(light.direction) / np.linalg.norm(light.direction)
            solid_angle = 2 * math.pi * (1 - math.cos(math.radians(light.cone_angle)))
            out[f"light{i}"] = {"type": "spot", "intensity": _rgb(np.array(light.power) / solid_angle),
                                "cutoff_angle": light.cone_angle, "beam_width": light.cone_angle * 0.9999,
                                "to_world": T().look_at(origin=list(light.position),
                                                        target=list(np.array(light.position) + axis),
                                                        up=list(_frame(axis)))}
        elif isinstance(light, DirectionalLight):
            out[f"light{i}"] = {"type": "directional", "direction": list(light.direction),
                                "irradiance": _rgb(light.irradiance)}
        else:
            assert isinstance(light, EnvironmentLight)
            out[f"light{i}"] = _environment(scene, light, base_dir)
    return out


def _environment(scene: Scene, light: EnvironmentLight, base_dir: Path) -> dict[str, Any]:
    """`constant`, or an `envmap` of the map's radiance (scale applied) as a bitmap."""
    mi = mitsuba()
    sky = env_map(scene, light, base_dir, base_dir)
    if sky.texels is None:
        return {"type": "constant", "radiance": _rgb(sky.radiance)}
    matrix = np.eye(4)
    matrix[:3, :3] = sky.to_world
    return {"type": "envmap", "bitmap": mi.Bitmap(sky.texels.astype(np.float32)),
            "to_world": mi.ScalarTransform4f(matrix.tolist())}


def render(scene: Scene, base_dir: Path, resolution: tuple[int, int], spp: int,
           integrator: Literal["path", "ptracer"], seed: int = 0) -> tuple[np.ndarray, float]:
    """(H, W, 3) linear image and the seconds the render took (scene loading excluded)."""
    mi = mitsuba()
    with tempfile.TemporaryDirectory() as tmp:
        loaded = mi.load_dict(scene_dict(scene, base_dir, resolution, spp, integrator, Path(tmp)))
        t0 = time.perf_counter()
        image = np.array(mi.render(loaded, spp=spp, seed=seed), dtype=np.float64)
        return image[..., :3], time.perf_counter() - t0
