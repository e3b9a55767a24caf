"""Scene validation: every bad scene is refused with a SceneError naming the exact field.

Covers the pydantic schema (worker.scene.parse_scene), mesh loading and its sandbox
(worker.scene.shape_triangles via worker.scene_arrays.compile_scene), the documented
limits, and the `photonfarm render` CLI's handling of bad input (exit 2, one line on
stderr, no traceback). Nothing here needs OpenCL: every CLI case fails before the
engine creates a context.
"""

from __future__ import annotations

import copy
import json
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from pydantic import StrictInt, TypeAdapter, ValidationError

import worker.scene as scene_mod
from tests.helpers import PHOTONFARM
from worker.scene import (
    MAX_LIGHTS,
    MAX_PIXELS,
    MAX_RESOLUTION,
    MAX_SHAPES,
    SCENES_DIR,
    SceneError,
    Vec3,
    load_scene_file,
    parse_scene,
    shape_triangles,
)
from worker.scene_arrays import compile_scene

REPO = Path(__file__).resolve().parent.parent
BUNDLED = sorted(SCENES_DIR.glob("*.json"))


# --------------------------------------------------------------------------- helpers
def minimal_scene() -> dict:
    """A small valid scene: one diffuse sphere (shape 0), one point light (light 0)."""
    return {
        "description": "test scene",
        "camera": {"position": [0.0, 0.0, -5.0], "look_at": [0.0, 0.0, 0.0], "resolution": [16, 16]},
        "materials": {"white": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
        "shapes": [{"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0, "material": "white"}],
        "lights": [{"type": "point", "position": [0.0, 3.0, 0.0], "power": [10.0, 10.0, 10.0]}],
    }


def sphere(**kw) -> dict:
    return {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0, "material": "white", **kw}


def quad(**kw) -> dict:
    return {"type": "quad", "corner": [-1.0, -1.0, 0.0], "edge1": [2.0, 0.0, 0.0], "edge2": [0.0, 2.0, 0.0],
            "material": "white", **kw}


def scene_with(*shapes: dict) -> dict:
    """minimal_scene() with `shapes` appended, so the first of them is shape 1."""
    d = minimal_scene()
    d["shapes"].extend(copy.deepcopy(list(shapes)))
    return d


def parse_error(data: object) -> SceneError:
    with pytest.raises(SceneError) as info:
        parse_scene(data)
    return info.value


def compile_error(data: dict, base_dir: Path = SCENES_DIR, root: Path = SCENES_DIR) -> SceneError:
    scene = parse_scene(data)  # must be valid as far as the schema goes
    with pytest.raises(SceneError) as info:
        compile_scene(scene, base_dir, root=root)
    return info.value


def via_json_text(data: dict) -> object:
    """Round-trip through JSON text, as a scene file would arrive (Python json allows NaN/Infinity)."""
    return json.loads(json.dumps(data))


# ------------------------------------------------------------------- bundled scenes
def test_there_are_bundled_scenes():
    assert len(BUNDLED) >= 1


@pytest.mark.parametrize("path", BUNDLED, ids=[p.stem for p in BUNDLED])
def test_bundled_scene_parses_and_compiles(path: Path):
    scene, base_dir = load_scene_file(path)
    assert base_dir == SCENES_DIR
    arrays = compile_scene(scene, base_dir)
    assert (arrays.width, arrays.height) == tuple(scene.camera.resolution)
    assert len(arrays.tri_v0) + len(arrays.spheres) > 0
    assert np.all(np.isfinite(arrays.camera))
    assert arrays.emitter_cdf[-1] == 1.0


@pytest.mark.parametrize("path", BUNDLED, ids=[p.stem for p in BUNDLED])
def test_bundled_scene_has_one_line_description(path: Path):
    description = json.loads(path.read_text()).get("description")
    assert isinstance(description, str)
    assert description.strip(), "description is empty"
    assert "\n" not in description and "\r" not in description, "description is not one line"


def test_minimal_scene_is_valid():
    """The helper every case below starts from parses and compiles as written: one sphere,
    one point light, the camera's resolution."""
    scene = parse_scene(minimal_scene())
    arrays = compile_scene(scene, SCENES_DIR)
    assert (arrays.width, arrays.height) == (16, 16)
    assert len(arrays.spheres) == 1 and len(arrays.tri_v0) == 0
    assert len(scene.lights) == 1 and arrays.emitter_cdf[-1] == 1.0


# ------------------------------------------------------------------------ materials
def test_unknown_material_type():
    d = minimal_scene()
    d["materials"]["shiny"] = {"type": "velvet", "albedo": [0.5, 0.5, 0.5]}
    assert parse_error(d).field == "materials.shiny"


def test_material_without_type():
    d = minimal_scene()
    d["materials"]["shiny"] = {"albedo": [0.5, 0.5, 0.5]}
    assert parse_error(d).field == "materials.shiny"


def test_shape_with_undefined_material():
    d = scene_with(sphere(material="nonexistent"))
    err = parse_error(d)
    assert err.field == "shapes.1.material"
    assert "nonexistent" in err.message


@pytest.mark.parametrize("ior", [0.5, 5.0, 0.0, -1.5, float("nan"), float("inf")])
def test_glass_ior_out_of_range(ior: float):
    d = minimal_scene()
    d["materials"]["lens"] = {"type": "glass", "ior": ior}
    assert parse_error(via_json_text(d)).field == "materials.lens.ior"


@pytest.mark.parametrize("ior", [1.0, 1.5, 3.0])
def test_glass_ior_in_range(ior: float):
    d = minimal_scene()
    d["materials"]["lens"] = {"type": "glass", "ior": ior}
    assert parse_scene(d).materials["lens"].ior == ior


def test_albedo_above_one():
    d = minimal_scene()
    d["materials"]["white"]["albedo"] = [0.5, 1.5, 0.5]
    assert parse_error(d).field == "materials.white.albedo.1"


# --------------------------------------------------------------- non-finite numbers
@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")], ids=["nan", "inf", "-inf"])
def test_non_finite_sphere_center(value: float):
    d = scene_with(sphere(center=[0.0, 0.0, value]))
    data = via_json_text(d)
    assert math.isnan(data["shapes"][1]["center"][2]) or math.isinf(data["shapes"][1]["center"][2])
    err = parse_error(data)
    assert err.field.startswith("shapes.1.")
    assert err.field == "shapes.1.center.2"


@pytest.mark.parametrize("value", [float("nan"), float("inf")], ids=["nan", "inf"])
def test_non_finite_quad_corner(value: float):
    d = scene_with(quad(corner=[value, 0.0, 0.0]))
    err = parse_error(via_json_text(d))
    assert err.field.startswith("shapes.1.")
    assert err.field == "shapes.1.corner.0"


def test_non_finite_from_json_text_literal():
    text = json.dumps(minimal_scene()).replace('"radius": 1.0', '"radius": NaN')
    assert "NaN" in text
    assert parse_error(json.loads(text)).field == "shapes.0.radius"


def test_non_finite_light_power():
    d = minimal_scene()
    d["lights"][0]["power"] = [1.0, float("nan"), 1.0]
    assert parse_error(via_json_text(d)).field == "lights.0.power.1"


def test_coordinate_above_max_coord():
    d = scene_with(sphere(center=[0.0, 2 * scene_mod.MAX_COORD, 0.0]))
    assert parse_error(d).field == "shapes.1.center.1"


# -------------------------------------------------------------------------- shapes
@pytest.mark.parametrize("radius", [-1.0, 0.0, -0.0])
def test_bad_sphere_radius(radius: float):
    assert parse_error(scene_with(sphere(radius=radius))).field == "shapes.1.radius"


def test_zero_area_emitting_quad():
    d = scene_with(quad(edge1=[1.0, 0.0, 0.0], edge2=[2.0, 0.0, 0.0], emission=[5.0, 5.0, 5.0]))
    err = compile_error(d)
    assert err.field == "shapes.1.emission"


def test_zero_area_emitting_quad_via_shape_triangles():
    d = scene_with(quad(edge1=[0.0, 0.0, 0.0], edge2=[0.0, 1.0, 0.0], emission=[1.0, 0.0, 0.0]))
    with pytest.raises(SceneError) as info:
        shape_triangles(parse_scene(d), SCENES_DIR)
    assert info.value.field == "shapes.1.emission"


def test_zero_area_quad_without_emission_is_not_an_emitter_error():
    d = scene_with(quad(edge1=[1.0, 0.0, 0.0], edge2=[2.0, 0.0, 0.0], emission=[0.0, 0.0, 0.0]))
    tris = shape_triangles(parse_scene(d), SCENES_DIR)
    assert tris[0] is None and tris[1].shape == (2, 3, 3)


@pytest.mark.parametrize("triangles", [[[0, 1, 3]], [[-1, 0, 1]]], ids=["past-end", "negative"])
def test_inline_mesh_indexes_missing_vertex(triangles):
    mesh = {"type": "mesh", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "triangles": triangles,
            "material": "white"}
    err = parse_error(scene_with(mesh))
    assert err.field.startswith("shapes.1")
    # "mesh" is the union tag, not a field of the scene: the path is the shape itself.
    assert err.field == "shapes.1"


def test_unknown_shape_type():
    d = scene_with({"type": "cube", "material": "white"})
    assert parse_error(d).field == "shapes.1"


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d["shapes"][0].update(radus=1.0), "shapes.0.radus"),
        (lambda d: d["camera"].update(fvo=40.0), "camera.fvo"),
        (lambda d: d["materials"]["white"].update(ior=1.5), "materials.white.ior"),
        (lambda d: d["lights"][0].update(powr=[1, 1, 1]), "lights.0.powr"),
        (lambda d: d.update(light=[]), "light"),
        (lambda d: d["shapes"][0].update(emision=[1, 1, 1]), "shapes.0.emision"),
    ],
    ids=["shape", "camera", "material", "light", "top-level", "optional-emission"],
)
def test_unknown_field_is_rejected(mutate, field: str):
    d = minimal_scene()
    mutate(d)
    err = parse_error(d)
    assert err.field == field
    assert field.rsplit(".", 1)[-1] in err.field


