"""The environment light (kernels/environment.cl): its sampling agrees with its own pdf and
radiance lookup, its radiance is Mitsuba 3's envmap's, a convex diffuse object under a
constant sky has radiance rho L everywhere (and a lossless mirror or glass ball L), and a
scene lit by an envmap from an EXR renders as Mitsuba renders the same XML file (image
means within 2%, 8x8 blocks within the combined noise), for sppm, vcm and bpt.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pyopencl as cl
import pytest

from kernels.contract import build_options
from kernels.program import KERNEL_DIR, PREAMBLE, SOURCES
from tests.analytic import camera_rays
from tests.conftest import image, render
from tests.helpers import PEER_BIAS, assert_matches_block_by_block, mitsuba_renders
from tests.test_bsdf_consistency import grid_directions
from worker.engine import Engine
from worker.images import Pixels
from worker.integrators.photon_mapping import sum_layout
from worker.mitsuba_scene import convert_mitsuba
from worker.scene import SceneError, load_any_scene, parse_scene
from worker.scene_arrays import compile_scene
from worker.settings import Settings

PROBE = """
__kernel void probe_env_sample(__global const float4* emitters, int k, __global float4* dirs,
                               __global float4* looked_up) {
    int i = get_global_id(0);
    Rng rng = rng_make(11UL, 0u, (uint)i, 9UL);
    float u1 = rng_float(&rng), u2 = rng_float(&rng);
    float pdf;
    float3 w = env_sample(emitters, k, u1, u2, &pdf);
    dirs[i] = (float4)(w, pdf);
    looked_up[i] = (float4)(env_radiance(emitters, k, w), env_pdf(emitters, k, w));
}

