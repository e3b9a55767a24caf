"""Images in scenes: files read with OpenImageIO and carried inline, exactly; sRGB decoding;
every bad file or inline image a SceneError naming the texture, never a traceback."""

from __future__ import annotations

import base64
import json
import zlib
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from worker.images import Pixels
from worker.scene import LoadBudget, SceneError, SceneLimitError, bundled_scene_path, load_any_scene, parse_scene


def write_image(path: Path, pixels: np.ndarray, sample: str) -> None:
    out = oiio.ImageOutput.create(str(path))
    height, width, channels = pixels.shape
    assert out.open(str(path), oiio.ImageSpec(width, height, channels, sample))
    assert out.write_image(pixels)
    out.close()


def scene_with_textures(folder: Path, textures: dict) -> Path:
    scene = json.loads(bundled_scene_path("point-plane").read_text())
    scene["textures"] = textures
    path = folder / "scene.json"
    path.write_text(json.dumps(scene))
    return path


def test_files_inline_exactly_and_decode(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    png = (rng.random((5, 7, 3)) * 255).astype(np.uint8)
    exr = rng.random((4, 8, 3)).astype(np.float16)
    write_image(tmp_path / "albedo.png", png, "uint8")
    write_image(tmp_path / "sky.exr", exr, "half")
    path = scene_with_textures(tmp_path, {"albedo": {"type": "bitmap", "file": "albedo.png"},
                                          "sky": {"type": "bitmap", "file": "sky.exr"}})
    scene, _ = load_any_scene(path)
    albedo, sky = scene.textures["albedo"].pixels, scene.textures["sky"].pixels
    assert albedo is not None and sky is not None
    assert albedo.sample == "uint8" and np.array_equal(albedo.array, png)
    assert sky.sample == "float16" and np.array_equal(sky.array, exr)
    # sRGB (IEC 61966-2-1) unless raw; float images are linear as stored.
    v = png / 255.0
    srgb = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    assert np.allclose(albedo.linear(), srgb, rtol=1e-5, atol=1e-7)
    assert np.allclose(albedo.linear(raw=True), v, rtol=1e-6)
    assert np.array_equal(sky.linear(), exr.astype(np.float32))
    # The inline form survives the job's JSON and a second parse unchanged.
    again = parse_scene(json.loads(scene.model_dump_json()))
    assert np.array_equal(again.textures["albedo"].pixels.array, png)


@pytest.mark.parametrize(("texture", "message"), [
    ({"type": "bitmap", "file": "../outside.png"}, "leaves the scene's directory"),
    ({"type": "bitmap", "file": "missing.png"}, "not found"),
    ({"type": "bitmap", "file": "scene.json"}, "is not one of"),
    ({"type": "bitmap", "file": "garbage.png"}, "garbage.png"),
    ({"type": "bitmap"}, "give either file or pixels"),
    ({"type": "bitmap", "pixels": {"width": 2, "height": 2, "channels": 3, "sample": "uint8", "data": "AAAA"}},
     "not base64 of zlib"),
])
def test_bad_images_name_the_texture(tmp_path: Path, texture: dict, message: str) -> None:
    (tmp_path / "garbage.png").write_bytes(b"not an image")
    with pytest.raises(SceneError) as err:
        load_any_scene(scene_with_textures(tmp_path, {"wood": texture}))
    assert err.value.field.startswith("textures.wood") and message in err.value.message


def test_inline_pixels_hold_what_they_declare() -> None:
    good = Pixels.of(np.zeros((2, 3, 1), np.float32)).model_dump()
    short = Pixels.of(np.zeros((2, 2, 1), np.float32)).model_dump() | {"width": 3}
    nan = good | {"data": base64.b64encode(zlib.compress(np.full(6, np.nan, "<f4").tobytes())).decode()}
    assert Pixels.model_validate(good).array.shape == (2, 3, 1)
    for bad, message in ((short, "does not hold"), (nan, "not finite")):
        with pytest.raises(ValueError, match=message):
            Pixels.model_validate(bad)


def test_declared_size_counts_before_decoding(tmp_path: Path) -> None:
    write_image(tmp_path / "big.png", np.zeros((64, 64, 3), np.uint8), "uint8")
    path = scene_with_textures(tmp_path, {"big": {"type": "bitmap", "file": "big.png"}})
    budget = LoadBudget()
    budget.used["texels"] = budget.used["texels"] + (1 << 26) - 64 * 64 * 3 + 1
    with pytest.raises(SceneLimitError) as err:
        load_any_scene(path, budget=budget)
    assert err.value.field == "textures.big.file" and "texels" in err.value.message
