"""The Mitsuba 3 XML corpus under scenes/mitsuba/ read by us and by Mitsuba 3 from the very
same file: colours, radiances, triangle counts, shape bounds and the camera agree with what
`mi.traverse` gives within 1%, and image means within 2% where both renders converge.

The corpus uses: search paths (`<path>` declared after its use, a fragment in a subfolder
naming its mesh relative to the main file and including its sibling), an area emitter
referenced by id, `<ref name>`, twosided over a reference, ignored sensor and film
properties, spectra (wavelength:value lists, a single value, an .spd file, blackbody),
serialized meshes (two shapes in one file, face normals), cylinders, disks, spheres,
instances of a shapegroup, and every bsdf plugin we read (plastic, roughplastic, conductor
and roughconductor with eta and k and with a named metal, thindielectric, a dielectric tinted
differently in reflection and transmission).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.conftest import image, render
from tests.helpers import (
    PEER_BIAS,
    assert_matches_block_by_block,
    assert_same_material,
    mitsuba_material,
    mitsuba_renders,
    our_material,
)
from worker.metals import METALS
from worker.mitsuba_scene import convert_mitsuba
from worker.scene import SCENES_DIR, parse_scene

CORPUS = SCENES_DIR / "mitsuba"


@pytest.fixture()
def mi():
    import mitsuba

    mitsuba.set_variant("scalar_rgb")
    mitsuba.set_log_level(mitsuba.LogLevel.Error)
    return mitsuba


def close(ours: object, theirs: object, rtol: float = 0.01) -> None:
    a = np.broadcast_to(np.asarray(ours, np.float64), (3,))
    b = np.broadcast_to(np.asarray(theirs, np.float64), (3,))
    np.testing.assert_allclose(a, b, rtol=rtol, atol=1e-3 * max(1.0, float(np.abs(b).max())))


def shape_bounds(shape: dict) -> np.ndarray:
    """(2, 3) bounds of one of our JSON shapes."""
    if shape["type"] == "sphere":
        c = np.array(shape["center"])
        return np.array([c - shape["radius"], c + shape["radius"]])
    if shape["type"] == "quad":
        c, e1, e2 = (np.array(shape[k]) for k in ("corner", "edge1", "edge2"))
        points = np.array([c, c + e1, c + e2, c + e1 + e2])
    else:
        points = np.array(shape["vertices"])
    return np.array([points.min(axis=0), points.max(axis=0)])


def union(boxes: list[np.ndarray]) -> np.ndarray:
    return np.array([np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)])


def their_bounds(scene) -> list[np.ndarray]:
    return [np.array([list(s.bbox().min), list(s.bbox().max)]) for s in scene.shapes()]


def faces(scene) -> int:
    """Triangles of Mitsuba's mesh shapes (rectangles, cubes, files)."""
    return sum(s.face_count() for s in scene.shapes() if s.is_mesh())


def test_spectral_box(mi) -> None:
    path = CORPUS / "spectral-box.xml"
    notes: list[str] = []
    ours = convert_mitsuba(path, notes=notes)
    params = mi.traverse(mi.load_file(str(path)))
    for name in ("grey", "rust", "teal", "lilac"):
        close(ours["materials"][name]["albedo"], params[f"{name}.reflectance.value"])
    close(ours["materials"]["floor"]["albedo"], params["grey.reflectance.value"])  # twosided over a <ref>
    radiance = params["lamp.radiance.value"]  # the scene-level emitter the light refers to
    [light] = [s for s in ours["shapes"] if "emission" in s]
    close(light["emission"], radiance)
    ignored = {line.split(" (")[0].split(": ")[-1] for line in notes}
    assert ignored == {"<integrator>", "<sampler>", "pixel_format", "component_format", "<rfilter>", "far_clip",
                       "shutter_open", "focus_distance"}, notes
    assert all(line.startswith("ignored: spectral-box.xml line ") for line in notes)


