"""Scenes users already have: Mitsuba 3 XML (worker/mitsuba_scene.py), OBJ and PLY meshes
(worker/meshes.py) and their smooth shading normals.

The three scenes under scenes/mitsuba/ are rendered by our engine and by Mitsuba 3 itself
(`scalar_rgb`, its `path` integrator) from the same file; where both converge their image
means agree within 2%. Each bad scene file gives one SceneError naming what is wrong.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.mitsuba_peer import beckmann_alpha
from tests.conftest import image, render
from tests.helpers import SENSOR, assert_matches_block_by_block, mitsuba_renders, xml
from worker.engine import Engine
from worker.error_estimate import LUMINANCE
from worker.meshes import MeshError, load_mesh
from worker.mitsuba_scene import Node, convert_mitsuba, look_at, to_world_matrix
from worker.scene import (
    SCENES_DIR,
    LoadBudget,
    SceneError,
    load_any_scene,
    parse_scene,
    shape_geometry,
)
from worker.scene_arrays import compile_scene
from worker.settings import Settings

MITSUBA_SCENES = SCENES_DIR / "mitsuba"


@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("scalar_rgb")
    mitsuba.set_log_level(mitsuba.LogLevel.Warn)
    return mitsuba


def convert(tmp_path: Path, body: str, params: dict | None = None, name: str = "scene.xml") -> dict:
    path = tmp_path / name
    path.write_text(xml(SENSOR + "\n" + body))
    return convert_mitsuba(path, params)


def convert_error(tmp_path: Path, body: str, with_sensor: bool = True, root: Path | None = None) -> SceneError:
    path = tmp_path / "scene.xml"
    path.write_text(xml((SENSOR + "\n" if with_sensor else "") + body))
    with pytest.raises(SceneError) as info:
        convert_mitsuba(path, root=root)
    return info.value


def line_of(path: Path, needle: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if needle in line)


# ----------------------------------------------------------- against Mitsuba itself
@pytest.mark.parametrize("name", ["ply-mesh", "obj-mesh", "thinlens-glossy"])
def test_matches_mitsuba(make_engine, mi, name: str) -> None:
    """Same file, two renderers. Image means: budgets where both have converged to well
    under 2% here (measured: within 0.2%, 1.4% and 1.0% of Mitsuba; the rest is SPPM's
    finite-radius bias at concave edges and Mitsuba's noise). Pixels: a mean cannot see a
    mirrored camera or a misplaced object, so the per-pixel difference (luminance, L1 over
    the image, relative to the mean; 6%, 6% and 18% here, mostly noise) must be under half
    of what it is against the same image mirrored (9% to 24% left-right, more top-bottom)."""
    path = MITSUBA_SCENES / f"{name}.xml"
    peer = np.array(mi.render(mi.load_file(str(path)), spp=256, seed=1), dtype=np.float64)[..., :3]
    engine = make_engine(path, photons_per_pass=1 << 16, seed=1)
    ours = image(engine, render(engine, 32))
    assert ours.shape == peer.shape
    np.testing.assert_allclose(ours.mean(axis=(0, 1)), peer.mean(axis=(0, 1)), rtol=0.02)

    lum_ours, lum_peer = ours @ LUMINANCE, peer @ LUMINANCE

    def l1(a: np.ndarray) -> float:
        return float(np.mean(np.abs(a - lum_peer)) / np.mean(lum_peer))

    assert l1(lum_ours) < 0.5 * min(l1(lum_ours[:, ::-1]), l1(lum_ours[::-1])), \
        (l1(lum_ours), l1(lum_ours[:, ::-1]), l1(lum_ours[::-1]))


THIN_LENS_RUNS = 4
THIN_LENS = {"aperture": "0.1", "focus": "0.6", "resolution": "64"}  # a wide lens focused short of everything


@pytest.fixture(scope="module")
def mitsuba_thin_lens() -> np.ndarray:
    return mitsuba_renders(MITSUBA_SCENES / "thinlens-glossy.xml", THIN_LENS_RUNS, **THIN_LENS)


@pytest.mark.parametrize("method", ["sppm", "vcm", "bpt", "lt"])
def test_thin_lens_in_every_method_matches_mitsuba(ctx, mitsuba_thin_lens: np.ndarray, method: str) -> None:
    """thinlens-glossy with a wide lens focused short of everything, the sphere blurred: camera
    paths leave from the lens and light tracing projects through it. Image means within 1% of
    Mitsuba's per channel, and every 8 x 8 block's luminance within 5 combined standard errors
    of the two means plus 3% of the block (the photon methods' radius at the sphere's contact);
    a pinhole in its place fails the blocks."""
    scene, base = load_any_scene(MITSUBA_SCENES / "thinlens-glossy.xml", THIN_LENS)
    ours = []
    for s in range(THIN_LENS_RUNS):
        engine = Engine(scene, base, Settings(method=method, seed=40 + s), ctx=ctx)
        ours.append(image(engine, render(engine, 256 if method == "lt" else 64)))  # lt: the noisiest
    mine = np.array(ours)
    assert_matches_block_by_block(mine, mitsuba_thin_lens, 0.01, 0.03)


def test_scenes_use_what_they_claim() -> None:
    """The three scenes hold what they are there to test."""
    ply = parse_scene(convert_mitsuba(MITSUBA_SCENES / "ply-mesh.xml"))
    assert any(getattr(s, "normals", None) is not None for s in ply.shapes), "PLY mesh carries its vertex normals"
    obj = convert_mitsuba(MITSUBA_SCENES / "obj-mesh.xml")
    assert {light["type"] for light in obj["lights"]} == {"point", "spot", "directional"}
    glossy = convert_mitsuba(MITSUBA_SCENES / "thinlens-glossy.xml")
    assert glossy["camera"]["aperture_radius"] > 0
    assert any(m["type"] == "rough_conductor" for m in glossy["materials"].values())
    assert (MITSUBA_SCENES / "meshes" / "icosphere.ply").read_bytes().startswith(b"ply\nformat binary_little_endian")
    for data in (obj, glossy):  # what `photonfarm convert` writes is plain JSON that reads back
        assert parse_scene(json.loads(json.dumps(data))) == parse_scene(data)


# ----------------------------------------------------------- transforms against numpy
def transform_node(ops: str) -> Node:
    """Parse <transform>ops</transform> with the converter's own reader."""
    import tempfile

    from worker.mitsuba_scene import _read_xml

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "t.xml"
        path.write_text(f'<transform name="to_world">{ops}</transform>')
        return _read_xml(path, LoadBudget())


def test_translate() -> None:
    expected = np.eye(4)
    expected[:3, 3] = [1.0, -2.0, 0.5]
    np.testing.assert_allclose(to_world_matrix(transform_node('<translate x="1" y="-2" z="0.5"/>')), expected)
    np.testing.assert_allclose(to_world_matrix(transform_node('<translate value="1, -2, 0.5"/>')), expected)


def test_scale() -> None:
    np.testing.assert_allclose(to_world_matrix(transform_node('<scale value="2"/>')), np.diag([2.0, 2, 2, 1]))
    np.testing.assert_allclose(to_world_matrix(transform_node('<scale x="2" z="3"/>')), np.diag([2.0, 1, 3, 1]))


@pytest.mark.parametrize("axis, angle", [((0, 1, 0), 90.0), ((0.6, 0.8, 0), -30.0), ((0.48, -0.6, 0.64), 137.0)])
def test_rotate(axis: tuple, angle: float) -> None:
    expected = np.eye(4)
    expected[:3, :3] = Rotation.from_rotvec(np.radians(angle) * np.array(axis) / np.linalg.norm(axis)).as_matrix()
    node = transform_node(f'<rotate x="{axis[0]}" y="{axis[1]}" z="{axis[2]}" angle="{angle}"/>')
    np.testing.assert_allclose(to_world_matrix(node), expected, atol=1e-12)


def test_rotation_axis_must_be_unit() -> None:
    """Mitsuba does not normalise the axis (its matrix is then no rotation): refused."""
    with pytest.raises(SceneError, match="unit length"):
        to_world_matrix(transform_node('<rotate x="1" y="1" angle="30"/>'))


def test_matrix_is_row_by_row() -> None:
    values = np.arange(16.0).reshape(4, 4)
    values[3] = [0, 0, 0, 1]
    text = " ".join(str(v) for v in values.ravel())
    np.testing.assert_allclose(to_world_matrix(transform_node(f'<matrix value="{text}"/>')), values)


def test_lookat_maps_local_axes() -> None:
    """+z looks at the target, +y is the up vector made orthogonal, +x is to the left."""
    origin, target, up = np.array([1.0, 2, 3]), np.array([0.0, 0, -1]), np.array([0.0, 1, 0])
    m = to_world_matrix(transform_node('<lookat origin="1, 2, 3" target="0, 0, -1" up="0, 1, 0"/>'))
    d = (target - origin) / np.linalg.norm(target - origin)
    np.testing.assert_allclose(m[:3, 3], origin)
    np.testing.assert_allclose(m[:3, 2], d)
    assert abs(m[:3, 1] @ d) < 1e-12 and m[:3, 1] @ up > 0
    np.testing.assert_allclose(np.cross(m[:3, 1], m[:3, 2]), m[:3, 0], atol=1e-12)  # right-handed: left = up x dir
    np.testing.assert_allclose(m, look_at(origin, target, up))


def test_operations_compose_in_order() -> None:
    """Each operation applies after the ones before it: M = R S T for translate, scale, rotate."""
    m = to_world_matrix(transform_node('<translate x="1"/><scale value="2"/><rotate y="1" angle="90"/>'))
    t, s, r = np.eye(4), np.diag([2.0, 2, 2, 1]), np.eye(4)
    t[0, 3] = 1.0
    r[:3, :3] = Rotation.from_rotvec([0, math.pi / 2, 0]).as_matrix()
    np.testing.assert_allclose(m, r @ s @ t, atol=1e-12)


def test_composition_matches_mitsuba(mi) -> None:
    ops = '<translate x="1" y="0.5"/><scale x="2" y="1" z="0.5"/><rotate x="0.48" y="-0.6" z="0.64" angle="40"/>' \
          '<lookat origin="0, 1, 2" target="1, 0, 0" up="0, 0, 1"/><matrix value="1 0 0 0 0 1 0 3 0 0 1 0 0 0 0 1"/>'
    scene = mi.load_string(xml(f'<shape type="rectangle"><transform name="to_world">{ops}</transform></shape>'))
    theirs = np.array(mi.traverse(scene.shapes()[0])["to_world"].matrix, dtype=np.float64)
    np.testing.assert_allclose(to_world_matrix(transform_node(ops)), theirs, atol=1e-5)


@pytest.mark.parametrize("target", ["0, 0, 0", "0, -5, 5", "0.3, 0.5, -1", "0, 0, 10"])
def test_lookat_without_up_matches_mitsuba(mi, target: str) -> None:
    ops = f'<lookat origin="0, 0, 5" target="{target}"/>'
    scene = mi.load_string(xml(f'<shape type="rectangle"><transform name="to_world">{ops}</transform></shape>'))
    theirs = np.array(mi.traverse(scene.shapes()[0])["to_world"].matrix, dtype=np.float64)
    np.testing.assert_allclose(to_world_matrix(transform_node(ops)), theirs, atol=1e-5)


# ------------------------------------------------------------------ element mapping
def test_camera_fov_axis_and_thin_lens(tmp_path: Path) -> None:
    body = """<sensor type="thinlens"><float name="fov" value="60"/><float name="aperture_radius" value="0.1"/>
    <float name="focus_distance" value="4"/><float name="near_clip" value="0.5"/>
    <transform name="to_world"><lookat origin="0, 1, 5" target="0, 1, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="20"/></film></sensor>"""
    (tmp_path / "s.xml").write_text(xml(body))
    cam = convert_mitsuba(tmp_path / "s.xml")["camera"]
    assert math.tan(math.radians(cam["fov"]) / 2) == pytest.approx(math.tan(math.radians(30)) * 20 / 40)
    assert cam["resolution"] == [40, 20] and cam["aperture_radius"] == 0.1 and cam["focus_distance"] == 4
    assert cam["near_clip"] == 0.5
    np.testing.assert_allclose(np.subtract(cam["look_at"], cam["position"]), [0, 0, -1])


@pytest.mark.parametrize("fov, size", [
    ('<float name="fov" value="60"/><string name="fov_axis" value="y"/>', (40, 20)),
    ('<float name="fov" value="50"/><string name="fov_axis" value="diagonal"/>', (30, 20)),
    ('<float name="fov" value="50"/><string name="fov_axis" value="smaller"/>', (20, 30)),
    ('<float name="fov" value="50"/><string name="fov_axis" value="larger"/>', (20, 30)),
    ('<float name="fov" value="45"/>', (32, 24)),
    ('<string name="focal_length" value="35mm"/>', (32, 24)),
    ("", (32, 24)),  # Mitsuba's default: a 50 mm lens
], ids=["y", "diagonal", "smaller", "larger", "x", "focal-length", "default"])
def test_field_of_view_matches_mitsuba(tmp_path: Path, mi, fov: str, size: tuple[int, int]) -> None:
    text = xml(f"""<sensor type="perspective">{fov}<film type="hdrfilm"><integer name="width" value="{size[0]}"/>
    <integer name="height" value="{size[1]}"/></film></sensor>""")
    (tmp_path / "s.xml").write_text(text)
    ours = convert_mitsuba(tmp_path / "s.xml")["camera"]["fov"]
    x_fov = float(mi.traverse(mi.load_string(text).sensors()[0])["x_fov"])
    ours_x = math.degrees(2 * math.atan(math.tan(math.radians(ours) / 2) * size[0] / size[1]))
    assert ours_x == pytest.approx(x_fov, rel=1e-5)


def test_materials(tmp_path: Path) -> None:
    data = convert(tmp_path, """
    <bsdf type="dielectric" id="glass"><float name="int_ior" value="1.6"/><float name="ext_ior" value="1.2"/></bsdf>
    <bsdf type="dielectric" id="named"><string name="int_ior" value="water"/></bsdf>
    <bsdf type="conductor" id="mirror"><rgb name="specular_reflectance" value="0.9, 0.8, 0.7"/></bsdf>
    <bsdf type="roughconductor" id="rough"><float name="alpha" value="0.1"/></bsdf>
    <bsdf type="roughplastic" id="plastic"><rgb name="diffuse_reflectance" value="0.2, 0.3, 0.4"/>
        <float name="alpha" value="0.2"/></bsdf>
    <bsdf type="plastic" id="smooth"><boolean name="nonlinear" value="true"/></bsdf>
    <bsdf type="thindielectric" id="pane"><rgb name="specular_transmittance" value="0.5"/></bsdf>
    <bsdf type="twosided" id="two"><bsdf type="diffuse"><rgb name="reflectance" value="0.25"/></bsdf></bsdf>
    <shape type="sphere"><ref id="glass"/></shape>""")
    m = data["materials"]
    assert m["glass"] == {"type": "glass", "ior": pytest.approx(1.6 / 1.2), "albedo": [1.0, 1.0, 1.0]}
    assert m["named"]["ior"] == pytest.approx(1.3330 / 1.000277)
    assert m["mirror"] == {"type": "mirror", "albedo": [0.9, 0.8, 0.7]}
    assert m["rough"] == {"type": "rough_conductor", "specular": [1.0, 1.0, 1.0], "alpha": 0.1,
                          "distribution": "beckmann"}
    assert m["plastic"] == {"type": "rough_plastic", "albedo": [0.2, 0.3, 0.4], "specular": [1.0, 1.0, 1.0],
                            "ior": pytest.approx(1.49 / 1.000277), "nonlinear": False, "alpha": 0.2,
                            "distribution": "beckmann"}
    assert m["smooth"] == {"type": "plastic", "albedo": [0.5, 0.5, 0.5], "specular": [1.0, 1.0, 1.0],
                           "ior": pytest.approx(1.49 / 1.000277), "nonlinear": True}
    assert m["pane"] == {"type": "thin_glass", "ior": pytest.approx(1.5046 / 1.000277), "albedo": [1.0, 1.0, 1.0],
                         "transmittance": [0.5, 0.5, 0.5]}
    assert m["two"] == {"type": "diffuse", "albedo": [0.25, 0.25, 0.25]}


@pytest.mark.parametrize("n", [555.0, 49.5, 12.0])
def test_glossy_lobe_width_matches_beckmann(n: float) -> None:
    """The Mitsuba peer's Beckmann roughness for our Phong exponent (`beckmann_alpha`): at
    normal incidence, the angle from the mirror direction where the lobe falls to half its
    peak, our cos^n lobe against Beckmann's D(half vector) / cos^4, within 5%."""
    alpha = beckmann_alpha(n)
    psi = np.linspace(0, 1.2, 200_001)
    phong = np.cos(psi) ** n
    th = psi / 2  # the half vector turns half as far as the reflected direction
    beckmann = np.exp(-np.tan(th) ** 2 / alpha ** 2) / np.cos(th) ** 4
    half = psi[np.argmax(phong < 0.5)], psi[np.argmax(beckmann < 0.5)]
    assert half[0] == pytest.approx(half[1], rel=0.05)


def test_lights(tmp_path: Path) -> None:
    data = convert(tmp_path, """
    <emitter type="point"><point name="position" value="1, 2, 3"/><rgb name="intensity" value="2"/></emitter>
    <emitter type="spot">
        <transform name="to_world"><lookat origin="0, 2, 0" target="0, 0, 0" up="1, 0, 0"/></transform>
        <float name="cutoff_angle" value="30"/><float name="beam_width" value="30"/>
        <rgb name="intensity" value="1"/></emitter>
    <emitter type="directional"><vector name="direction" value="0, -1, 0"/>
        <rgb name="irradiance" value="0.5"/></emitter>
    <shape type="sphere"><emitter type="area"><rgb name="radiance" value="3, 2, 1"/></emitter></shape>""")
    point, spot, sun = data["lights"]
    assert point["position"] == [1, 2, 3] and point["power"] == pytest.approx([8 * math.pi] * 3)
    assert spot["cone_angle"] == 30 and spot["power"] == pytest.approx([2 * math.pi * (1 - math.cos(math.pi / 6))] * 3)
    np.testing.assert_allclose(spot["direction"], [0, -1, 0], atol=1e-12)
    assert sun == {"type": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": [0.5, 0.5, 0.5]}
    assert data["shapes"][0]["emission"] == [3.0, 2.0, 1.0]


def test_shapes(tmp_path: Path) -> None:
    data = convert(tmp_path, """
    <shape type="rectangle"><transform name="to_world"><scale value="2"/><translate z="1"/></transform></shape>
    <shape type="cube"><transform name="to_world"><scale value="0.5"/></transform></shape>
    <shape type="sphere"><point name="center" value="1, 0, 0"/><float name="radius" value="2"/>
        <transform name="to_world"><scale value="3"/><translate y="1"/></transform></shape>
    <shape type="disk"><transform name="to_world"><scale value="2"/></transform></shape>""")
    scene = parse_scene(data)
    geometry = shape_geometry(scene, tmp_path, tmp_path)
    rect, _, sphere, _ = data["shapes"]
    assert rect["corner"] == [-2, -2, 1] and np.cross(rect["edge1"], rect["edge2"])[2] > 0  # front side +z
    tris = geometry[1].triangles
    assert len(tris) == 12
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    assert np.all(np.einsum("ij,ij->i", normals, tris.mean(axis=1)) > 0)  # wound to face outwards
    assert 0.5 * np.linalg.norm(normals, axis=1).sum() == pytest.approx(6.0)  # side 1
    assert sphere["center"] == [3, 1, 0] and sphere["radius"] == 6
    t = geometry[3].triangles
    area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
    assert area == pytest.approx(4 * math.pi, rel=1e-3)
    assert np.all(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])[:, 2] > 0)