__kernel void probe_env_eval(__global const float4* emitters, int k, __global const float4* dirs,
                             __global float4* out) {
    int i = get_global_id(0);
    float3 w = dirs[i].xyz;
    out[i] = (float4)(env_radiance(emitters, k, w), env_pdf(emitters, k, w));
}
"""
SAMPLES = 1 << 20
# to_world of the test's sky: a turn about y, then a tilt about x (a rotation, not the identity).
TURN = np.array([[math.cos(1.0), 0.0, math.sin(1.0)], [0.0, 1.0, 0.0], [-math.sin(1.0), 0.0, math.cos(1.0)]])
TILT = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(0.3), -math.sin(0.3)], [0.0, math.sin(0.3), math.cos(0.3)]])
TO_WORLD = TILT @ TURN


def sky_image(height: int = 64, width: int = 128) -> np.ndarray:
    """(height, width, 3) float32 lat-long radiance in Mitsuba's envmap layout: a blue sky
    brightening toward the zenith over a dark ground, and a bright sun-like blob (a Gaussian
    of 4 degrees) 40 degrees above the horizon."""
    theta = np.pi * np.arange(height) / (height - 1)
    phi = 2.0 * np.pi * (np.arange(width) + 0.5) / width
    t, p = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], axis=-1)
    up = np.clip(d[..., 1], 0.0, 1.0)[..., None]
    sky = np.where(d[..., 1:2] > 0.0, np.array([0.3, 0.5, 1.0]) * (0.4 + 0.6 * up), np.array([0.15, 0.12, 0.1]))
    sun_dir = np.array([math.cos(math.radians(40.0)) * math.sin(2.0), math.sin(math.radians(40.0)),
                        -math.cos(math.radians(40.0)) * math.cos(2.0)])
    angle = np.arccos(np.clip(d @ sun_dir, -1.0, 1.0))
    sun = 300.0 * np.exp(-0.5 * (angle / math.radians(4.0)) ** 2)[..., None] * np.array([1.0, 0.9, 0.7])
    return (sky + sun).astype(np.float32)


def write_exr(path: Path, pixels: np.ndarray) -> None:
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    height, width, channels = pixels.shape
    assert out.open(str(path), oiio.ImageSpec(width, height, channels, "float"))
    assert out.write_image(pixels)
    out.close()


def sky_scene(**light: object) -> dict:
    """A diffuse sphere lit by an environment light of fields `light` (the sky as `sky`)."""
    return {"camera": {"position": [0, 0, 4], "look_at": [0, 0, 0], "resolution": [16, 16]},
            "materials": {"white": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
            "shapes": [{"type": "sphere", "center": [0, 0, 0], "radius": 1, "material": "white"}],
            "textures": {"sky": {"type": "bitmap", "pixels": Pixels.of(sky_image()).model_dump()}},
            "lights": [{"type": "environment", **light}]}


# --------------------------------------------------------------------------- validation
@pytest.mark.parametrize("change, field", [
    (lambda d: d["lights"].append(dict(d["lights"][0])), "lights.1"),
    (lambda d: d["lights"][0].update(to_world=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]), "lights.0.to_world"),
    (lambda d: d["lights"][0].update(radiance=[1, 1, 1]), "lights.0"),
    (lambda d: d["lights"][0].update(map="nothing"), "lights.0.map"),
    (lambda d: d["textures"].update(sky={"type": "checkerboard"}), "lights.0.map"),
    (lambda d: d["textures"]["sky"].update(pixels=Pixels.of(-sky_image()).model_dump()), "textures.sky.pixels"),
    (lambda d: d["textures"]["sky"].update(pixels=Pixels.of(sky_image(2, 8)).model_dump()), "textures.sky.pixels"),
    (lambda d: d["textures"]["sky"].update(wrap_mode="clamp"), "textures.sky.wrap_mode"),
    (lambda d: d["textures"]["sky"].update(to_uv=[[2, 0, 0], [0, 1, 0]]), "textures.sky.to_uv"),
], ids=["two", "to_world", "both", "unknown-map", "not-bitmap", "negative", "too-small", "wrap-mode", "to-uv"])
def test_environment_errors_name_the_field(change, field: str) -> None:
    data = sky_scene(map="sky")
    change(data)
    with pytest.raises(SceneError) as err:
        parse_scene(data)
    assert err.value.field == field, err.value


def test_map_from_a_file(tmp_path: Path) -> None:
    """A JSON scene's sky may be an image file beside it: loading inlines it, and a scene that
    still names the file compiles to the same emitter table (the file read, inside the root)."""
    write_exr(tmp_path / "sky.exr", sky_image())
    data = sky_scene(map="sky", scale=2.0)
    data["textures"]["sky"] = {"type": "bitmap", "file": "sky.exr"}
    (tmp_path / "scene.json").write_text(json.dumps(data))
    inlined, base = load_any_scene(tmp_path / "scene.json")
    expected = compile_scene(inlined, base).emitters
    named = compile_scene(parse_scene(data), tmp_path, root=tmp_path).emitters
    np.testing.assert_array_equal(named, expected)
    with pytest.raises(SceneError) as err:
        compile_scene(parse_scene(data), tmp_path, root=tmp_path / "elsewhere")
    assert err.value.field == "textures.sky.file"


# ------------------------------------------------------------------- sampling and lookup
@pytest.fixture(scope="module")
def program(ctx: cl.Context) -> cl.Program:
    source = PREAMBLE + "\n".join((KERNEL_DIR / name).read_text() for name in SOURCES) + PROBE
    return cl.Program(ctx, source).build(options=["-cl-mad-enable", *build_options(sum_layout(False))])


def sky_table(ctx: cl.Context) -> tuple[cl.Buffer, np.int32]:
    """The emitter table of sky_scene (its sky under TO_WORLD) on the device, and the
    environment's record."""
    arrays = compile_scene(parse_scene(sky_scene(map="sky", to_world=TO_WORLD.tolist())), Path("."))
    buf = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=arrays.emitters)
    return buf, np.int32(len(arrays.emitter_cdf) - 1)


def lookup(ctx: cl.Context, program: cl.Program, dirs: np.ndarray) -> np.ndarray:
    """(n, 4): the sky's radiance and pdf toward each of `dirs` (n, 4)."""
    table, k = sky_table(ctx)
    queue = cl.CommandQueue(ctx)
    out = np.empty_like(dirs)
    dbuf = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=dirs)
    obuf = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, out.nbytes)
    cl.Kernel(program, "probe_env_eval")(queue, (len(dirs),), None, table, k, dbuf, obuf)
    cl.enqueue_copy(queue, out, obuf)
    return out


