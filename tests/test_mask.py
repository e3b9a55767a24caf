"""Opacity (Mitsuba 3's mask) in every method: a surface of opacity a reflects a times its
material's light and passes the rest straight through. Checked cell by cell against the
closed form on point-plane's plane under a checkerboard of opacities (tests/analytic.py),
side by side with Mitsuba 3 on a room whose light falls through a cut-out panel, and in
Mitsuba XML as Mitsuba reads it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import image, render
from tests.helpers import PEER_BIAS, SENSOR, assert_matches_block_by_block, mitsuba_renders, room_shell, xml
from tests.test_images import write_image
from tests.test_materials import BALL, LE, PATHS, ball_radiance, furnace_scene
from tests.test_textures import METHODS, cells_and_closed_form, checker_plane
from worker.mitsuba_scene import convert_mitsuba
from worker.scene import SceneError, parse_scene

# Not ppm nor lt, for what they are, whatever the material: ppm traces its eye paths once, so
# each pixel keeps the part (the ball or what lies behind) its one path took, as for a
# plastic's coat; lt's connections to the camera are blocked by a surface in between, so it
# cannot see a diffuse surface through a mask, as through a glass (nor can Mitsuba's
# particle tracer).
ALBEDO = 0.8
# The checkerboard's two opacities: one number each, a colour's channel mean (Mitsuba's eval_1).
OPACITY0, OPACITY1 = (0.25, 0.25, 0.25), (0.9, 0.6, 0.3)


def masked_plane() -> dict:
    """point-plane whose plane (albedo ALBEDO) has a checkerboard of opacities: below it is
    nothing, so what passes through is lost."""
    data = checker_plane()
    checks = data["textures"]["checks"]
    checks["color0"], checks["color1"] = list(OPACITY0), list(OPACITY1)
    data["materials"]["plane"] = {"type": "diffuse", "albedo": [ALBEDO] * 3, "opacity": {"texture": "checks"}}
    return data


@pytest.mark.parametrize("method", METHODS)
def test_masked_plane_cell_by_cell(make_engine, tmp_path: Path, method: str) -> None:
    """Each whole cell's mean within 1% of ALBEDO times its opacity times the closed form,
    plus three standard errors of the mean from its pixels' scatter: an eye path takes the
    surface or passes through it by a coin flip, a noise the cell's pixels show one by one."""
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(masked_plane()))
    eng = make_engine(path, method=method, seed=12, photons_per_pass=1 << 17)
    ours = image(eng, render(eng, 256))
    cell_id, parity, white = cells_and_closed_form(eng)
    checked = 0
    for cell in np.unique(cell_id[cell_id >= 0]):
        inside = cell_id == cell
        if inside.sum() < 30:  # a cell cut by the image's border: too few pixels to judge 1%
            continue
        opacity = float(np.mean(OPACITY0 if parity[inside][0] == 0 else OPACITY1))
        ratio = ours[inside] / (ALBEDO * opacity * white[inside, None])
        error = np.abs(ratio.mean(axis=0) - 1.0)
        assert np.all(error <= 0.01 + 3.0 * ratio.std(axis=0) / np.sqrt(inside.sum())), (cell, error)
        checked += 1
    assert checked >= 30, checked


@pytest.mark.parametrize("method", METHODS)
def test_masked_ball_in_the_furnace(make_engine, tmp_path: Path, method: str) -> None:
    """A diffuse ball of albedo rho and opacity a among walls that emit Le and reflect nothing:
    Le arrives from every direction outside, so by symmetry the ball's inside leaves a uniform
    L_in = a rho L_in + (1 - a) Le, and the camera sees a rho Le + (1 - a) L_in, that is
    Le (a rho + (1 - a)^2 / (1 - a rho)); the image mean over the ball within 1%."""
    rho, a = np.array([0.7, 0.4, 0.2]), 0.5
    data = furnace_scene({"type": "diffuse", "albedo": rho.tolist(), "opacity": a})
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(data))
    radius = {"initial_radius": BALL / 30.0} if method == "vcm" else {}
    eng = make_engine(path, method=method, seed=13, photons_per_pass=PATHS, **radius)
    ours = image(eng, render(eng, 32))
    _, full = ball_radiance(eng, parse_scene(data).materials["ball"])
    np.testing.assert_allclose(ours[full].mean(axis=0), LE * (a * rho + (1 - a) ** 2 / (1 - a * rho)), rtol=0.01)


def test_opacity_out_of_range_names_the_field() -> None:
    data = masked_plane()
    data["materials"]["plane"]["opacity"] = 1.5
    with pytest.raises(SceneError) as err:
        parse_scene(data)
    assert err.value.field == "materials.plane.opacity", err.value


# ------------------------------------------------------------------ Mitsuba XML
def _bsdf(inner: str) -> str:
    return xml(f'{SENSOR}<bsdf type="mask" id="m">{inner}</bsdf><shape type="rectangle"><ref id="m"/></shape>')


