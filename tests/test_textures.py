"""Textures in every method: a checkerboard on point-plane's plane gives, cell by cell, the
cell's albedo times the closed form (tests/analytic.py); texture lookups (wrap modes,
bilinear and nearest filtering, to_uv, checkerboards) and the shapes' texture coordinates
against Mitsuba 3's own, from one XML file; and texture references in our JSON checked like
every other field.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

from kernels.contract import build_options
from kernels.program import KERNEL_DIR, PREAMBLE, SOURCES
from tests.analytic import PLANE_H, PLANE_I, camera_rays
from tests.conftest import image, render
from tests.helpers import PEER_BIAS, assert_matches_block_by_block, mitsuba_renders, room_shell
from tests.test_images import write_image
from worker.mitsuba_scene import convert_mitsuba
from worker.scene import SceneError, bundled_scene_path, parse_scene
from worker.surfaces import used_textures

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


# ------------------------------------------------------------------ lookups against Mitsuba 3
PROBE = """
__kernel void probe_texture(SCENE_PARAMS, int tex, __global const float2* uv, __global float4* out) {
    int i = get_global_id(0);
    SceneGeom g = SCENE_GEOM;
    out[i] = (float4)(texture_eval(&g, tex, uv[i]), 0.0f);
}

__kernel void probe_uv(SCENE_PARAMS, __global const float4* origins, __global const float4* dirs,
                       __global float4* out) {
    int i = get_global_id(0);
    SceneGeom g = SCENE_GEOM;
    float3 o = origins[i].xyz, d = dirs[i].xyz;
    Hit h = intersect(&g, o, d);
    float2 uv = h.surf == SURF_NONE ? (float2)(0.0f) : prim_uv(&g, hit_prim(&h), o + h.t * d);
    out[i] = (float4)(uv, h.t, (float)h.surf);
}
"""
# Texture elements as Mitsuba reads them (by id in the scene below, alone for Mitsuba's own lookup).
TEXTURES = {
    "repeat": '<texture type="bitmap" id="repeat"><string name="filename" value="pattern.png"/>'
              '<transform name="to_uv"><scale x="2" y="3"/><rotate z="1" angle="30"/><translate x="0.3" y="-0.2"/>'
              '</transform></texture>',
    "mirror": '<texture type="bitmap" id="mirror"><string name="filename" value="pattern.png"/>'
              '<string name="wrap_mode" value="mirror"/><string name="filter_type" value="nearest"/>'
              '<transform name="to_uv"><scale value="3"/></transform></texture>',
    "clamp": '<texture type="bitmap" id="clamp"><string name="filename" value="pattern.png"/>'
             '<string name="wrap_mode" value="clamp"/><boolean name="raw" value="true"/>'
             '<transform name="to_uv"><scale value="2"/><translate x="-0.5" y="-0.5"/></transform></texture>',
    "checks": '<texture type="checkerboard" id="checks"><rgb name="color0" value="0.9, 0.6, 0.1"/>'
              '<rgb name="color1" value="0.1, 0.3, 0.8"/>'
              '<transform name="to_uv"><scale x="4" y="3"/><translate x="0.1"/></transform></texture>',
    "grey": '<texture type="bitmap" id="grey"><string name="filename" value="grey.png"/>'
            '<transform name="to_uv"><scale x="3" y="2"/></transform></texture>',
    "float": '<texture type="bitmap" id="float"><string name="filename" value="float.exr"/>'
             '<string name="wrap_mode" value="mirror"/>'
             '<transform name="to_uv"><scale value="2"/></transform></texture>',
    "float_grey": '<texture type="bitmap" id="float_grey"><string name="filename" value="float_grey.exr"/>'
                  '<string name="wrap_mode" value="clamp"/><string name="filter_type" value="nearest"/></texture>',
}
# The images beside it: every storage our texels have (kernels/textures.cl): 8-bit rgb and grey,
# half floats from half-float rgb and single-float grey.
IMAGES = {"pattern.png": ((5, 7, 3), "uint8"), "grey.png": ((6, 9, 1), "uint8"),
          "float.exr": ((7, 6, 3), "half"), "float_grey.exr": ((5, 5, 1), "float")}
TEXTURED_SCENE = """<scene version="3.0.0">
    <sensor type="perspective"><transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/>
        </transform><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
    </sensor>
    {textures}
    <bsdf type="diffuse" id="a"><ref name="reflectance" id="repeat"/></bsdf>
    <bsdf type="plastic" id="b"><ref name="diffuse_reflectance" id="mirror"/></bsdf>
    <bsdf type="diffuse" id="c"><ref name="reflectance" id="clamp"/></bsdf>
    <bsdf type="roughconductor" id="d"><ref name="specular_reflectance" id="checks"/></bsdf>
    <bsdf type="diffuse" id="e"><ref name="reflectance" id="grey"/></bsdf>
    <bsdf type="plastic" id="f"><ref name="diffuse_reflectance" id="float"/></bsdf>
    <bsdf type="roughconductor" id="g"><ref name="alpha" id="float_grey"/></bsdf>
    <shape type="rectangle"><transform name="to_world"><translate x="-1.2" y="1.2"/></transform><ref id="a"/></shape>
    <shape type="rectangle"><transform name="to_world"><rotate z="1" angle="30"/><translate x="1.2" y="1.2"/>
        </transform><boolean name="flip_normals" value="true"/><ref id="c"/></shape>
    <shape type="sphere"><point name="center" x="-1.2" y="-1.2" z="0"/><float name="radius" value="0.9"/>
        <ref id="b"/></shape>
    <shape type="obj"><string name="filename" value="quad.obj"/>
        <transform name="to_world"><translate x="1.2" y="-1.2"/></transform><ref id="d"/></shape>