def test_sampling_agrees_with_its_pdf_and_radiance(ctx: cl.Context, program: cl.Program) -> None:
    """The direction a light sample draws has the density its pdf states: the pdf the
    sampler returns is the lookup's at that direction; the pdf integrates to 1 over the
    sphere; the estimate L / pdf of the samples is the quadrature of L (1%); and a histogram
    of the samples over coarse cells matches the pdf's integral over each (within 5 standard
    errors of the count, plus 1% for the quadrature)."""
    table, k = sky_table(ctx)
    queue = cl.CommandQueue(ctx)
    sampled, looked = np.empty((SAMPLES, 4), np.float32), np.empty((SAMPLES, 4), np.float32)
    sbuf = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, sampled.nbytes)
    lbuf = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, looked.nbytes)
    program.probe_env_sample(queue, (SAMPLES,), None, table, k, sbuf, lbuf)
    cl.enqueue_copy(queue, sampled, sbuf)
    cl.enqueue_copy(queue, looked, lbuf)
    queue.finish()
    rel = np.abs(sampled[:, 3] / looked[:, 3] - 1.0)
    assert np.median(rel) < 1e-4 and np.mean(rel > 1e-3) < 1e-3, (np.median(rel), np.mean(rel > 1e-3))

    dirs, cell = grid_directions()
    grid = lookup(ctx, program, dirs).astype(np.float64)
    assert grid[:, 3].sum() * cell == pytest.approx(1.0, rel=2e-3)
    quadrature = grid[:, :3].sum(axis=0) * cell
    estimate = (looked[:, :3].astype(np.float64) / sampled[:, 3:4]).mean(axis=0)
    np.testing.assert_allclose(estimate, quadrature, rtol=0.01)

    # Histogram over 16 x 32 cells of (z, phi), against the pdf's quadrature over each.
    z_bin = np.minimum(((sampled[:, 2] + 1.0) * 8.0).astype(int), 15)
    phi = np.mod(np.arctan2(sampled[:, 1], sampled[:, 0]), 2.0 * math.pi)
    p_bin = np.minimum((phi / (2.0 * math.pi) * 32).astype(int), 31)
    counts = np.bincount(z_bin * 32 + p_bin, minlength=512) / SAMPLES
    expected = (grid[:, 3] * cell).reshape(1024, 512)
    expected = expected.reshape(16, 64, 32, 16).sum(axis=(1, 3)).ravel()
    z_score = np.abs(counts - expected) / (np.sqrt(expected / SAMPLES) + 0.01 * expected)
    assert z_score.max() < 5.0, z_score.max()


def test_radiance_is_mitsubas_envmap(ctx: cl.Context, program: cl.Program, tmp_path: Path) -> None:
    """Toward any direction, the sky (under TO_WORLD) has the radiance Mitsuba 3's envmap
    gives for the same EXR and to_world, within float32 rounding."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    write_exr(tmp_path / "sky.exr", sky_image())
    matrix = np.eye(4)
    matrix[:3, :3] = TO_WORLD
    emitter = mi.load_dict({"type": "envmap", "filename": str(tmp_path / "sky.exr"),
                            "to_world": mi.ScalarTransform4f(matrix.tolist())})
    rng = np.random.default_rng(5)
    v = rng.normal(size=(2000, 3))
    dirs = np.zeros((len(v), 4), np.float32)
    dirs[:, :3] = v / np.linalg.norm(v, axis=1, keepdims=True)
    ours = lookup(ctx, program, dirs)[:, :3]
    theirs = []
    for d in dirs[:, :3].astype(np.float64):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-d))
        theirs.append(list(emitter.eval(si)))
    np.testing.assert_allclose(ours, np.array(theirs), rtol=2e-3, atol=1e-4)


# ------------------------------------------------------------------ analytic: rho L
RHO, SKY = np.array([0.8, 0.5, 0.2]), np.array([1.0, 2.0, 0.5])
CONVEX = {
    "sphere": [{"type": "sphere", "center": [0, 0, 0], "radius": 1.0, "material": "m"}],
    "cube": [{"type": "quad", "corner": c, "edge1": e1, "edge2": e2, "material": "m"} for c, e1, e2 in (
        ([-0.7, -0.7, 0.7], [1.4, 0, 0], [0, 1.4, 0]), ([-0.7, -0.7, -0.7], [0, 1.4, 0], [1.4, 0, 0]),
        ([0.7, -0.7, -0.7], [0, 1.4, 0], [0, 0, 1.4]), ([-0.7, -0.7, -0.7], [0, 0, 1.4], [0, 1.4, 0]),
        ([-0.7, 0.7, -0.7], [0, 0, 1.4], [1.4, 0, 0]), ([-0.7, -0.7, -0.7], [1.4, 0, 0], [0, 0, 1.4]))],
}


def coverage(engine: Engine, shape: str, sub: int = 16) -> np.ndarray:
    """(h, w): the share of each pixel's sub x sub rays that meet the object."""
    o, d = camera_rays(engine, sub)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    if shape == "sphere":
        b = d @ o
        hit = b * b - (o @ o - 1.0) > 0.0
    else:
        with np.errstate(divide="ignore"):
            t0, t1 = (-0.7 - o) / d, (0.7 - o) / d
        hit = np.minimum(t0, t1).max(axis=-1) < np.maximum(t0, t1).min(axis=-1)
    h, w = engine.arrays.height, engine.arrays.width
    return hit.reshape(h, sub, w, sub).mean(axis=(1, 3))