def triangle_normal_at(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The unit winding normal of the triangle that holds the surface point p."""
    e1, e2, v = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], p - t[:, 0]
    d00, d01, d11 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    d20, d21 = (v * e1).sum(1), (v * e2).sum(1)
    b1, b2 = (d11 * d20 - d01 * d21) / (d00 * d11 - d01 ** 2), (d00 * d21 - d01 * d20) / (d00 * d11 - d01 ** 2)
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    inside = (b1 > -1e-4) & (b2 > -1e-4) & (b1 + b2 < 1 + 1e-4)
    distance = np.where(inside, np.abs((v * n).sum(1)), np.inf)
    return n[np.argmin(distance)]


@pytest.mark.parametrize("shape", [
    ('<shape type="rectangle"><transform name="to_world"><scale x="2" y="0.5"/>'
     '<rotate x="0.6" y="0" z="0.8" angle="30"/><translate x="1" y="2" z="3"/></transform></shape>'),
    ('<shape type="cube"><transform name="to_world"><scale x="0.5" y="1" z="2"/><rotate y="1" angle="20"/>'
     '</transform></shape>'),
    ('<shape type="sphere"><point name="center" value="1, 0, 0"/><float name="radius" value="0.5"/>'
    '<transform name="to_world"><scale value="2"/><translate z="1"/></transform></shape>'),
    '<shape type="disk"><transform name="to_world"><scale value="1.5"/><rotate x="1" angle="70"/></transform></shape>',
    ('<shape type="ply"><string name="filename" value="meshes/icosphere.ply"/>'
    '<transform name="to_world"><matrix value="1 0.2 0 1  0 1 0 0  0 0 0.5 2  0 0 0 1"/></transform></shape>'),
    ('<shape type="obj"><string name="filename" value="meshes/gem.obj"/>'
    '<transform name="to_world"><lookat origin="1, 1, 1" target="0, 0, 0" up="0, 1, 0"/></transform></shape>'),
], ids=["rectangle", "cube", "sphere", "disk", "ply", "obj"])
def test_shape_placement_matches_mitsuba(tmp_path: Path, mi, shape: str) -> None:
    """Where each shape ends up, and how large it is, against Mitsuba's own loader."""
    shutil.copytree(MITSUBA_SCENES / "meshes", tmp_path / "meshes")
    data = convert(tmp_path, shape)
    mesh = mi.load_file(str(tmp_path / "scene.xml")).shapes()[0]
    box = mesh.bbox()
    geometry = shape_geometry(parse_scene(data), tmp_path, tmp_path)[0]
    if geometry is None:
        sphere = data["shapes"][0]
        points = np.array([np.subtract(sphere["center"], sphere["radius"]), np.add(sphere["center"], sphere["radius"])])
        area = 4 * math.pi * sphere["radius"] ** 2
    else:
        t = geometry.triangles
        points = t.reshape(-1, 3)
        area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
    np.testing.assert_allclose(points.min(axis=0), np.array(box.min), atol=2e-3 * float(np.max(np.abs(points))))
    np.testing.assert_allclose(points.max(axis=0), np.array(box.max), atol=2e-3 * float(np.max(np.abs(points))))
    assert area == pytest.approx(float(mesh.surface_area()), rel=1e-3)
    if geometry is not None:  # the front side: our winding's normal where Mitsuba's faces
        for u in (0.1, 0.4, 0.8):
            sample = mesh.sample_position(0.0, mi.Point2f(u, 1.0 - 0.7 * u))
            normal = triangle_normal_at(geometry.triangles, np.array(sample.p, dtype=np.float64))
            assert float(np.dot(normal, np.array(sample.n))) > 0.5  # its n is the shading normal where smooth


def test_default_params_and_overrides(tmp_path: Path) -> None:
    body = """<default name="r" value="0.25"/>
    <shape type="sphere"><float name="radius" value="$r"/></shape>"""
    assert convert(tmp_path, body)["shapes"][0]["radius"] == 0.25
    assert convert(tmp_path, body, {"r": 2})["shapes"][0]["radius"] == 2


def test_include_and_ref(tmp_path: Path) -> None:
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "materials.xml").write_text(xml(
        '<bsdf type="diffuse" id="grey"><rgb name="reflectance" value="0.3"/></bsdf>'))
    data = convert(tmp_path, '<include filename="parts/materials.xml"/>\n<shape type="sphere"><ref id="grey"/></shape>')
    assert data["shapes"][0]["material"] == "grey"
    assert data["materials"]["grey"]["albedo"] == [0.3, 0.3, 0.3]