</scene>"""
# Two triangles with their own texture coordinates (not a quad's (s, t)).
QUAD_OBJ = """v -1 -1 0
v 1 -1 0.2
v 1 1 0
v -1 1 -0.2
vt 0.1 0.2
vt 0.9 0.1
vt 0.7 0.8
vt 0.2 0.95
f 1/1 2/2 3/3
f 1/1 3/3 4/4
"""


@pytest.fixture()
def mi():
    import mitsuba

    mitsuba.set_variant("scalar_rgb")
    mitsuba.set_log_level(mitsuba.LogLevel.Error)
    return mitsuba


def textured_scene(folder: Path) -> Path:
    """TEXTURED_SCENE with its IMAGES (random values: integer ones sRGB-encoded, float ones
    linear in [0, 1]) and its mesh beside it."""
    rng = np.random.default_rng(3)
    for name, (shape, sample) in IMAGES.items():
        values = rng.random(shape)
        write_image(folder / name, (values * 255).astype(np.uint8) if sample == "uint8" else values.astype(np.float32),
                    sample)
    (folder / "quad.obj").write_text(QUAD_OBJ)
    path = folder / "textured.xml"
    path.write_text(TEXTURED_SCENE.format(textures="\n    ".join(TEXTURES.values())))
    return path


def _probe(eng) -> cl.Program:
    source = PREAMBLE + "\n".join((KERNEL_DIR / name).read_text() for name in SOURCES) + PROBE
    return cl.Program(eng.device.ctx, source).build(options=["-cl-mad-enable", *build_options(eng.integrator.sums)])


def _probe_uvs(eng, seed: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n rays from the plane z = 5 over [-2.3, 2.3]^2, nearly straight down -z: their origins,
    directions and, per ray, our hit's (u, v, t, surface) (surface -1: a miss)."""
    dev, program = eng.device, _probe(eng)
    rng = np.random.default_rng(seed)
    origins = np.column_stack([rng.uniform(-2.3, 2.3, (n, 2)), np.full(n, 5.0), np.zeros(n)]).astype(np.float32)
    dirs = np.column_stack([rng.uniform(-0.05, 0.05, (n, 2)), -np.ones(n), np.zeros(n)])
    dirs[:, :3] /= np.linalg.norm(dirs[:, :3], axis=1, keepdims=True)
    dirs = dirs.astype(np.float32)
    ours = np.empty((n, 4), np.float32)
    out = dev.buffer(ours.nbytes)
    program.probe_uv(dev.queue, (n,), None, *dev.geometry, *dev.emitter_args, dev.const(origins), dev.const(dirs), out)
    cl.enqueue_copy(dev.queue, ours, out)
    return origins, dirs, ours