def test_camera_matches(mi) -> None:
    path = CORPUS / "spectral-box.xml"
    sensor = mi.load_file(str(path)).sensors()[0]
    cam = convert_mitsuba(path)["camera"]
    m = np.array(mi.traverse(sensor)["to_world"].matrix, np.float64)
    close(cam["position"], m[:3, 3])
    close(np.subtract(cam["look_at"], cam["position"]), m[:3, 2])
    close(cam["up"], m[:3, 1])
    width, height = cam["resolution"]
    x_fov = math.degrees(2 * math.atan(math.tan(math.radians(cam["fov"]) / 2) * width / height))
    assert x_fov == pytest.approx(float(mi.traverse(sensor)["x_fov"]), rel=1e-3)


def test_search_paths(mi) -> None:
    """The serialized file is found through a <path> that follows its use; the fragment's
    mesh relative to the main file; the fragment's sibling include beside it."""
    path = CORPUS / "search-paths.xml"
    scene = mi.load_file(str(path))
    ours = convert_mitsuba(path)
    triangles = sum(2 if s["type"] == "quad" else len(s["triangles"]) for s in ours["shapes"])
    assert triangles == faces(scene) == 6 * 2 + 8 + 12 + 320
    theirs = their_bounds(scene)
    extent = 2.0
    for shape in ours["shapes"][6:]:
        box = shape_bounds(shape)
        assert any(np.abs(box - t).max() < 0.01 * extent for t in theirs), box
    flat = [s for s in ours["shapes"] if s["type"] == "mesh" and len(s["triangles"]) == 12]
    assert len(flat) == 1 and "normals" not in flat[0]  # face_normals: flat shading


def test_instances(mi) -> None:
    """Each instance is its shapegroup's shapes through its to_world; cylinders and the disk
    land where Mitsuba's do (bounds within 1% of the room)."""
    path = CORPUS / "instances.xml"
    scene = mi.load_file(str(path))
    ours = convert_mitsuba(path)
    shapes = ours["shapes"]
    assert [s["type"] for s in shapes[6:]] == ["mesh", "sphere", "mesh", "sphere", "mesh", "mesh"]
    objects = [union([shape_bounds(s) for s in shapes[6:8]]), union([shape_bounds(s) for s in shapes[8:10]]),
               shape_bounds(shapes[10]), shape_bounds(shapes[11])]
    theirs = their_bounds(scene)
    for box in objects:
        assert any(np.abs(box - t).max() < 0.02 for t in theirs), (box, theirs)
    assert sum(2 for s in shapes if s["type"] == "quad") == faces(scene)
    assert shapes[6]["material"] == "white" and shapes[7]["material"] == shapes[9]["material"]


def test_materials(mi) -> None:
    """Each bsdf of materials.xml is the material of the same parameters as `mi.traverse`
    gives for it (within 1%), through a twosided wrapper too, a named metal's eta and k being
    worker/metals.py's, a mask's opacity Mitsuba's; the integrator and the rfilter are the notes."""
    path = CORPUS / "materials.xml"
    notes: list[str] = []
    ours = parse_scene(convert_mitsuba(path, notes=notes))
    scene = mi.load_file(str(path))
    bsdfs = {shape.bsdf().id(): shape.bsdf() for shape in scene.shapes()}
    kinds = {"plastic": "plastic", "roughplastic": "rough_plastic", "copper": "conductor",
             "panel": "rough_conductor", "pane": "thin_glass", "glass": "glass"}
    for name, kind in kinds.items():
        material = our_material(ours.materials[name])
        assert material["type"] == kind
        assert_same_material(material, mitsuba_material(mi, bsdfs[name]))
    for name, (kind, metal) in {"gold": ("conductor", "Au"), "rough-copper": ("rough_conductor", "Cu")}.items():
        material, theirs = our_material(ours.materials[name]), mitsuba_material(mi, bsdfs[name])
        assert material["type"] == kind
        assert material.pop("eta") == METALS[metal].eta and material.pop("k") == METALS[metal].k
        del theirs["eta"], theirs["k"]  # Mitsuba's own data: reflectance within 2% (tests/test_named_metals.py)
        assert_same_material(material, theirs)
    veil = ours.materials["veil"]
    assert veil.type == "diffuse" and veil.opacity == pytest.approx(mi.traverse(bsdfs["veil"])["opacity.value"])
    assert ours.materials["panel"].distribution == "ggx"
    assert ours.materials["glass"].transmittance != ours.materials["glass"].albedo
    spheres = [s for s in ours.shapes if s.type == "sphere"]
    assert len(spheres) == sum(not s.is_mesh() for s in scene.shapes()) == 6
    assert 2 * (len(ours.shapes) - len(spheres) - 1) + 12 == faces(scene)  # quads and the cube (Mitsuba merges meshes)
    assert [line.split(" (")[0].split(": ")[-1] for line in notes] == ["<integrator>", "<rfilter>"], notes