# ------------------------------------------------------------------------ meshes (.obj)
OBJ_TEXT = """\
# a triangle, a quad (fan-triangulated into 2) and a pentagon (3), with v/vt/vn syntax
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
vt 0 0
vn 0 0 1
f 1 2 3
f 1/1/1 2/1/1 3/1/1 4/1/1
f -5 -4 -3 -2 -1
"""


def mesh_shape(obj: str, **kw) -> dict:
    return {"type": "mesh", "file": obj, "material": "white", **kw}


@pytest.fixture
def mesh_root(tmp_path: Path) -> Path:
    root = tmp_path / "root"
    (root / "meshes").mkdir(parents=True)
    (root / "meshes" / "thing.obj").write_text(OBJ_TEXT)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "evil.obj").write_text(OBJ_TEXT)
    return root


def _same_triangle(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal up to a rotation of the corners (same winding: same front side)."""
    return any(np.array_equal(np.roll(a, k, axis=0), b) for k in range(3))


def test_obj_inside_root_loads(mesh_root: Path):
    scene = parse_scene(scene_with(mesh_shape("meshes/thing.obj")))
    per_shape = shape_triangles(scene, mesh_root, mesh_root)
    tris = per_shape[1]
    assert tris.shape == (1 + 2 + 3, 3, 3)
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1]], float)
    # quad 1 2 3 4 splits along the diagonal 1-3 into (1 2 3), (1 3 4), winding kept
    assert _same_triangle(tris[0], v[[0, 1, 2]])
    assert _same_triangle(tris[1], v[[0, 1, 2]])
    assert _same_triangle(tris[2], v[[0, 2, 3]])
    # negative indices count back from the last vertex: the pentagon covers all five
    assert {tuple(p) for p in tris[3:].reshape(-1, 3)} == {tuple(p) for p in v}
    arrays = compile_scene(scene, mesh_root, root=mesh_root)
    assert len(arrays.tri_v0) == 6


def test_obj_relative_to_scene_dir_in_subfolder(mesh_root: Path):
    scene = parse_scene(scene_with(mesh_shape("thing.obj")))
    assert len(compile_scene(scene, mesh_root / "meshes", root=mesh_root).tri_v0) == 6


def test_obj_missing(mesh_root: Path):
    err = compile_error(scene_with(mesh_shape("missing.obj")), base_dir=mesh_root, root=mesh_root)
    assert err.field == "shapes.1.file"
    assert "not found" in err.message


def test_obj_wrong_suffix_is_not_read(mesh_root: Path):
    (mesh_root / "meshes" / "thing.txt").write_text(OBJ_TEXT)
    err = compile_error(scene_with(mesh_shape("meshes/thing.txt")), base_dir=mesh_root, root=mesh_root)
    assert err.field == "shapes.1.file"


def test_obj_is_a_directory(mesh_root: Path):
    (mesh_root / "dir.obj").mkdir()
    err = compile_error(scene_with(mesh_shape("dir.obj")), base_dir=mesh_root, root=mesh_root)
    assert err.field == "shapes.1.file"


@pytest.mark.parametrize("obj", ["../outside/evil.obj", "meshes/../../outside/evil.obj", "ABSOLUTE",
                                 "../../../../../../../../etc/passwd", "/etc/passwd"])
def test_obj_escaping_root(mesh_root: Path, obj: str):
    if obj == "ABSOLUTE":
        obj = str(mesh_root.parent / "outside" / "evil.obj")
    assert Path(mesh_root / obj).resolve().exists() or obj.endswith("passwd")
    err = compile_error(scene_with(mesh_shape(obj)), base_dir=mesh_root, root=mesh_root)
    assert err.field == "shapes.1.file"
    assert "leaves the scene's directory" in err.message


def test_obj_escaping_root_through_symlink(mesh_root: Path):
    link = mesh_root / "link.obj"
    try:
        link.symlink_to(mesh_root.parent / "outside" / "evil.obj")
    except OSError:
        pytest.skip("cannot create symlinks here")
    err = compile_error(scene_with(mesh_shape("link.obj")), base_dir=mesh_root, root=mesh_root)
    assert err.field == "shapes.1.file"
    assert "leaves the scene's directory" in err.message


def test_obj_escaping_default_scenes_root():
    err = compile_error(scene_with(mesh_shape("../../../../../../etc/passwd")))
    assert err.field == "shapes.1.file"
    assert "leaves the scene's directory" in err.message


def test_obj_in_sibling_dir_with_root_as_prefix(tmp_path: Path):
    """'root-evil' starts with the characters of 'root' but is not inside it."""
    root = tmp_path / "root"
    root.mkdir()
    (tmp_path / "root-evil").mkdir()
    (tmp_path / "root-evil" / "x.obj").write_text(OBJ_TEXT)
    err = compile_error(scene_with(mesh_shape("../root-evil/x.obj")), base_dir=root, root=root)
    assert err.field == "shapes.1.file"


@pytest.mark.parametrize("text", ["v 0 0 0\nv 1 0 0\nf 1 2 3\n", "v 0 0 0\nv x 0 0\nv 0 1 0\nf 1 2 3\n",
                                  "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 a 3\n"],
                         ids=["missing-vertex", "bad-number", "nan", "bad-index"])
def test_malformed_obj(tmp_path: Path, text: str):
    (tmp_path / "bad.obj").write_text(text)
    err = compile_error(scene_with(mesh_shape("bad.obj")), base_dir=tmp_path, root=tmp_path)
    assert err.field == "shapes.1.file"


def test_obj_index_zero_is_rejected(tmp_path: Path):
    """OBJ indices are 1-based; 0 is invalid even when a vertex is defined after the face."""
    (tmp_path / "zero.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\nv 1 1 0\n")
    err = compile_error(scene_with(mesh_shape("zero.obj")), base_dir=tmp_path, root=tmp_path)
    assert err.field == "shapes.1.file"


def test_mesh_needs_exactly_one_source():
    both = {"type": "mesh", "file": "x.obj", "vertices": [[0, 0, 0]], "triangles": [], "material": "white"}
    neither = {"type": "mesh", "material": "white"}
    assert parse_error(scene_with(both)).field.startswith("shapes.1")
    assert parse_error(scene_with(neither)).field.startswith("shapes.1")


# ------------------------------------------------------------- inline meshes as arrays
TRIANGLE = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]


def inline_mesh(**kw) -> dict:
    return {"type": "mesh", "vertices": copy.deepcopy(TRIANGLE), "triangles": [[0, 1, 2]], "material": "white", **kw}


def pydantic_error(rows_type: object, value: object) -> tuple[tuple, str]:
    """(location, message) of pydantic's own first error for `value` as `rows_type`."""
    with pytest.raises(ValidationError) as info:
        TypeAdapter(rows_type).validate_python(value)
    err = info.value.errors()[0]
    return err["loc"], err["msg"]


INDICES = list[tuple[StrictInt, StrictInt, StrictInt]]


@pytest.mark.parametrize("key, rows_type, value", [
    ("vertices", list[Vec3], TRIANGLE[:2] + [[0.0, True, 0.0]]),
    ("vertices", list[Vec3], TRIANGLE[:2] + [[0.0, "1", 0.0]]),
    ("vertices", list[Vec3], TRIANGLE[:2] + [[0.0, float("nan"), 0.0]]),
    ("vertices", list[Vec3], TRIANGLE[:2] + [[0.0, 2 * scene_mod.MAX_COORD, 0.0]]),
    ("vertices", list[Vec3], TRIANGLE[:2] + [[0.0, 1.0]]),
    ("vertices", list[Vec3], TRIANGLE[:2] + [None]),
    ("vertices", list[Vec3], {"0": [0.0, 0.0, 0.0]}),
    ("normals", list[Vec3], TRIANGLE[:2] + [[0.0, 0.0, float("inf")]]),
    ("triangles", INDICES, [[0, 1, 2], [0, 1.0, 2]]),
    ("triangles", INDICES, [[0, 1, 2], [0, False, 2]]),
    ("triangles", INDICES, [[0, 1, 2], [0, 1, 2, 3]]),
], ids=["bool", "string", "nan", "past-max-coord", "two-coordinates", "null-row", "object", "normal-inf",
        "float-index", "bool-index", "four-indices"])
def test_inline_mesh_rows_are_refused_as_pydantic_refuses_them(key: str, rows_type: object, value: object):
    """The arrays are checked vectorised, but a bad value gets pydantic's own error for the
    list type it stands for, at the element's path."""
    err = parse_error(scene_with(inline_mesh(**{key: value})))
    loc, msg = pydantic_error(rows_type, value)
    assert (err.field, err.message) == (".".join(map(str, ("shapes", 1, key, *loc))), msg)


@pytest.mark.parametrize("value", [float("nan"), 2 * scene_mod.MAX_COORD], ids=["nan", "past-max-coord"])
def test_inline_mesh_arrays_are_refused_as_their_lists_are(value: float):
    """An array (as the Mitsuba import passes them) is refused with its list's error."""
    vertices = np.array(TRIANGLE)
    vertices[2, 1] = value
    as_array = parse_error(scene_with(inline_mesh(vertices=vertices)))
    as_list = parse_error(scene_with(inline_mesh(vertices=vertices.tolist())))
    assert (as_array.field, as_array.message) == (as_list.field, as_list.message)
    assert as_array.field == "shapes.1.vertices.2.1"


def test_inline_mesh_is_held_as_arrays_and_written_as_lists():
    """Integers are accepted as coordinates (as JSON writes 0 for 0.0); the mesh is held as
    float64 and int64 arrays; its JSON is lists again and reads back to an equal scene."""
    d = scene_with(inline_mesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], normals=[(0.0, 0.0, 1.0)] * 3))
    scene = parse_scene(d)
    mesh = scene.shapes[1]
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.shape == (3, 3)
    assert mesh.triangles.dtype == np.int64 and mesh.triangles.shape == (1, 3)
    np.testing.assert_array_equal(mesh.vertices, TRIANGLE)
    written = json.loads(scene.model_dump_json(exclude_none=True))["shapes"][1]
    assert written["vertices"] == TRIANGLE and written["triangles"] == [[0, 1, 2]]
    assert written["normals"] == [[0.0, 0.0, 1.0]] * 3
    assert parse_scene(json.loads(scene.model_dump_json())) == scene
    moved = scene_with(inline_mesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 1e-9]], normals=[(0.0, 0.0, 1.0)] * 3))
    assert parse_scene(moved) != scene


