"""Mitsuba 3 XML details read as Mitsuba reads them, each checked against Mitsuba loading the
same file: where files are found (its file resolver), references by id, spectra, serialized
meshes, each bsdf plugin's parameters and defaults (and the Mitsuba peer's export of each of
our materials), and what cannot be honoured (one error naming the plugin and the line)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import assert_same_material, mitsuba_material, our_material
from worker.mitsuba_scene import convert_mitsuba
from worker.scene import SceneError, parse_scene
from worker.serialized import read_serialized, write_serialized

SENSOR = '<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>' \
         '<integer name="height" value="8"/></film></sensor>'


@pytest.fixture()
def mi():
    import mitsuba

    mitsuba.set_variant("scalar_rgb")
    mitsuba.set_log_level(mitsuba.LogLevel.Error)
    return mitsuba


def fan(path: Path, n: int) -> None:
    """A PLY of n triangles (its count tells which file was read)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["ply", "format ascii 1.0", f"element vertex {n + 2}", "property float x", "property float y",
             "property float z", f"element face {n}", "property list uchar int vertex_indices", "end_header"]
    lines += ["0 0 0"] + [f"{math.cos(t):.6f} {math.sin(t):.6f} 0" for t in np.linspace(0, 3, n + 1)]
    lines += [f"3 0 {i + 1} {i + 2}" for i in range(n)]
    path.write_text("\n".join(lines) + "\n")


def write(path: Path, body: str, sensor: bool = False) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'<scene version="3.0.0">{SENSOR if sensor else ""}{body}</scene>\n')
    return path


def ply(name: str) -> str:
    return f'<shape type="ply"><string name="filename" value="{name}"/></shape>'


def ours_counts(path: Path, root: Path | None = None) -> list[int]:
    return sorted(len(s["triangles"]) for s in convert_mitsuba(path, root=root)["shapes"] if s["type"] == "mesh")


def their_counts(mi, path: Path) -> list[int]:
    return sorted(s.face_count() for s in mi.load_file(str(path)).shapes())


@pytest.fixture()
def tree(tmp_path: Path) -> Path:
    """Files of the same name in several folders, told apart by their triangle counts."""
    for rel, n in [("a/m.ply", 1), ("b/m.ply", 2), ("sub/meshes/x.ply", 3), ("meshes/x.ply", 4), ("m.ply", 5),
                   ("sub/m.ply", 6), ("common/c.ply", 7)]:
        fan(tmp_path / rel, n)
    return tmp_path


@pytest.mark.parametrize("body, count", [
    ('<path value="a"/><path value="b"/>' + ply("m.ply"), 2),  # the last <path> is searched first
    (ply("c.ply") + '<path value="common"/>', 7),  # a <path> after the shape still applies
    ('<path value="a"/><path value="b"/><path value="a"/>' + ply("m.ply"), 1),
    ('<path value="a"/>' + ply("x.ply") + ply("meshes/x.ply"), None),  # x.ply is nowhere searched
])
def test_path_order_as_mitsuba(mi, tree: Path, body: str, count: int | None) -> None:
    path = write(tree / "scene.xml", body, sensor=True)
    if count is None:
        with pytest.raises(SceneError, match="'x.ply' not found"):
            convert_mitsuba(path)
        with pytest.raises(RuntimeError, match="not found"):
            mi.load_file(str(path))
        return
    assert ours_counts(path) == their_counts(mi, path) == [count]


def test_fragment_names_meshes_relative_to_the_main_file(mi, tree: Path) -> None:
    """A fragment in sub/ naming meshes/x.ply and m.ply gets the main folder's, though sub/
    has files of those names too (Mitsuba's own Cornell box relies on this)."""
    write(tree / "sub" / "frag.xml", ply("meshes/x.ply") + ply("m.ply"))
    path = write(tree / "scene.xml", '<include filename="sub/frag.xml"/>', sensor=True)
    assert ours_counts(path) == their_counts(mi, path) == [4, 5]


def test_fragment_path_and_includes(mi, tree: Path) -> None:
    """A <path> in a fragment is relative to it and finds its includes; an include is found
    beside the file that includes it; a main <path> then finds the mesh."""
    write(tree / "sub" / "lib" / "inner.xml", ply("c.ply"))
    write(tree / "sub" / "frag.xml", '<path value="lib"/><include filename="inner.xml"/>')
    path = write(tree / "scene.xml", '<path value="common"/><include filename="sub/frag.xml"/>', sensor=True)
    assert ours_counts(path) == their_counts(mi, path) == [7]