def test_blackbody_matches_a_spectral_render(mi) -> None:
    """Mitsuba's RGB variants refuse blackbody spectra; its spectral variant renders the
    emitter filling the view, and its image (sRGB through the CIE functions) is the
    emitter's radiance."""
    path = CORPUS / "blackbody.xml"
    radiance = convert_mitsuba(path)["shapes"][0]["emission"]
    mi.set_variant("scalar_spectral")
    try:
        peer = np.array(mi.render(mi.load_file(str(path)), spp=1024, seed=3))[..., :3].mean(axis=(0, 1))
    finally:
        mi.set_variant("scalar_rgb")
    close(radiance, peer, rtol=0.01)


@pytest.mark.parametrize("name", ["spectral-box", "instances", "search-paths"])
def test_image_mean_matches_mitsuba(make_engine, mi, name: str) -> None:
    """Same file, two renderers, at the file's resolution (32 x 32; materials.xml 64 x 64):
    image means per channel within 2%. 128 passes: the
    corpus's objects sit near the floor, where SPPM's finite radius carries light into the
    contact shadows (a bias that shrinks with the radius, pass by pass)."""
    path = CORPUS / f"{name}.xml"
    peer = np.array(mi.render(mi.load_file(str(path)), spp=256, seed=1), dtype=np.float64)[..., :3]
    engine = make_engine(path, photons_per_pass=1 << 16, seed=1)
    ours = image(engine, render(engine, 128))
    assert ours.shape == peer.shape
    np.testing.assert_allclose(ours.mean(axis=(0, 1)), peer.mean(axis=(0, 1)), rtol=0.02)


RUNS = 6  # independent renders a side: the spread of a block between them is its noise


@pytest.fixture(scope="module")
def mitsuba_materials() -> np.ndarray:
    return mitsuba_renders(CORPUS / "materials.xml", RUNS)


@pytest.mark.parametrize("method", ["sppm", "vcm", "bpt"])
def test_materials_match_mitsuba_block_by_block(make_engine, mitsuba_materials: np.ndarray, method: str) -> None:
    """materials.xml (every bsdf plugin we read) by Mitsuba's path tracer and by us, RUNS
    independent renders each (ours 32 passes): image means per channel within 2%, and every
    8 x 8 block's luminance within 5 combined standard errors of the two means plus PEER_BIAS of
    the block: 2% for bpt, which is unbiased; 3% for sppm and 6% for vcm, whose radius after
    32 passes still carries light into the contact shadows under the balls and blurs the
    caustic beneath the glass one."""
    ours = []
    for s in range(RUNS):
        engine = make_engine(CORPUS / "materials.xml", method=method, seed=100 + s)
        ours.append(image(engine, render(engine, 32)))
    mine = np.array(ours)
    assert_matches_block_by_block(mine, mitsuba_materials, 0.02, PEER_BIAS[method])