def test_json_scene_with_meshes_beside_it_is_self_contained(tmp_path: Path) -> None:
    """A user's JSON scene and its mesh, anywhere: load_any_scene reads the file (inside the
    scene's folder) and inlines it, so the scene compiles with no file at hand."""
    (tmp_path / "meshes").mkdir()
    shutil.copy(MITSUBA_SCENES / "meshes" / "icosphere.ply", tmp_path / "meshes" / "ball.ply")
    data = {"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "resolution": [8, 8]},
            "materials": {"m": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            "shapes": [{"type": "mesh", "file": "meshes/ball.ply", "material": "m"}]}
    (tmp_path / "scene.json").write_text(json.dumps(data))
    scene, _ = load_any_scene(tmp_path / "scene.json")
    arrays = compile_scene(scene, SCENES_DIR)  # no file is read here any more
    assert len(arrays.tri_v0) == 320 and len(arrays.tri_nrm) == 3 * 320
    data["shapes"][0]["file"] = "../elsewhere.ply"
    (tmp_path / "scene.json").write_text(json.dumps(data))
    with pytest.raises(SceneError) as info:
        load_any_scene(tmp_path / "scene.json")
    assert info.value.field == "shapes.0.file"


def test_load_any_scene_reads_both_formats(tmp_path: Path) -> None:
    scene, base = load_any_scene(MITSUBA_SCENES / "obj-mesh.xml")
    assert base == MITSUBA_SCENES and len(scene.shapes) == 5
    scene, base = load_any_scene(SCENES_DIR / "cornell-box.json")
    assert base == SCENES_DIR


# ---------------------------------------------------------------- bad scene files
def test_unknown_plugin_names_element_and_line(tmp_path: Path) -> None:
    err = convert_error(tmp_path, '<shape type="sphere">\n  <bsdf type="hair"/>\n</shape>')
    line = line_of(tmp_path / "scene.xml", 'type="hair"')
    assert f"line {line}" in str(err) and '<bsdf type="hair">' in str(err) and "unknown bsdf plugin" in str(err)
    assert err.field == "scene.xml"


@pytest.mark.parametrize("body, needle, says", [
    ('<shape type="shapegroup"/>', "shapegroup", "needs an id"),
    ('<shape type="hair"/>', "hair", "unknown shape plugin"),
    ('<emitter type="sunsky"/>', "sunsky", "unknown emitter plugin"),
    ('<emitter type="envmap"/>', "envmap", "needs a filename"),
    ('<emitter type="constant"/>\n<emitter type="constant" id="second"/>', 'id="second"', "at most one environment"),
    ('<medium type="homogeneous"/>', "medium", "not supported"),
    ('<shape type="sphere"><float name="roughness" value="1"/></shape>', "roughness", "not supported"),
    ('<bsdf type="conductor" id="c"><string name="material" value="Cr"/></bsdf>', "Cr", "material"),
    ('<bsdf type="roughconductor" id="c"><float name="alpha_u" value="0.1"/><float name="alpha_v" value="0.3"/></bsdf>',
     "alpha_u", "anisotropic"),
    ('<emitter type="spot"><float name="cutoff_angle" value="30"/></emitter>', "spot", "no falloff"),
    ('<bsdf type="diffuse" id="d"><texture type="bitmap" name="reflectance"/></bsdf>', "bitmap", "needs a filename"),
    ('<shape type="sphere"><float name="radius" value="$nope"/></shape>', "$nope", "undefined parameter"),
    ('<shape type="sphere"><ref id="missing"/></shape>', "missing", "no object with id"),
])
def test_outside_the_subset_is_an_error_with_its_line(tmp_path: Path, body: str, needle: str, says: str) -> None:
    err = convert_error(tmp_path, body)
    path = tmp_path / "scene.xml"
    assert f"line {line_of(path, needle)}" in str(err), str(err)
    assert says in str(err), str(err)


def test_invalid_value_names_the_element(tmp_path: Path) -> None:
    """Values the schema refuses point back at the XML element that gave them."""
    err = convert_error(tmp_path, '<shape type="sphere">\n'
                                  '<emitter type="area"><rgb name="radiance" value="-1"/></emitter>\n</shape>')
    line = line_of(tmp_path / "scene.xml", '<shape type="sphere">')
    assert f"line {line}" in str(err)
    assert "shapes.0.emission" in str(err)


def test_singular_transform(tmp_path: Path) -> None:
    err = convert_error(tmp_path, '<shape type="cube"><transform name="to_world"><scale x="0"/></transform></shape>')
    assert "singular" in str(err) and f"line {line_of(tmp_path / 'scene.xml', 'scale')}" in str(err)


def test_triangle_limit_applies_while_converting(tmp_path: Path, monkeypatch) -> None:
    from worker import mitsuba_scene

    monkeypatch.setattr(mitsuba_scene, "MAX_TRIANGLES", 20)
    err = convert_error(tmp_path, '<shape type="cube"/>\n<shape type="cube"/>')  # 12 triangles each
    assert "more than 20 triangles" in str(err) and f"line {line_of(tmp_path / 'scene.xml', 'cube') + 1}" in str(err)


def test_malformed_xml(tmp_path: Path) -> None:
    err = convert_error(tmp_path, '<shape type="sphere">\n<float name="radius" value="1">\n</shape>')
    assert "malformed XML" in str(err) and "line" in str(err)


def test_old_format_and_no_sensor(tmp_path: Path) -> None:
    (tmp_path / "old.xml").write_text(xml('<shape type="sphere"/>', version="0.6.0"))
    with pytest.raises(SceneError, match="only Mitsuba 3"):
        convert_mitsuba(tmp_path / "old.xml")
    assert "no sensor" in str(convert_error(tmp_path, '<shape type="sphere"/>', with_sensor=False))


def test_missing_mesh(tmp_path: Path) -> None:
    err = convert_error(tmp_path, '<shape type="ply"><string name="filename" value="nope.ply"/></shape>')
    assert "not found" in str(err) and f"line {line_of(tmp_path / 'scene.xml', 'nope.ply')}" in str(err)


def test_broken_ply(tmp_path: Path) -> None:
    good = (MITSUBA_SCENES / "meshes" / "icosphere.ply").read_bytes()
    (tmp_path / "broken.ply").write_bytes(good[: len(good) // 2])  # truncated binary body
    err = convert_error(tmp_path, '<shape type="ply"><string name="filename" value="broken.ply"/></shape>')
    assert "broken.ply" in str(err) and "malformed PLY" in str(err)


@pytest.mark.parametrize("name", ["../outside.ply", "ABSOLUTE", "../../../../etc/passwd"])
def test_mesh_outside_root(tmp_path: Path, name: str) -> None:
    root = tmp_path / "upload"
    root.mkdir()
    shutil.copy(MITSUBA_SCENES / "meshes" / "icosphere.ply", tmp_path / "outside.ply")
    if name == "ABSOLUTE":
        name = str(tmp_path / "outside.ply")
    err = convert_error(root, f'<shape type="ply"><string name="filename" value="{name}"/></shape>')
    assert "leaves the scene's directory" in str(err)


def test_include_outside_root(tmp_path: Path) -> None:
    root = tmp_path / "upload"
    root.mkdir()
    (tmp_path / "other.xml").write_text(xml(""))
    err = convert_error(root, '<include filename="../other.xml"/>')
    assert "leaves the scene's directory" in str(err)


# ------------------------------------------------------------------ meshes
def test_ply_ascii_and_binary_agree(tmp_path: Path) -> None:
    import trimesh

    binary = load_mesh(MITSUBA_SCENES / "meshes" / "icosphere.ply")
    mesh = trimesh.Trimesh(binary.vertices, binary.triangles, vertex_normals=binary.normals, process=False)
    (tmp_path / "ascii.ply").write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="ascii", vertex_normal=True))
    ascii_ = load_mesh(tmp_path / "ascii.ply")
    assert binary.triangles.shape == (320, 3) and binary.normals is not None
    np.testing.assert_array_equal(ascii_.triangles, binary.triangles)
    np.testing.assert_allclose(ascii_.vertices, binary.vertices, atol=1e-6)
    np.testing.assert_allclose(ascii_.normals, binary.normals, atol=1e-6)


def test_obj_normals_are_read(tmp_path: Path) -> None:
    (tmp_path / "n.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nvn 0 0.6 0.8\nvn 0.6 0 0.8\n"
                                    "f 1//1 2//2 3//3\n")
    mesh = load_mesh(tmp_path / "n.obj")
    np.testing.assert_allclose(mesh.normals, [[0, 0, 1], [0, 0.6, 0.8], [0.6, 0, 0.8]])
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert load_mesh(tmp_path / "flat.obj").normals is None


def test_obj_bytes_outside_utf8(tmp_path: Path) -> None:
    """A Latin-1 comment does not stop an OBJ from reading; bytes that are no OBJ at all say so."""
    latin1 = "# caf\u00e9 mod\u00e8le\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".encode("latin-1")
    (tmp_path / "latin1.obj").write_bytes(latin1)
    assert load_mesh(tmp_path / "latin1.obj").triangles.tolist() == [[0, 1, 2]]
    (tmp_path / "binary.obj").write_bytes(b"\x00\x01\x02 binary \xff\xfe")
    with pytest.raises(MeshError, match="no triangles"):
        load_mesh(tmp_path / "binary.obj")


@pytest.mark.parametrize("content", [b"", b"ply\nformat ascii 1.0\nend_header\n", b"solid x\nendsolid\n"],
                         ids=["empty", "no-elements", "not-ply"])
def test_bad_ply_is_a_mesh_error(tmp_path: Path, content: bytes) -> None:
    (tmp_path / "bad.ply").write_bytes(content)
    with pytest.raises(MeshError):
        load_mesh(tmp_path / "bad.ply")


def test_json_scene_with_ply_file(tmp_path: Path) -> None:
    """Our own JSON takes `file` for .ply as for .obj; a missing one names shapes.N.file."""
    shutil.copy(MITSUBA_SCENES / "meshes" / "icosphere.ply", tmp_path / "ball.ply")
    base = {"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "resolution": [8, 8]},
            "materials": {"m": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            "shapes": [{"type": "mesh", "file": "ball.ply", "material": "m"}],
            "lights": [{"type": "point", "position": [0, 3, 3], "power": [1, 1, 1]}]}
    arrays = compile_scene(parse_scene(base), tmp_path, root=tmp_path)
    assert len(arrays.tri_v0) == 320 and np.all(arrays.tri_e1[:, 3] == 1.0) and len(arrays.tri_nrm) == 3 * 320
    base["shapes"][0]["file"] = "gone.ply"
    with pytest.raises(SceneError) as info:
        compile_scene(parse_scene(base), tmp_path, root=tmp_path)
    assert info.value.field == "shapes.0.file"


# ------------------------------------------------------------------ smooth normals
def ball_scene(normals: str, material: dict | None = None) -> dict:
    """A coarse icosphere (80 faces) in mirror or diffuse, lit by a quad light, with the given
    vertex normals: none (flat), the face normals (flat again, through the smooth path), or
    the true sphere's."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    v, f = np.asarray(ico.vertices), np.asarray(ico.faces)
    tris = v[f].reshape(-1, 3)  # unshared corners: each may have its own normal
    shape = {"type": "mesh", "vertices": tris.tolist(), "triangles": np.arange(len(tris)).reshape(-1, 3).tolist(),
             "material": "ball"}
    if normals == "face":
        n = np.cross(v[f][:, 1] - v[f][:, 0], v[f][:, 2] - v[f][:, 0])
        shape["normals"] = np.repeat(n / np.linalg.norm(n, axis=1, keepdims=True), 3, axis=0).tolist()
    elif normals == "sphere":
        shape["normals"] = (tris / np.linalg.norm(tris, axis=1, keepdims=True)).tolist()
    return {"camera": {"position": [0, 0, 4], "look_at": [0, 0, 0], "fov": 35, "resolution": [24, 24]},
            "materials": {"ball": material or {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]},
                          "wall": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            "shapes": [shape, {"type": "quad", "corner": [-3, -3, -2], "edge1": [6, 0, 0], "edge2": [0, 6, 0],
                               "material": "wall"},
                       {"type": "quad", "corner": [-6, -6, 6], "edge1": [0, 12, 0], "edge2": [12, 0, 0],
                        "material": "wall"}],  # behind the camera: what the ball reflects
            "lights": [{"type": "point", "position": [2, 2, 3], "power": [300, 300, 300]}]}


def render_dict(make_engine, tmp_path: Path, data: dict, passes: int = 8) -> np.ndarray:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(data))
    engine = make_engine(path, photons_per_pass=1 << 15, seed=5)
    return image(engine, render(engine, passes))


def test_flat_scenes_carry_no_normals() -> None:
    """Scenes without normals take the unchanged flat path in the kernels (no normal rows,
    every triangle flagged flat): same seed, same image as before smooth normals existed."""
    scene, base = load_any_scene(SCENES_DIR / "cornell-caustics.json")
    arrays = compile_scene(scene, base)
    assert arrays.tri_nrm.shape == (0, 4) and np.all(arrays.tri_e1[:, 3] == 0.0)


def test_face_normals_render_as_flat(make_engine, tmp_path: Path) -> None:
    """The smooth path with normals equal to the face normals is the flat image, up to float
    rounding of the interpolated normal (which can flip a rare Russian roulette decision)."""
    flat = render_dict(make_engine, tmp_path, ball_scene("none"))
    face = render_dict(make_engine, tmp_path, ball_scene("face"))
    assert np.mean(np.abs(face - flat)) < 0.01 * np.mean(flat)


@pytest.mark.parametrize("material", [{"type": "diffuse", "albedo": [0.8, 0.8, 0.8]},
                                      {"type": "mirror", "albedo": [0.9, 0.9, 0.9]}], ids=["diffuse", "mirror"])
def test_sphere_normals_hide_the_facets(make_engine, tmp_path: Path, material: dict) -> None:
    """A flat icosphere shows its facets (in its shading, or in what it reflects); with the
    sphere's normals it looks like a true sphere. Compared inside the silhouette (the
    outlines differ). Not glass: through a ball this coarse, refraction depends on where
    the facets really are, and smooth normals cannot hide that."""
    sphere = ball_scene("none", material)
    sphere["shapes"][0] = {"type": "sphere", "center": [0, 0, 0], "radius": 1.0, "material": "ball"}
    scenes = {"flat": ball_scene("none", material), "smooth": ball_scene("sphere", material), "true": sphere}
    images = {k: render_dict(make_engine, tmp_path, d, passes=64).mean(axis=2) for k, d in scenes.items()}
    inner = slice(7, 17), slice(7, 17)  # well inside the ball's silhouette
    error = {k: float(np.mean(np.abs(images[k][inner] - images["true"][inner]))) for k in ("flat", "smooth")}
    assert error["smooth"] < 0.7 * error["flat"], error  # both include the three renders' noise