def test_lookups_match_mitsuba(make_engine, mi, tmp_path: Path) -> None:
    """Each texture (wrap modes, filters, to_uv with a rotation, raw, checkerboard) at random (u, v) in [-2, 3]^2,
    ours against Mitsuba's own `eval` of the same element."""
    eng = make_engine(textured_scene(tmp_path), photons_per_pass=1 << 10)
    dev, probe = eng.device, cl.Kernel(_probe(eng), "probe_texture")
    uv = np.random.default_rng(4).uniform(-2.0, 3.0, (512, 2)).astype(np.float32)
    order = used_textures(parse_scene(convert_mitsuba(tmp_path / "textured.xml")))
    for name, element in TEXTURES.items():
        alone = element
        for image_name in IMAGES:
            alone = alone.replace(f'"{image_name}"', f'"{tmp_path / image_name}"')
        texture = mi.load_string(alone.replace("<texture ", '<texture version="3.0.0" ', 1))
        si = mi.SurfaceInteraction3f()
        theirs = []
        for u, v in uv:
            si.uv = mi.Point2f(float(u), float(v))
            theirs.append(list(texture.eval(si)))
        ours = np.empty((len(uv), 4), np.float32)
        out = dev.buffer(ours.nbytes)
        probe(dev.queue, (len(uv),), None, *dev.geometry, *dev.emitter_args,
              np.int32(order.index(name)), dev.const(uv), out)
        cl.enqueue_copy(dev.queue, ours, out)
        # Our texels are half floats: each within 2^-12 of its value, a part in 4096.
        np.testing.assert_allclose(ours[:, :3], np.array(theirs), rtol=1e-3, atol=1e-5, err_msg=name)


def test_surface_uvs_match_mitsuba(make_engine, mi, tmp_path: Path) -> None:
    """Rays at the four shapes (a rectangle, a flipped and turned rectangle, a sphere, an OBJ
    mesh with its own texture coordinates): the (u, v) at our hit is Mitsuba's at its hit."""
    path = textured_scene(tmp_path)
    n = 2000
    origins, dirs, ours = _probe_uvs(make_engine(path, photons_per_pass=1 << 10), 5, n)
    scene = mi.load_file(str(path))
    hits = 0
    for i in range(n):
        ray = mi.Ray3f(mi.Point3f(*map(float, origins[i, :3])), mi.Vector3f(*map(float, dirs[i, :3])))
        si = scene.ray_intersect(ray)
        if not si.is_valid():
            assert ours[i, 3] < 0, i
            continue
        hits += 1
        assert abs(ours[i, 2] - si.t) < 1e-4, (i, ours[i], si.t)
        u, v = si.uv
        np.testing.assert_allclose(ours[i, :2], [u, v], atol=2e-5, err_msg=str(i))
    assert hits > n // 2, hits


SHAPES_SCENE = """<scene version="3.0.0">
    <sensor type="perspective"><transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/>
        </transform><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
    </sensor>
    <bsdf type="diffuse" id="a"><texture type="checkerboard" name="reflectance"/></bsdf>
    <shape type="cube"><transform name="to_world"><scale value="0.6"/><rotate x="0.6" y="0.8" angle="35"/>
        <translate x="-1.2" y="1.2"/></transform><ref id="a"/></shape>
    <shape type="disk"><transform name="to_world"><scale value="0.9"/><rotate y="1" angle="-20"/>
        <translate x="1.2" y="1.2"/></transform><ref id="a"/></shape>
    <shape type="cylinder"><point name="p0" x="-1.8" y="-1.5" z="-0.3"/><point name="p1" x="-0.6" y="-0.9" z="0.2"/>
        <float name="radius" value="0.4"/><ref id="a"/></shape>
    <shape type="cylinder"><transform name="to_world"><scale x="0.5" y="0.5" z="1.2"/><rotate x="1" angle="-70"/>
        <translate x="1.2" y="-1.5"/></transform><ref id="a"/></shape>
</scene>"""


def test_generated_shapes_uvs_match_mitsuba(make_engine, mi, tmp_path: Path) -> None:
    """A cube, a disk and two cylinders (one by p0 and p1), each turned: the (u, v) at our hit
    is Mitsuba's at its hit, within a part in 500 (a disk's fan and a cylinder's tube are
    tessellated: between a fan's edges near the centre the angle is interpolated linearly),
    modulo 1 at the seams where phi wraps."""
    path = tmp_path / "shapes.xml"
    path.write_text(SHAPES_SCENE)
    n = 3000
    origins, dirs, ours = _probe_uvs(make_engine(path, photons_per_pass=1 << 10), 6, n)
    scene = mi.load_file(str(path))
    hits: dict[int, int] = {}
    for i in range(n):
        ray = mi.Ray3f(mi.Point3f(*map(float, origins[i, :3])), mi.Vector3f(*map(float, dirs[i, :3])))
        si = scene.ray_intersect(ray)
        if not si.is_valid() or abs(ours[i, 2] - si.t) > 2e-3:  # a tessellated rim: one hits, the other not
            continue
        hits[int(ours[i, 3])] = hits.get(int(ours[i, 3]), 0) + 1
        gap = np.abs(ours[i, :2] - np.array(si.uv))
        assert np.all(np.minimum(gap, 1.0 - gap) < 2e-3), (i, ours[i], si.uv)
    assert len(hits) == 4 and min(hits.values()) > 100, hits  # every shape, often