@pytest.mark.parametrize(("inner", "opacity"), [
    ('<float name="opacity" value="0.3"/><bsdf type="diffuse"/>', 0.3),
    ('<rgb name="opacity" value="0.9, 0.6, 0.3"/><bsdf type="twosided"><bsdf type="diffuse"/></bsdf>', 0.6),
    ('<bsdf type="roughplastic"/>', 0.5),  # Mitsuba's default
])
def test_mask_imports_with_its_opacity(tmp_path: Path, inner: str, opacity: float) -> None:
    path = tmp_path / "mask.xml"
    path.write_text(_bsdf(inner))
    material = convert_mitsuba(path)["materials"]["m"]
    assert material["opacity"] == pytest.approx(opacity)


@pytest.mark.parametrize(("xml", "message"), [
    (_bsdf('<float name="opacity" value="1.5"/><bsdf type="diffuse"/>'), "opacity must lie in [0, 1]"),
    (_bsdf('<float name="opacity" value="0.5"/>'), "mask takes exactly one nested bsdf"),
    (_bsdf('<bsdf type="mask"><bsdf type="diffuse"/></bsdf>'), "a mask inside a mask"),
    (xml(f'{SENSOR}<bsdf type="twosided" id="t"><bsdf type="mask"><bsdf type="diffuse"/></bsdf></bsdf>'
         '<shape type="rectangle"><ref id="t"/></shape>'), "twosided takes an opaque bsdf"),
])
def test_bad_masks_are_refused_by_line(tmp_path: Path, xml: str, message: str) -> None:
    """What Mitsuba refuses too (an opacity outside [0, 1] aside, which it would not check)."""
    path = tmp_path / "mask.xml"
    path.write_text(xml)
    with pytest.raises(SceneError) as err:
        convert_mitsuba(path)
    assert message in str(err.value) and "line" in str(err.value), err.value


# ------------------------------------------------------------------ side by side with Mitsuba 3
ROOM = f"""<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="-1"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="60"/>
        <transform name="to_world"><lookat origin="0, 0.3, 0.95" target="0, -0.6, -0.3" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="48"/>
            <rfilter type="box"/></film>
    </sensor>
    <bsdf type="twosided" id="white"><bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf></bsdf>
    <bsdf type="mask" id="screen">
        <texture type="bitmap" name="opacity"><string name="filename" value="holes.png"/>
            <string name="filter_type" value="nearest"/></texture>
        <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.5, 0.3"/></bsdf></bsdf>
    </bsdf>
    <bsdf type="mask" id="veil">
        <float name="opacity" value="0.6"/>
        <bsdf type="twosided"><bsdf type="roughplastic"><rgb name="diffuse_reflectance" value="0.2, 0.4, 0.7"/>
            <float name="alpha" value="0.2"/></bsdf></bsdf>
    </bsdf>
    {room_shell("white")}
    <shape type="rectangle"><transform name="to_world"><scale x="0.6" y="0.6"/><rotate x="1" angle="-90"/>
        <translate y="0.2" z="-0.2"/></transform><ref id="screen"/></shape>
    <shape type="rectangle"><transform name="to_world"><scale x="0.3" y="0.5"/><rotate y="1" angle="30"/>
        <translate x="0.5" y="-0.5" z="-0.4"/></transform><ref id="veil"/></shape>
</scene>"""
SIDE_RUNS = 4  # independent renders a side: the spread of a block between them is its noise


def mask_room(folder: Path) -> Path:
    """ROOM with its opacity image beside it: an 8-bit grey 8 x 8 grid of holes (opacity 0)
    in a screen of opacity 1, and a row of half-open cells."""
    holes = np.full((8, 8), 255, np.uint8)
    holes[1::3, 1::3] = 0
    holes[6, :] = 128
    write_image(folder / "holes.png", holes[..., None], "uint8")
    path = folder / "room.xml"
    path.write_text(ROOM)
    return path


@pytest.fixture(scope="module")
def room_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("mask-room")
    mask_room(folder)
    return folder


@pytest.fixture(scope="module")
def mitsuba_room(room_folder: Path) -> np.ndarray:
    return mitsuba_renders(room_folder / "room.xml", SIDE_RUNS)


@pytest.mark.parametrize("method", METHODS)
def test_mask_room_matches_mitsuba_block_by_block(make_engine, room_folder: Path, mitsuba_room: np.ndarray,
                                                  method: str) -> None:
    """A screen with a bitmap of holes under the light and a half-clear rough plastic veil,
    by Mitsuba's path tracer and by us (32 passes), SIDE_RUNS renders each: image means per
    channel within 2%, every 8 x 8 block's luminance within 5 combined standard errors of the
    two means plus the method's PEER_BIAS (tests/helpers.py)."""
    ours = []
    for s in range(SIDE_RUNS):
        engine = make_engine(room_folder / "room.xml", method=method, seed=300 + s)
        ours.append(image(engine, render(engine, 32)))
    assert_matches_block_by_block(np.array(ours), mitsuba_room, 0.02, PEER_BIAS[method])