@pytest.mark.parametrize("index", [2**70, -(2**70)], ids=["past-int64", "below-int64"])
def test_inline_mesh_index_past_int64_is_out_of_range(index: int):
    err = parse_error(scene_with(inline_mesh(triangles=[[0, 1, 2], [0, index, 2]])))
    assert err.field == "shapes.1" and "triangles[1] indexes a vertex outside 0..2" in err.message


def test_inline_mesh_without_triangles_has_none():
    scene = parse_scene(scene_with(inline_mesh(triangles=[])))
    assert scene.shapes[1].triangles.shape == (0, 3)
    with pytest.raises(SceneError) as info:
        shape_triangles(scene, SCENES_DIR)
    assert (info.value.field, info.value.message) == ("shapes.1", "no triangles")


# -------------------------------------------------------------------------- limits
@pytest.mark.parametrize("k", [0, 1])
def test_resolution_above_max(k: int):
    d = minimal_scene()
    d["camera"]["resolution"][k] = MAX_RESOLUTION + 1
    err = parse_error(d)
    assert err.field == f"camera.resolution.{k}"


@pytest.mark.parametrize("k", [0, 1])
def test_resolution_zero(k: int):
    d = minimal_scene()
    d["camera"]["resolution"][k] = 0
    assert parse_error(d).field == f"camera.resolution.{k}"