# ------------------------------------------------------------------ side by side with Mitsuba 3
ROOM = f"""<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="-1"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="62"/>
        <transform name="to_world"><lookat origin="0, 0.1, 0.95" target="0, -0.45, -0.6" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="64"/>
            <rfilter type="box"/></film>
    </sensor>
    <texture type="bitmap" id="tiles"><string name="filename" value="tiles.png"/>
        <transform name="to_uv"><scale value="3"/></transform></texture>
    <bsdf type="twosided" id="white"><bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf></bsdf>
    <bsdf type="diffuse" id="floor"><ref name="reflectance" id="tiles"/></bsdf>
    <bsdf type="plastic" id="ball">
        <texture type="checkerboard" name="diffuse_reflectance"><rgb name="color0" value="0.8, 0.7, 0.1"/>
            <rgb name="color1" value="0.1, 0.2, 0.7"/>
            <transform name="to_uv"><scale x="8" y="4"/></transform></texture>
        <float name="int_ior" value="1.5"/>
    </bsdf>
    <bsdf type="twosided" id="panel"><bsdf type="diffuse">  <!-- its back is lit: twosided, as ours -->
        <texture type="bitmap" name="reflectance"><string name="filename" value="tiles.png"/>
            <string name="filter_type" value="nearest"/><string name="wrap_mode" value="mirror"/></texture>
    </bsdf></bsdf>
    {room_shell("floor")}
    <shape type="sphere"><point name="center" x="-0.45" y="-0.68" z="-0.4"/><float name="radius" value="0.32"/>
        <ref id="ball"/></shape>
    <shape type="obj"><string name="filename" value="panel.obj"/>
        <transform name="to_world"><scale value="0.35"/><rotate y="1" angle="-25"/>
            <translate x="0.45" y="-0.62" z="-0.55"/></transform><ref id="panel"/></shape>
</scene>"""


def textured_room(folder: Path) -> Path:
    """ROOM with its image (a 4 x 4 sRGB tiling of random colours, a white grout line in
    each tile) and its mesh (QUAD_OBJ: texture coordinates of its own) beside it."""
    rng = np.random.default_rng(8)
    tiles = np.repeat(np.repeat(rng.random((4, 4, 3)) * 0.9, 8, axis=0), 8, axis=1)
    tiles[::8, :] = tiles[:, ::8] = 0.95
    write_image(folder / "tiles.png", (tiles * 255).round().astype(np.uint8), "uint8")
    (folder / "panel.obj").write_text(QUAD_OBJ)
    path = folder / "room.xml"
    path.write_text(ROOM)
    return path


SIDE_RUNS = 4  # independent renders a side: the spread of a block between them is its noise


@pytest.fixture(scope="module")
def room_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("textured-room")
    textured_room(folder)
    return folder


@pytest.fixture(scope="module")
def mitsuba_room(room_folder: Path) -> np.ndarray:
    return mitsuba_renders(room_folder / "room.xml", SIDE_RUNS)


@pytest.mark.parametrize("method", METHODS)
def test_textured_room_matches_mitsuba_block_by_block(make_engine, room_folder: Path, mitsuba_room: np.ndarray,
                                                      method: str) -> None:
    """A room with a bitmap-textured floor (bilinear, repeated), a plastic ball with a
    checkerboard diffuse base and an OBJ panel with its own texture coordinates (nearest,
    mirrored), by Mitsuba's path tracer and by us (32 passes), SIDE_RUNS renders each: image
    means per channel within 2%, every 8 x 8 block's luminance within 5 combined standard
    errors of the two means plus the method's PEER_BIAS (tests/helpers.py)."""
    ours = []
    for s in range(SIDE_RUNS):
        engine = make_engine(room_folder / "room.xml", method=method, seed=200 + s)
        ours.append(image(engine, render(engine, 32)))
    assert_matches_block_by_block(np.array(ours), mitsuba_room, 0.02, PEER_BIAS[method])


def test_client_sends_a_scenes_images(tmp_path: Path) -> None:
    """`photonfarm submit` uploads the images beside a scene, as its meshes (the service reads
    only what the scene names, inside the upload)."""
    from service.client import scene_folder_files

    write_image(tmp_path / "wood.png", np.zeros((2, 2, 3), np.uint8), "uint8")
    scene = checker_plane()
    scene["textures"]["wood"] = {"type": "bitmap", "file": "wood.png"}
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    assert [name for name, _ in scene_folder_files(tmp_path / "scene.json")] == ["scene.json", "wood.png"]