def test_fragment_folder_is_a_last_resort(tree: Path) -> None:
    """Mitsuba does not search a fragment's folder for meshes; we do, after everything it
    searches (the behaviour of earlier versions), so a scene Mitsuba loads reads the same files."""
    fan(tree / "sub" / "only.ply", 9)
    write(tree / "sub" / "frag.xml", ply("only.ply"))
    path = write(tree / "scene.xml", '<include filename="sub/frag.xml"/>', sensor=True)
    assert ours_counts(path) == [9]


@pytest.mark.parametrize("body", ['<path value=".."/>', '<path value="/"/>'])
def test_path_outside_the_root_is_refused(tree: Path, body: str) -> None:
    path = write(tree / "scene.xml", body + ply("m.ply"), sensor=True)
    with pytest.raises(SceneError, match="line 1: <path>: .* leaves the scene's directory"):
        convert_mitsuba(path)


def test_path_inside_a_wider_root(mi, tree: Path) -> None:
    """The service's root is the upload: a scene in a subfolder may reach ../common."""
    path = write(tree / "scenes" / "scene.xml", '<path value="../common"/>' + ply("c.ply"), sensor=True)
    assert ours_counts(path, root=tree) == their_counts(mi, path) == [7]
    with pytest.raises(SceneError, match="leaves the scene's directory"):
        convert_mitsuba(path)  # the default root: the scene's own folder


# ------------------------------------------------------------------------------ refs
def test_emitter_and_named_refs(mi, tmp_path: Path) -> None:
    body = ('<emitter type="area" id="glow"><rgb name="radiance" value="3, 2, 1"/></emitter>'
            '<bsdf type="diffuse" id="paint"><rgb name="reflectance" value="0.2, 0.4, 0.6"/></bsdf>'
            '<bsdf type="twosided" id="both"><ref id="paint"/></bsdf>'
            '<shape type="rectangle"><ref id="glow"/><ref name="bsdf" id="both"/></shape>')
    path = write(tmp_path / "scene.xml", body, sensor=True)
    shape = convert_mitsuba(path)["shapes"][0]
    params = mi.traverse(mi.load_file(str(path)))
    assert shape["emission"] == pytest.approx(list(params["glow.radiance.value"]), rel=1e-6)
    assert convert_mitsuba(path)["materials"][shape["material"]]["albedo"] == pytest.approx([0.2, 0.4, 0.6])


def test_unreferenced_named_objects_are_noted(mi, tmp_path: Path) -> None:
    """Mitsuba loads a scene-level area emitter or texture that nothing refers to and renders
    nothing of it; so do we, with a note."""
    body = ('<emitter type="area" id="spare"><rgb name="radiance" value="1"/></emitter>'
            '<texture type="checkerboard" id="tiles"/><shape type="sphere"/>')
    path = write(tmp_path / "scene.xml", body, sensor=True)
    notes: list[str] = []
    ours = convert_mitsuba(path, notes=notes)
    assert not mi.load_file(str(path)).emitters() and "emission" not in ours["shapes"][0]
    assert [n.split(" (")[0].split(": ")[-1] for n in notes] == ["id 'spare'", "id 'tiles'"], notes
    body = '<shape type="sphere" id="ball"/><shape type="sphere" id="other"/><emitter type="point" id="bulb"/>'
    notes.clear()
    convert_mitsuba(write(tmp_path / "scene.xml", body, sensor=True), notes=notes)
    assert [n.split(": ")[2] for n in notes] == ['<shape type="sphere">', '<emitter type="point">'], notes


