"""A scene's image does not depend on its unit, nor on where it stands. The ray offset
(kernels/geometry.cl, ray_eps) is relative to the coordinates:
- it had a floor of 1 near the origin: the Cornell box built in metres at 5.5 cm had its rays
  leave surfaces 0.2% of its size off, and its corners came out 1-3% darker (10% at 5.5 mm).
  The floor is now the scene's own scale (at most 1), taken where rays start and land (a
  sphere's nearest point to the origin, not its bounds: smallppm at 1e-5 came out 1% dark);
- it was 1e-4 of the largest coordinate: the box moved 18 of its sizes away from the origin had
  its corners 2-3.5% darker (10% at 180 sizes). It is now 1e-5, still some 80 float32 ulps."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import image, render
from worker.scene import bundled_scene_path


def _scaled(name: str, scale: float) -> dict:
    """A bundled scene in another unit: every length times `scale`, a point light's power times
    scale^2 (the same irradiance at the scaled distances)."""
    scene = json.loads(bundled_scene_path(name).read_text())
    camera = scene["camera"]
    for key in ("position", "look_at"):
        camera[key] = [v * scale for v in camera[key]]
    if "near_clip" in camera:
        camera["near_clip"] *= scale
    for shape in scene["shapes"]:
        for key in ("corner", "edge1", "edge2", "center"):
            if key in shape:
                shape[key] = [v * scale for v in shape[key]]
        if "radius" in shape:
            shape["radius"] *= scale
    for light in scene["lights"]:
        light["position"] = [v * scale for v in light["position"]]
        light["power"] = [v * scale * scale for v in light["power"]]
    return scene


@pytest.mark.parametrize("name", ["cornell-box", "smallppm"])
@pytest.mark.parametrize("method", ["sppm", "bpt"])
def test_the_image_does_not_depend_on_the_scenes_unit(make_engine, tmp_path: Path, name: str, method: str) -> None:
    """The box given in millimetres, then in metres and in 100 m units; smallppm's room (its walls
    spheres of radius 1e5, which must not set the room's scale) likewise. Uniform photons: a
    chain's accept or reject turns on a visibility test, where a rounding difference sends
    it down another path."""
    images = {}
    for scale in (1.0, 1e-4, 1e-5):
        path = tmp_path / f"scene_{scale}.json"
        path.write_text(json.dumps(_scaled(name, scale)))
        eng = make_engine(path, resolution=(32, 32), photons_per_pass=1 << 14, seed=5, method=method,
                          sampler="uniform")
        images[scale] = image(eng, render(eng, 4)).mean(axis=-1)
    # The same seed traces the same paths up to rounding: the images agree far within their noise.
    # The lower corners (the bottom rows' ends) are where the offset showed.
    corners = np.s_[-4:, list(range(4)) + list(range(28, 32))]
    for scale in (1e-4, 1e-5):
        whole = images[scale].mean() / images[1.0].mean()
        corner = images[scale][corners].mean() / images[1.0][corners].mean()
        assert abs(whole - 1.0) < 2e-3 and abs(corner - 1.0) < 5e-3, (scale, whole, corner)


def _moved_cornell_box(offset: float) -> dict:
    scene = json.loads(bundled_scene_path("cornell-box").read_text())
    for key in ("position", "look_at"):
        scene["camera"][key] = [v + offset for v in scene["camera"][key]]
    for shape in scene["shapes"]:
        shape["corner"] = [v + offset for v in shape["corner"]]
    return scene


@pytest.mark.parametrize("method", ["sppm", "bpt"])
def test_the_image_does_not_depend_on_where_the_scene_stands(make_engine, tmp_path: Path, method: str) -> None:
    images = {}
    for offset in (0.0, 1e4):  # the box is 555 across
        path = tmp_path / f"box_{offset}.json"
        path.write_text(json.dumps(_moved_cornell_box(offset)))
        eng = make_engine(path, resolution=(64, 64), photons_per_pass=1 << 15, seed=5, method=method)
        images[offset] = image(eng, render(eng, 4)).mean(axis=-1)
    # Rounding at 1e4 is 18x that at 555: the paths part ways now and then, so the bound is the
    # images' noise rather than rounding. The corners: the box's lower ones, 4 pixels square.
    corners = np.s_[-4:, list(range(4)) + list(range(60, 64))]
    whole = images[1e4].mean() / images[0.0].mean()
    corner = images[1e4][corners].mean() / images[0.0][corners].mean()
    assert abs(whole - 1.0) < 2e-3 and abs(corner - 1.0) < 5e-3, (whole, corner)
