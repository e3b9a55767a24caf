"""Textures in every method: a checkerboard on point-plane's plane gives, cell by cell, the
cell's albedo times the closed form (tests/analytic.py); texture lookups (wrap modes,
bilinear and nearest filtering, the shapes' UVs) against the same arithmetic in NumPy; and
texture references in our JSON checked like every other field.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tests.analytic import PLANE_H, PLANE_I, camera_rays
from tests.conftest import image, render
from worker.scene import SceneError, bundled_scene_path, parse_scene

METHODS = ("sppm", "vcm", "bpt")
COLOR0, COLOR1 = (0.8, 0.5, 0.2), (0.15, 0.35, 0.7)
CELLS_PER_UNIT = 2.0  # checker cells a unit of length on the plane (cells of 0.5 x 0.5)


def checker_plane() -> dict:
    """point-plane with its plane a checkerboard of COLOR0 and COLOR1: the quad's (s, t) run
    along z and x over 20 units, so to_uv scales them by 20 CELLS_PER_UNIT."""
    data = json.loads(bundled_scene_path("point-plane").read_text())
    k = 20.0 * CELLS_PER_UNIT
    data["textures"] = {"checks": {"type": "checkerboard", "color0": list(COLOR0), "color1": list(COLOR1),
                                   "to_uv": [[k, 0.0, 0.0], [0.0, k, 0.0]]}}
    data["materials"]["plane"] = {"type": "diffuse", "albedo": {"texture": "checks"}}
    data["camera"]["resolution"] = [48, 48]
    return data


def cell_index(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The checker cell of plane points, (row, column): the quad's corner is (-10, 0, -10), so
    s = (z + 10) / 20 and t = (x + 10) / 20."""
    return np.floor((z + 10.0) * CELLS_PER_UNIT), np.floor((x + 10.0) * CELLS_PER_UNIT)


def cells_and_closed_form(eng, sub: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel: its checker cell (row * 1000 + column) and parity, both -1 where its
    footprint straddles a cell edge (the camera looks straight down: a pixel's footprint is
    the rectangle between its corners' points), and the closed form I h / (pi d^3) of a white
    plane averaged over the pixel."""
    cam = eng.arrays.camera.astype(np.float64)
    w, h = eng.arrays.width, eng.arrays.height
    sx, sy = 2.0 * np.arange(w + 1) / w - 1.0, 1.0 - 2.0 * np.arange(h + 1) / h
    d = cam[1, :3] + sx[None, :, None] * cam[2, :3] + sy[:, None, None] * cam[3, :3]
    corner = cam[0, :3] + (-cam[0, 1] / d[..., 1])[..., None] * d
    row, col = cell_index(corner[..., 0], corner[..., 2])
    cell = row * 1000 + col
    quads = np.stack([cell[:-1, :-1], cell[1:, :-1], cell[:-1, 1:], cell[1:, 1:]])
    whole = quads.min(axis=0) == quads.max(axis=0)
    cell, parity = np.where(whole, quads[0], -1), np.where(whole, (row + col)[:-1, :-1] % 2, -1)
    o, rays = camera_rays(eng, sub)
    p = o + (-o[1] / rays[..., 1])[..., None] * rays
    d2 = PLANE_H ** 2 + p[..., 0] ** 2 + p[..., 2] ** 2
    white = PLANE_I * PLANE_H / (math.pi * d2 ** 1.5)
    return cell, parity, white.reshape(h, sub, w, sub).mean(axis=(1, 3))


@pytest.mark.parametrize("method", METHODS)
def test_checker_plane_cell_by_cell(make_engine, tmp_path: Path, method: str) -> None:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(checker_plane()))
    eng = make_engine(path, method=method, seed=11, photons_per_pass=1 << 17)
    ours = image(eng, render(eng, 256))
    cell_id, parity, white = cells_and_closed_form(eng)
    checked = 0
    for cell in np.unique(cell_id[cell_id >= 0]):
        inside = cell_id == cell
        if inside.sum() < 30:  # a cell cut by the image's border: too few pixels to judge 1%
            continue
        albedo = np.array(COLOR0 if parity[inside][0] == 0 else COLOR1)
        expected = albedo * white[inside].mean()
        got = ours[inside].mean(axis=0)
        np.testing.assert_allclose(got, expected, rtol=0.01, err_msg=f"cell {cell}")
        checked += 1
    assert checked >= 30, checked


def test_unknown_texture_names_the_field() -> None:
    data = checker_plane()
    data["materials"]["plane"]["albedo"] = {"texture": "wood"}
    with pytest.raises(SceneError) as err:
        parse_scene(data)
    assert err.value.field == "materials.plane.albedo.texture" and "'wood'" in err.value.message


@pytest.mark.parametrize(("albedo", "field"), [
    ({"texture": "checks", "scale": 2}, "materials.plane.albedo.scale"),
    ({}, "materials.plane.albedo.texture"),
    ([0.5, 0.5, 2.0], "materials.plane.albedo.2"),
])
def test_bad_colour_names_the_field(albedo: object, field: str) -> None:
    data = checker_plane()
    data["materials"]["plane"]["albedo"] = albedo
    with pytest.raises(SceneError) as err:
        parse_scene(data)
    assert err.value.field == field, err.value