def test_resolution_at_max_side_within_pixel_limit():
    d = minimal_scene()
    d["camera"]["resolution"] = [MAX_RESOLUTION, MAX_PIXELS // MAX_RESOLUTION]
    assert tuple(parse_scene(d).camera.resolution) == (MAX_RESOLUTION, MAX_PIXELS // MAX_RESOLUTION)
    d["camera"]["resolution"] = [MAX_RESOLUTION, MAX_PIXELS // MAX_RESOLUTION + 1]  # one row more is refused
    assert "pixels" in parse_error(d).message


def test_too_many_pixels():
    d = minimal_scene()
    d["camera"]["resolution"] = [MAX_RESOLUTION, MAX_RESOLUTION]
    assert MAX_RESOLUTION * MAX_RESOLUTION > MAX_PIXELS
    err = parse_error(d)
    assert err.field.startswith("camera")
    assert "pixels" in err.message


def test_too_many_inline_triangles(monkeypatch):
    monkeypatch.setattr(scene_mod, "MAX_TRIANGLES", 10)
    mesh = {"type": "mesh", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "triangles": [[0, 1, 2]] * 11,
            "material": "white"}
    err = parse_error(scene_with(mesh))
    assert err.field.startswith("shapes")
    assert err.field.startswith("shapes.1")


def test_inline_triangles_at_limit(monkeypatch):
    monkeypatch.setattr(scene_mod, "MAX_TRIANGLES", 10)
    mesh = {"type": "mesh", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "triangles": [[0, 1, 2]] * 10,
            "material": "white"}
    assert len(shape_triangles(parse_scene(scene_with(mesh)), SCENES_DIR)[1]) == 10


def test_too_many_triangles_across_shapes(monkeypatch):
    monkeypatch.setattr(scene_mod, "MAX_TRIANGLES", 10)
    d = scene_with(*[quad() for _ in range(6)])  # shapes 1..6, 2 triangles each: 12 > 10 at shape 6
    err = compile_error(d)
    assert err.field.startswith("shapes")
    assert err.field == "shapes.6"


def test_too_many_triangles_from_obj(monkeypatch, mesh_root: Path):
    monkeypatch.setattr(scene_mod, "MAX_TRIANGLES", 5)  # thing.obj has 6
    err = compile_error(scene_with(mesh_shape("meshes/thing.obj")), base_dir=mesh_root, root=mesh_root)
    assert err.field == "shapes.1"


def test_too_many_shapes():
    d = minimal_scene()
    d["shapes"] = [d["shapes"][0]] * (MAX_SHAPES + 1)  # the same dict, repeated: cheap
    err = parse_error(d)
    assert err.field == "shapes"


def test_max_shapes_is_allowed():
    d = minimal_scene()
    d["shapes"] = [d["shapes"][0]] * MAX_SHAPES
    assert len(parse_scene(d).shapes) == MAX_SHAPES


def test_too_many_lights():
    d = minimal_scene()
    d["lights"] = [d["lights"][0]] * (MAX_LIGHTS + 1)
    assert parse_error(d).field == "lights"
    d["lights"] = [d["lights"][0]] * MAX_LIGHTS
    assert len(parse_scene(d).lights) == MAX_LIGHTS


# -------------------------------------------------------------------------- camera
def test_camera_look_at_equals_position():
    d = minimal_scene()
    d["camera"]["look_at"] = list(d["camera"]["position"])
    err = parse_error(d)
    assert err.field == "camera"
    assert "look_at" in err.message


@pytest.mark.parametrize("up", [[0.0, 0.0, 1.0], [0.0, 0.0, -3.0], [0.0, 0.0, 0.0]],
                         ids=["parallel", "antiparallel", "zero"])
def test_camera_up_parallel_to_view(up):
    d = minimal_scene()  # views along +z
    d["camera"]["up"] = up
    err = parse_error(d)
    assert err.field == "camera"


@pytest.mark.parametrize("fov", [0.0, 180.0, -10.0])
def test_camera_bad_fov(fov: float):
    d = minimal_scene()
    d["camera"]["fov"] = fov
    assert parse_error(d).field == "camera.fov"


# -------------------------------------------------------------------------- lights
def test_spot_zero_direction():
    d = minimal_scene()
    d["lights"].append({"type": "spot", "position": [0, 2, 0], "direction": [0, 0, 0], "cone_angle": 30,
                        "power": [1, 1, 1]})
    assert parse_error(d).field == "lights.1.direction"


def test_directional_zero_direction():
    d = minimal_scene()
    d["lights"].append({"type": "directional", "direction": [0.0, 0.0, 0.0], "irradiance": [1, 1, 1]})
    assert parse_error(d).field == "lights.1.direction"


def test_unknown_light_type():
    d = minimal_scene()
    d["lights"].append({"type": "laser", "position": [0, 0, 0]})
    assert parse_error(d).field == "lights.1"


# ---------------------------------------------------------------- scene file / top level
@pytest.mark.parametrize("data", [[], "scene", 3, None])
def test_top_level_not_an_object(data):
    err = parse_error(data)
    assert err.field == "" and "dictionary" in err.message  # the whole document is at fault


def test_load_scene_file_not_json(tmp_path: Path):
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(SceneError, match="not valid JSON"):
        load_scene_file(p)


def test_load_scene_file_missing(tmp_path: Path):
    with pytest.raises(SceneError, match="not found"):
        load_scene_file(tmp_path / "nope.json")


# ----------------------------------------------------------------------------- CLI
def run_cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([str(PHOTONFARM), *args], capture_output=True, text=True, timeout=60, cwd=REPO, env=env)


def assert_clean_failure(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    for needle in needles:
        assert needle in proc.stderr, proc.stderr


def assert_one_line(proc: subprocess.CompletedProcess) -> None:
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr


def write_scene(path: Path, data: dict) -> Path:
    path.write_text(json.dumps(data))
    return path


@pytest.fixture(scope="module")
def cli_available():
    assert PHOTONFARM.exists(), f"{PHOTONFARM} not installed: run the tests through `make test`"


def test_cli_negative_radius(cli_available, tmp_path: Path):
    scene = write_scene(tmp_path / "bad.json", scene_with(sphere(radius=-1.0)))
    out = tmp_path / "x.png"
    proc = run_cli("render", str(scene), "--passes", "1", "--out", str(out))
    assert_clean_failure(proc, "shapes.1.radius")
    assert_one_line(proc)
    assert not out.exists()


def test_cli_nan_coordinate(cli_available, tmp_path: Path):
    scene = write_scene(tmp_path / "bad.json", scene_with(sphere(center=[0.0, float("nan"), 0.0])))
    proc = run_cli("render", str(scene), "--passes", "1", "--out", str(tmp_path / "x.png"))
    assert_clean_failure(proc, "shapes.1.center.1")
    assert_one_line(proc)


def test_cli_not_json(cli_available, tmp_path: Path):
    scene = tmp_path / "bad.json"
    scene.write_text("this is { not json")
    proc = run_cli("render", str(scene), "--passes", "1", "--out", str(tmp_path / "x.png"))
    assert_clean_failure(proc, "not valid JSON")
    assert_one_line(proc)


def test_cli_missing_file(cli_available, tmp_path: Path):
    proc = run_cli("render", str(tmp_path / "nope.json"), "--passes", "1", "--out", str(tmp_path / "x.png"))
    assert_clean_failure(proc, "not found")
    assert_one_line(proc)


def test_cli_unknown_bundled_scene(cli_available, tmp_path: Path):
    proc = run_cli("render", "no-such-scene", "--passes", "1", "--out", str(tmp_path / "x.png"))
    assert_clean_failure(proc, "no bundled scene", "no-such-scene")
    assert_one_line(proc)


def test_cli_mesh_escaping_the_scene_folder(cli_available, tmp_path: Path):
    """A mesh beside the scene file renders wherever the scene lives; one outside its folder
    is refused while loading, before the engine creates an OpenCL context."""
    (tmp_path / "m.obj").write_text(OBJ_TEXT)
    beside = write_scene(tmp_path / "ok.json", scene_with(mesh_shape("m.obj")))
    proc = run_cli("render", str(beside), "--passes", "1", "--resolution", "8x8", "--photons-per-pass", "1024",
                   "--out", str(tmp_path / "ok.png"))
    assert proc.returncode == 0, proc.stderr
    (tmp_path / "sub").mkdir()
    outside = write_scene(tmp_path / "sub" / "bad.json", scene_with(mesh_shape("../m.obj")))
    proc = run_cli("render", str(outside), "--passes", "1", "--out", str(tmp_path / "x.png"))
    assert_clean_failure(proc, "shapes.1.file", "leaves the scene's directory")
    assert_one_line(proc)


def test_cli_scene_path_is_a_directory(cli_available, tmp_path: Path):
    (tmp_path / "dir.json").mkdir()
    proc = run_cli("render", str(tmp_path / "dir.json"), "--passes", "1", "--out", str(tmp_path / "x.png"))
    assert_clean_failure(proc)
    assert_one_line(proc)


def test_cli_photons_per_pass_above_limit(cli_available, tmp_path: Path):
    from worker.settings import MAX_PHOTONS_PER_PASS

    proc = run_cli("render", "cornell-box", "--passes", "1", "--photons-per-pass", str(MAX_PHOTONS_PER_PASS + 1),
                   "--out", str(tmp_path / "x.png"))
    assert_clean_failure(proc, "--photons-per-pass")
    assert_one_line(proc)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--passes", "1", "--alpha", "1.5"], "--alpha"),
        (["--passes", "1", "--alpha", "0"], "--alpha"),
        (["--passes", "0"], "--passes"),
        (["--passes", "-3"], "--passes"),
        (["--seconds", "nan"], "--seconds"),
        (["--passes", "1", "--resolution", "10"], "--resolution"),
        (["--passes", "1", "--resolution", f"{MAX_RESOLUTION + 1}x16"], "--resolution"),
        (["--passes", "1", "--resolution", "0x16"], "--resolution"),
        (["--passes", "1", "--out-jpg"], "--out"),
        ([], "--passes"),
    ],
    ids=["alpha-1.5", "alpha-0", "passes-0", "passes-neg", "seconds-nan", "res-10", "res-too-big", "res-0",
         "out-jpg", "no-budget"],
)
def test_cli_bad_arguments(cli_available, tmp_path: Path, args: list[str], needle: str):
    out = str(tmp_path / "x.png")
    if "--out-jpg" in args:
        args = [a for a in args if a != "--out-jpg"]
        out = str(tmp_path / "x.jpg")
    proc = run_cli("render", "cornell-box", *args, "--out", out)
    assert_clean_failure(proc, needle)


def test_cli_resolution_override_respects_max_pixels(monkeypatch, tmp_path: Path):
    """--resolution must not bypass MAX_PIXELS (each side <= MAX_RESOLUTION is not enough).

    Run in-process with the engine replaced, so a failure cannot start a 16-Mpixel render.
    """
    import service.cli as cli

    def no_engine(*args, **kwargs):
        raise AssertionError("engine constructed for a resolution above MAX_PIXELS")

    monkeypatch.setattr("worker.engine.Engine", no_engine)
    res = f"{MAX_RESOLUTION}x{MAX_RESOLUTION}"
    try:
        rc = cli.main(["render", "cornell-box", "--passes", "1", "--resolution", res, "--out", str(tmp_path / "x.png")])
    except SystemExit as exc:  # an argparse error is fine too
        rc = exc.code
    assert rc == 2