@pytest.mark.parametrize("body, needle, says", [
    ('<texture type="checkerboard" id="t"/><bsdf type="roughplastic" id="p"><ref name="alpha" id="t"/></bsdf>',
     'name="alpha"', "a texture for 'alpha' is not supported on a roughplastic bsdf"),
    ('<texture type="checkerboard" id="t"/><shape type="sphere"><transform name="to_world"><rotate x="1" angle="30"/>'
     '</transform><bsdf type="diffuse"><ref name="reflectance" id="t"/></bsdf></shape>', 'type="sphere"',
     "a textured sphere's to_world may not rotate"),
    ('<bsdf type="mask" id="m"><float name="opacity" value="0.5"/></bsdf>', 'type="mask"',
     "mask takes exactly one nested bsdf"),
    ('<shape type="sphere"><medium type="homogeneous" name="interior"/></shape>', "homogeneous",
     "participating media"),
    ('<medium type="homogeneous" id="fog"/>', "fog", "participating media"),
    ('<shape type="hair"/>', "hair", "unknown shape plugin 'hair'"),
    ('<bsdf type="polarizer" id="p"/>', "polarizer", "unknown bsdf plugin 'polarizer'"),
    ('<shape type="sphere"><ref id="nothing"/></shape>', "nothing", "no object with id 'nothing'"),
    ('<shape type="instance"><ref id="g"/></shape>', 'id="g"', "no object with id 'g'"),
    ('<bsdf type="diffuse" id="d"><spectrum name="reflectance" value="500:0.5, 400:0.2"/></bsdf>', "500:",
     "wavelengths must increase"),
    ('<bsdf type="diffuse" id="d"><spectrum name="reflectance" type="blackbody"/></bsdf>', "blackbody",
     "is an emission"),
])
def test_what_cannot_be_honoured_names_plugin_and_line(tmp_path: Path, body: str, needle: str, says: str) -> None:
    path = tmp_path / "scene.xml"
    path.write_text('<scene version="3.0.0">\n' + SENSOR + "\n" + body.replace("><", ">\n<") + "\n</scene>\n")
    line = next(i for i, text in enumerate(path.read_text().splitlines(), 1) if needle in text)
    with pytest.raises(SceneError) as info:
        convert_mitsuba(path)
    assert f"line {line}:" in str(info.value) and says in str(info.value), str(info.value)


# ------------------------------------------------------------------------------ spectra
@pytest.mark.parametrize("spectrum", [
    'value="400:0.1, 500:0.5, 600:0.7, 700:0.2"',
    'value="0.35"',
    'value="380:0.9, 480:0.2, 560:0.05, 640:0.6, 780:0.1"',
    'filename="s.spd"',
])
@pytest.mark.parametrize("emission", [False, True])
def test_spectra_as_mitsuba(mi, tmp_path: Path, spectrum: str, emission: bool) -> None:
    (tmp_path / "s.spd").write_text("# comment\n400 0.3\n550 0.9  # green\n\n700 0.4\n")
    spec = f'<spectrum name="{"radiance" if emission else "reflectance"}" {spectrum}/>'
    body = (f'<shape type="rectangle"><emitter type="area">{spec}</emitter></shape>' if emission
            else f'<bsdf type="diffuse" id="d">{spec}</bsdf>')
    path = write(tmp_path / "scene.xml", body, sensor=True)
    ours = convert_mitsuba(path)
    params = mi.traverse(mi.load_file(str(path)))
    key = next(k for k in params.keys() if k.endswith("radiance.value" if emission else "reflectance.value"))
    got = ours["shapes"][0]["emission"] if emission else ours["materials"]["d"]["albedo"]
    np.testing.assert_allclose(got, np.broadcast_to(np.asarray(params[key], np.float64), (3,)), rtol=0.01, atol=1e-3)


def test_point_light_spectrum_is_an_emission(mi, tmp_path: Path) -> None:
    body = '<emitter type="point" id="p"><spectrum name="intensity" value="450:1, 650:3"/></emitter>'
    path = write(tmp_path / "scene.xml", body, sensor=True)
    power = np.array(convert_mitsuba(path)["lights"][0]["power"]) / (4 * math.pi)
    np.testing.assert_allclose(power, list(mi.traverse(mi.load_file(str(path)))["p.intensity.value"]), rtol=0.01)