@pytest.mark.parametrize("method", ["sppm", "vcm", "bpt", "lt"])
@pytest.mark.parametrize("shape", ["sphere", "cube"])
def test_convex_object_under_constant_sky(ctx: cl.Context, shape: str, method: str) -> None:
    """A convex diffuse object sees only the sky over every point's hemisphere, so under a
    constant sky L its radiance is rho L everywhere: its pixels' mean within 1% per channel,
    every pixel within 5 standard errors of the pixels' spread (each channel)."""
    data = {"camera": {"position": [2.5, 2.0, 3.5], "look_at": [0, 0, 0], "fov": 40, "resolution": [32, 32]},
            "materials": {"m": {"type": "diffuse", "albedo": RHO.tolist()}},
            "shapes": CONVEX[shape], "lights": [{"type": "environment", "radiance": SKY.tolist()}]}
    engine = Engine(parse_scene(data), Path("."), Settings(method=method, photons_per_pass=1 << 15, seed=3), ctx=ctx)
    img = image(engine, render(engine, 128))
    share = coverage(engine, shape)
    inside = share == 1.0
    assert inside.sum() > 100
    pixels = img[inside] / (RHO * SKY)
    np.testing.assert_allclose(pixels.mean(axis=0), 1.0, rtol=0.01)
    spread = pixels.std(axis=0)
    assert (np.abs(pixels - 1.0) < 5.0 * spread + 0.01).all()
    # The sky seen past the object: L exactly, in every pixel the object comes nowhere near
    # (light tracing splats a vertex on the object to whichever pixel it falls in).
    padded = np.pad(share, 1)
    near = np.max([padded[1 + dy:padded.shape[0] - 1 + dy, 1 + dx:padded.shape[1] - 1 + dx]
                   for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
    sky = img[near == 0.0]
    assert len(sky) > 100
    np.testing.assert_allclose(sky, np.broadcast_to(SKY, sky.shape), rtol=1e-5)


@pytest.mark.parametrize("method", ["sppm", "vcm", "bpt", "lt"])
@pytest.mark.parametrize("material", [{"type": "mirror"}, {"type": "glass", "ior": 1.5}], ids=["mirror", "glass"])
def test_lossless_object_under_constant_sky(ctx: cl.Context, material: dict, method: str) -> None:
    """The sky seen through specular chains: a lossless mirror or glass ball under a constant
    sky L sends L on along every chain (reflected and refracted shares add up to L), so each
    of its pixels is L."""
    data = {"camera": {"position": [2.5, 2.0, 3.5], "look_at": [0, 0, 0], "fov": 40, "resolution": [32, 32]},
            "materials": {"m": material}, "shapes": CONVEX["sphere"],
            "lights": [{"type": "environment", "radiance": SKY.tolist()}]}
    engine = Engine(parse_scene(data), Path("."), Settings(method=method, photons_per_pass=1 << 12, seed=3), ctx=ctx)
    img = image(engine, render(engine, 8))
    ball = img[coverage(engine, "sphere") == 1.0]
    assert len(ball) > 100
    np.testing.assert_allclose(ball, np.broadcast_to(SKY, ball.shape), rtol=1e-3)


# ---------------------------------------------------------- side by side with Mitsuba 3
SKY_XML = """<?xml version="1.0"?>
<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="-1"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="45"/>
        <transform name="to_world"><lookat origin="0, 1.2, 4.2" target="0, 0.2, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="48"/>
            <rfilter type="box"/></film>
    </sensor>
    <emitter type="envmap">
        <string name="filename" value="sky.exr"/>
        <float name="scale" value="0.8"/>
        <transform name="to_world"><matrix value="{matrix}"/></transform>
    </emitter>
    <shape type="rectangle">
        <transform name="to_world"><scale value="2.5"/><rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.5, 0.5"/></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" value="-0.6, 0.5, 0"/><float name="radius" value="0.5"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.5, 0.3"/></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" value="0.6, 0.5, 0.2"/><float name="radius" value="0.5"/>
        <bsdf type="roughconductor">
            <string name="material" value="none"/><string name="distribution" value="ggx"/>
            <float name="alpha" value="0.2"/><rgb name="specular_reflectance" value="0.8, 0.8, 0.8"/>
        </bsdf>
    </shape>
</scene>
"""
RUNS = 6  # independent renders a side (tests/test_mitsuba_corpus.py's block check)


@pytest.fixture(scope="module")
def sky_xml(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """SKY_XML beside the EXR of sky_image it names, its to_world TO_WORLD."""
    folder = tmp_path_factory.mktemp("sky")
    write_exr(folder / "sky.exr", sky_image())
    matrix = np.eye(4)
    matrix[:3, :3] = TO_WORLD
    path = folder / "sky.xml"
    path.write_text(SKY_XML.replace("{matrix}", " ".join(repr(float(x)) for x in matrix.ravel())))
    return path


@pytest.fixture(scope="module")
def mitsuba_sky(sky_xml: Path) -> np.ndarray:
    return mitsuba_renders(sky_xml, RUNS)


def test_envmap_import(sky_xml: Path) -> None:
    """The envmap becomes our environment light: its image inline among the textures, its
    scale and to_world as written; a constant emitter its radiance."""
    ours = convert_mitsuba(sky_xml)
    [light] = ours["lights"]
    assert light["type"] == "environment" and light["scale"] == pytest.approx(0.8)
    np.testing.assert_allclose(light["to_world"], TO_WORLD, atol=1e-6)
    pixels = Pixels.model_validate(ours["textures"][light["map"]]["pixels"])
    np.testing.assert_array_equal(pixels.linear(), sky_image())
    constant = sky_xml.with_name("constant.xml")
    constant.write_text(re.sub(r'<emitter type="envmap">.*?</emitter>',
                               '<emitter type="constant"><rgb name="radiance" value="0.5, 1, 2"/></emitter>',
                               sky_xml.read_text(), flags=re.DOTALL))
    assert convert_mitsuba(constant)["lights"] == [{"type": "environment", "radiance": [0.5, 1.0, 2.0]}]
    scaled = sky_xml.with_name("scaled.xml")
    scaled.write_text(re.sub(r'<matrix value="[^"]*"/>', '<scale value="2"/>', sky_xml.read_text()))
    with pytest.raises(SceneError) as err:
        convert_mitsuba(scaled)
    line = next(i for i, text in enumerate(scaled.read_text().splitlines(), 1) if '<scale value="2"/>' in text)
    assert "must be a rotation" in str(err.value) and f"line {line}:" in str(err.value), err.value


@pytest.mark.parametrize("method", ["sppm", "vcm", "bpt"])
def test_envmap_matches_mitsuba_block_by_block(ctx: cl.Context, sky_xml: Path, mitsuba_sky: np.ndarray,
                                               method: str) -> None:
    """The sky scene by Mitsuba's path tracer and by us, RUNS independent renders each (ours
    32 passes): image means per channel within 2%, and every 8 x 8 block's luminance within 5
    combined standard errors of the two means plus BIAS of the block (as the corpus's check)."""
    scene, base = load_any_scene(sky_xml)
    mine = np.array([image(e, render(e, 32)) for e in (
        Engine(scene, base, Settings(method=method, photons_per_pass=1 << 16, seed=200 + s), ctx=ctx)
        for s in range(RUNS))])
    assert_matches_block_by_block(mine, mitsuba_sky, 0.02, PEER_BIAS[method])