# ------------------------------------------------------------------------------ serialized
def test_serialized_reader_against_mitsuba(mi, tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    v0, t0, n0 = rng.random((30, 3)), rng.integers(0, 30, (40, 3)), rng.normal(size=(30, 3))
    v1, t1 = rng.random((9, 3)), rng.integers(0, 9, (7, 3))
    (tmp_path / "m.serialized").write_bytes(write_serialized([(v0, t0, n0), (v1, t1, None)]))
    for index, n in enumerate([n0, None]):
        shape = read_serialized((tmp_path / "m.serialized").read_bytes(), index)
        theirs = mi.traverse(mi.load_dict({"type": "serialized", "filename": str(tmp_path / "m.serialized"),
                                           "shape_index": index}))
        np.testing.assert_allclose(shape.mesh.vertices, np.reshape(theirs["vertex_positions"], (-1, 3)), atol=1e-6)
        assert shape.mesh.triangles.tolist() == np.reshape(theirs["faces"], (-1, 3)).tolist()
        assert (shape.mesh.normals is None) == (n is None)


@pytest.mark.parametrize("scale", ['<scale value="2"/>', '<scale x="1" y="3" z="0.5"/>', '<scale x="-1"/>'],
                         ids=["uniform", "non-uniform", "mirrored"])
def test_vertex_normals_as_mitsuba_computes_them(mi, tmp_path: Path, monkeypatch, scale: str) -> None:
    """A serialized mesh without normals, rotated, scaled (uniformly, non-uniformly,
    mirrored) and moved: our angle-weighted vertex normals, computed a few triangles at a
    time (so steps meet inside the mesh), point where Mitsuba's do (directions compared)."""
    import trimesh

    from worker import mitsuba_scene

    monkeypatch.setattr(mitsuba_scene, "NORMALS_CHUNK", 7)
    ico = trimesh.creation.icosphere(subdivisions=2)
    vertices = ico.vertices * (1 + 0.2 * np.random.default_rng(8).random((len(ico.vertices), 1)))
    (tmp_path / "m.serialized").write_bytes(write_serialized([(vertices, ico.faces, None)]))
    path = write(tmp_path / "scene.xml", '<shape type="serialized"><string name="filename" value="m.serialized"/>'
                 f'<transform name="to_world"><rotate x="1" angle="30"/>{scale}<translate x="1"/>'
                 '</transform></shape>', sensor=True)
    ours = np.array(convert_mitsuba(path)["shapes"][0]["normals"])
    theirs = np.reshape(mi.traverse(mi.load_file(str(path)).shapes()[0])["vertex_normals"], (-1, 3))
    assert len(ours) == len(theirs) == len(vertices) > 7 * 20
    np.testing.assert_allclose(ours / np.linalg.norm(ours, axis=1, keepdims=True), theirs, atol=1e-5)


def test_serialized_errors_and_budget(tmp_path: Path, monkeypatch) -> None:
    data = write_serialized([(np.eye(3), [[0, 1, 2]], None)])
    (tmp_path / "m.serialized").write_bytes(data)
    shape = '<shape type="serialized"><string name="filename" value="m.serialized"/>{}</shape>'
    path = write(tmp_path / "scene.xml", shape.format('<integer name="shape_index" value="3"/>'), sensor=True)
    with pytest.raises(SceneError, match="shape_index 3 is outside 0..0"):
        convert_mitsuba(path)
    (tmp_path / "m.serialized").write_bytes(data[:6] + b"garbage" + data[13:])
    path = write(tmp_path / "scene.xml", shape.format(""), sensor=True)
    with pytest.raises(SceneError, match="m.serialized: "):
        convert_mitsuba(path)
    from worker import scene

    (tmp_path / "m.serialized").write_bytes(data)
    monkeypatch.setitem(scene.LOAD_LIMITS, "triangles", 0)
    with pytest.raises(SceneError, match="more than 0 triangles"):
        convert_mitsuba(path)


def test_cylinder_counts_against_the_triangle_limit(tmp_path: Path, monkeypatch) -> None:
    from worker import mitsuba_scene

    monkeypatch.setattr(mitsuba_scene, "MAX_TRIANGLES", 600)
    path = write(tmp_path / "scene.xml", '<shape type="cylinder"/><shape type="cylinder"/>', sensor=True)
    with pytest.raises(SceneError, match="more than 600 triangles"):
        convert_mitsuba(path)


def test_cylinder_flip_normals_and_area(tmp_path: Path) -> None:
    """An open tube of area 2 pi r h, its shading normals outward (inward when flipped)."""
    tube = '<shape type="cylinder"><float name="radius" value="0.5"/><point name="p1" x="0" y="2" z="0"/>{}</shape>'
    for flip, sign in (("", 1), ('<boolean name="flip_normals" value="true"/>', -1)):
        shape = convert_mitsuba(write(tmp_path / "scene.xml", tube.format(flip), sensor=True))["shapes"][0]
        v, t, n = (np.array(shape[k]) for k in ("vertices", "triangles", "normals"))
        tris = v[t]
        cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        assert 0.5 * np.linalg.norm(cross, axis=1).sum() == pytest.approx(2 * math.pi * 0.5 * 2, rel=1e-3)
        radial = v * [1, 0, 1]
        assert np.all(sign * np.sum(n * radial, axis=1) > 0)
        centre = tris.mean(axis=1) * [1, 0, 1]
        assert np.all(sign * np.sum(cross * centre, axis=1) > 0)  # winding agrees with the normals


# ------------------------------------------------------------------------------ bsdfs
BSDFS = {
    "diffuse": '<bsdf type="diffuse" id="m"/>',
    "conductor-defaults": '<bsdf type="conductor" id="m"/>',
    "conductor-none-tinted": '<bsdf type="conductor" id="m"><string name="material" value="none"/>'
                             '<rgb name="specular_reflectance" value="0.9, 0.8, 0.7"/></bsdf>',
    "conductor-rgb": '<bsdf type="conductor" id="m"><rgb name="eta" value="0.27, 0.68, 1.22"/>'
                     '<rgb name="k" value="3.61, 2.62, 2.29"/><rgb name="specular_reflectance" value="0.9"/></bsdf>',
    "conductor-float": '<bsdf type="conductor" id="m"><float name="eta" value="1.8"/>'
                       '<float name="k" value="4"/></bsdf>',
    "conductor-eta-only": '<bsdf type="conductor" id="m"><rgb name="eta" value="1.5, 1.2, 0.9"/></bsdf>',
    "conductor-k-only": '<bsdf type="conductor" id="m"><rgb name="k" value="2"/></bsdf>',  # eta 0: a mirror
    "conductor-spectra": '<bsdf type="conductor" id="m"><spectrum name="eta" value="400:0.2, 500:0.9, 700:1.1"/>'
                         '<spectrum name="k" value="380:4.5, 450:2.5, 600:3.3, 780:5.9"/></bsdf>',
    "conductor-spd-uniform": '<bsdf type="conductor" id="m"><spectrum name="eta" filename="eta.spd"/>'
                             '<spectrum name="k" type="uniform"><float name="value" value="2.5"/></spectrum></bsdf>',
    "roughconductor-defaults": '<bsdf type="roughconductor" id="m"/>',
    "roughconductor-ggx": '<bsdf type="roughconductor" id="m"><string name="distribution" value="ggx"/>'
                          '<float name="alpha" value="0.3"/><boolean name="sample_visible" value="false"/>'
                          '<rgb name="eta" value="1.66, 0.88, 0.52"/><rgb name="k" value="9.2, 6.3, 4.8"/>'
                          '<rgb name="specular_reflectance" value="0.8, 0.85, 0.9"/></bsdf>',
    "roughconductor-alpha-uv": '<bsdf type="roughconductor" id="m"><float name="alpha_u" value="0.2"/>'
                               '<float name="alpha_v" value="0.2"/></bsdf>',
    "dielectric-defaults": '<bsdf type="dielectric" id="m"/>',
    "dielectric-tints": '<bsdf type="dielectric" id="m"><string name="int_ior" value="diamond"/>'
                        '<float name="ext_ior" value="1.1"/><rgb name="specular_reflectance" value="0.9"/>'
                        '<rgb name="specular_transmittance" value="0.6, 0.8, 1"/></bsdf>',
    "dielectric-reflectance-only": '<bsdf type="dielectric" id="m">'
                                   '<rgb name="specular_reflectance" value="0.5"/></bsdf>',
    "roughdielectric-defaults": '<bsdf type="roughdielectric" id="m"/>',
    "roughdielectric-ggx": '<bsdf type="roughdielectric" id="m"><string name="distribution" value="ggx"/>'
                           '<float name="alpha" value="0.3"/><string name="int_ior" value="water"/>'
                           '<rgb name="specular_transmittance" value="0.6, 0.8, 1"/></bsdf>',
    "thindielectric-defaults": '<bsdf type="thindielectric" id="m"/>',
    "thindielectric-tints": '<bsdf type="thindielectric" id="m"><float name="int_ior" value="1.33"/>'
                            '<rgb name="specular_reflectance" value="0.7"/>'
                            '<spectrum name="specular_transmittance" value="400:0.3, 550:0.9, 700:0.5"/></bsdf>',
    "plastic-defaults": '<bsdf type="plastic" id="m"/>',
    "plastic-nonlinear": '<bsdf type="plastic" id="m"><rgb name="diffuse_reflectance" value="0.1, 0.3, 0.7"/>'
                         '<float name="int_ior" value="1.6"/><string name="ext_ior" value="water"/>'
                         '<rgb name="specular_reflectance" value="0.8"/>'
                         '<boolean name="nonlinear" value="true"/></bsdf>',
    "roughplastic-defaults": '<bsdf type="roughplastic" id="m"/>',
    "roughplastic-ggx": '<bsdf type="roughplastic" id="m"><string name="distribution" value="ggx"/>'
                        '<float name="alpha" value="0.25"/><boolean name="nonlinear" value="true"/>'
                        '<spectrum name="diffuse_reflectance" value="400:0.6, 700:0.1"/>'
                        '<float name="int_ior" value="1.9"/></bsdf>',
    "roughplastic-alpha-uv": '<bsdf type="roughplastic" id="m"><float name="alpha_u" value="0.3"/>'
                             '<float name="alpha_v" value="0.3"/></bsdf>',
    "twosided-plastic": '<bsdf type="twosided" id="m"><bsdf type="plastic">'
                        '<rgb name="diffuse_reflectance" value="0.2, 0.6, 0.3"/></bsdf></bsdf>',
}


@pytest.mark.parametrize("body", BSDFS.values(), ids=BSDFS.keys())
def test_bsdf_mapping_as_mitsuba(mi, tmp_path: Path, body: str) -> None:
    """Each bsdf plugin, with its defaults and with given values (rgb, float, spectra), becomes
    the material of the same parameters as `mi.traverse` gives for the same file (within 1%).
    A conductor's eta and k spectra convert as Mitsuba's RGB variants convert them (D65,
    unclamped above)."""
    (tmp_path / "eta.spd").write_text("400 1.4\n550 0.9\n700 0.3\n")
    path = write(tmp_path / "scene.xml", body + '<shape type="sphere"><ref id="m"/></shape>', sensor=True)
    ours = our_material(parse_scene(convert_mitsuba(path)).materials["m"])
    theirs = mitsuba_material(mi, mi.load_file(str(path)).shapes()[0].bsdf())
    assert_same_material(ours, theirs)


def test_conductor_k_without_eta_is_noted(tmp_path: Path) -> None:
    notes: list[str] = []
    convert_mitsuba(write(tmp_path / "scene.xml", BSDFS["conductor-k-only"], sensor=True), notes=notes)
    assert len(notes) == 1 and "k (with eta 0" in notes[0], notes


@pytest.mark.parametrize("body, needle, says, mitsuba_loads", [
    ('<bsdf type="conductor" id="c"><rgb name="eta" value="1"/><rgb name="k" value="2"/>'
     '<float name="ext_ior" value="1.33"/></bsdf>', "ext_ior", "a conductor takes no ext_ior", False),
    ('<bsdf type="roughconductor" id="c"><float name="alpha_u" value="0.1"/><float name="alpha_v" value="0.3"/>'
     '</bsdf>', "roughconductor", "anisotropic", True),
    ('<bsdf type="roughconductor" id="c"><float name="alpha_u" value="0.1"/></bsdf>', "alpha_u",
     "both alpha_u and alpha_v", False),
    ('<bsdf type="roughplastic" id="c"><float name="alpha" value="0.1"/><float name="alpha_u" value="0.1"/>'
     '<float name="alpha_v" value="0.1"/></bsdf>', "alpha_v", "give alpha, or both", False),
    ('<bsdf type="roughconductor" id="c"><string name="distribution" value="phong"/></bsdf>', "phong",
     "beckmann or ggx", False),
    ('<bsdf type="dielectric" id="c"><float name="int_ior" value="1"/><float name="ext_ior" value="1.5"/></bsdf>',
     "dielectric", "below 1 (the outside is denser)", True),
    ('<bsdf type="thindielectric" id="c"><float name="int_ior" value="4"/></bsdf>', "thindielectric",
     "must lie in [1, 3]", True),
    ('<bsdf type="twosided" id="c">\n<bsdf type="dielectric"/></bsdf>', 'type="dielectric"', "opaque bsdf", False),
    ('<bsdf type="plastic" id="c"><rgb name="diffuse_reflectance" value="1.2, 0.5, 0.5"/></bsdf>', "1.2",
     "diffuse_reflectance must lie in [0, 1]", False),
], ids=["conductor-ext-ior", "anisotropic", "alpha-u-alone", "alpha-and-uv",
        "distribution", "ior-below-1", "ior-above-3", "twosided-dielectric", "colour-above-1"])
def test_bsdf_refusals(mi, tmp_path: Path, body: str, needle: str, says: str, mitsuba_loads: bool) -> None:
    """What a bsdf holds that we cannot honour is one error naming it and its line; where
    Mitsuba refuses the file too, it does (`mitsuba_loads` False)."""
    path = tmp_path / "scene.xml"
    path.write_text('<scene version="3.0.0">\n' + SENSOR + "\n" + body + "\n</scene>\n")
    line = next(i for i, text in enumerate(path.read_text().splitlines(), 1) if needle in text)
    with pytest.raises(SceneError) as info:
        convert_mitsuba(path)
    assert f"line {line}:" in str(info.value) and says in str(info.value), str(info.value)
    if mitsuba_loads:
        mi.load_file(str(path))
    else:
        with pytest.raises(RuntimeError):
            mi.load_file(str(path))


PEER_MATERIALS = [
    {"type": "diffuse", "albedo": [0.2, 0.4, 0.6]},
    {"type": "mirror", "albedo": [0.9, 0.8, 0.7]},
    {"type": "glass", "ior": 1.7},
    {"type": "glass", "ior": 1.33, "albedo": [0.9, 0.9, 0.9], "transmittance": [0.5, 0.7, 1.0]},
    {"type": "rough_glass", "ior": 1.45, "alpha": 0.2, "distribution": "ggx", "transmittance": [0.9, 0.6, 0.3]},
    {"type": "thin_glass", "ior": 1.45, "albedo": [0.8, 0.8, 0.8], "transmittance": [0.9, 0.6, 0.3]},
    {"type": "conductor", "specular": [0.95, 0.9, 0.85], "eta": [0.27, 0.68, 1.22], "k": [3.61, 2.62, 2.29]},
    {"type": "conductor"},
    {"type": "rough_conductor", "eta": [1.66, 0.88, 0.52], "k": [9.2, 6.3, 4.8], "alpha": 0.3, "distribution": "ggx"},
    {"type": "rough_conductor", "specular": [0.5, 0.6, 0.7]},
    {"type": "plastic", "albedo": [0.1, 0.3, 0.7], "specular": [0.8, 0.8, 0.8], "ior": 1.6, "nonlinear": True},
    {"type": "plastic"},
    {"type": "rough_plastic", "alpha": 0.25, "distribution": "ggx", "ior": 2.1},
    {"type": "rough_plastic", "albedo": [0.7, 0.6, 0.1], "nonlinear": True},
]


@pytest.mark.parametrize("material", PEER_MATERIALS, ids=lambda m: m["type"])
def test_peer_exports_each_material_as_mitsuba_reads_it(mi, material: dict) -> None:
    """bench/mitsuba_peer.py's bsdf for each of our materials is, by `mi.traverse`, the
    material itself: the peer and the importer are inverses. (`glossy` is the one
    approximation, tested by its lobe width in tests/test_scene_import.py.)"""
    from bench.mitsuba_peer import _bsdf

    ours = parse_scene({"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0]}, "materials": {"m": material},
                        "shapes": [{"type": "sphere", "center": [0, 0, 0], "radius": 1, "material": "m"}]})
    exported = _bsdf(ours.materials["m"])
    theirs = mitsuba_material(mi, mi.load_dict(exported))
    expected = our_material(ours.materials["m"])
    if expected["type"] == "conductor" and "eta" not in expected:  # Mitsuba's eta 0: the same surface as a mirror
        expected = {"type": "mirror", "albedo": expected["specular"]}
    assert_same_material(expected, theirs)
    assert (exported["type"] == "twosided") == (material["type"] not in ("glass", "rough_glass", "thin_glass"))
