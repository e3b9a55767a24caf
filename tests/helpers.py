"""Helpers several test modules share: the `photonfarm render` command line; scene files
and the Cornell box's corner check against Mitsuba 3; a Mitsuba bsdf and one of our
materials stated in the same fields; a running job written straight into
the store (as the API and a worker's setup leave it), and the sharded-state setup of
tests/test_sharded_state.py and tests/test_lost_deltas.py (its deltas are the `deltas`
fixture of tests/conftest.py)."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import redis
from pydantic import BaseModel

from kernels.contract import LUMINANCE
from tests.analytic import camera_rays, spot_plane_scene
from worker.engine import Engine
from worker.image_io import read_image
from worker.integrators.base import Delta
from worker.settings import Settings
from worker.store import Batch, Jobs, keys
from worker.store.tiles import as_sent

PHOTONFARM = Path(sys.executable).parent / "photonfarm"  # installed beside the running interpreter
SMALL = ["--resolution", "16x16", "--photons-per-pass", "4096"]  # `photonfarm render` options of a quick image


def render_cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """`photonfarm render ARGS`, its output captured as text."""
    return subprocess.run([str(PHOTONFARM), "render", *args], capture_output=True, text=True, timeout=timeout)


def spot_scene(tmp_path: Path) -> Path:
    """A spot light over a plane, 75% of the image outside its cone (tests/analytic.py)."""
    path = tmp_path / "spot.json"
    path.write_text(json.dumps(spot_plane_scene()))
    return path


CORNELL_CORNERS = Path(__file__).resolve().parent.parent / "bench" / "reference" / "cornell-box-corners-96x96.exr"
BOX = 555.0  # the Cornell box's walls: x = 0, x = BOX, y = 0, y = BOX, z = BOX (open at z = 0)


def concave_corner_pixels(eng: Engine, band: float, sub: int = 4) -> np.ndarray:
    """(H, W) mask of the pixels whose whole footprint (sub x sub rays) sees a wall within
    `band` of a perpendicular wall: the Cornell box's concave corners."""
    w, h = eng.arrays.width, eng.arrays.height
    o, d = camera_rays(eng, sub)
    walls = [(0, 0.0), (0, BOX), (1, 0.0), (1, BOX), (2, BOX)]
    t_hit, wall_hit = np.full(d.shape[:2], np.inf), np.full(d.shape[:2], -1)
    for k, (axis, c) in enumerate(walls):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c - o[axis]) / d[..., axis]
        inside = np.all(np.abs(o + t[..., None] * d - BOX / 2) <= BOX / 2 + 1e-3, axis=-1) & (t > 0) & (t < t_hit)
        t_hit, wall_hit = np.where(inside, t, t_hit), np.where(inside, k, wall_hit)
    p = o + t_hit[..., None] * d
    gap = np.full(d.shape[:2], np.inf)
    for k, (axis, c) in enumerate(walls):
        gap = np.where(wall_hit != k, np.minimum(gap, np.abs(p[..., axis] - c)), gap)
    return (np.isfinite(t_hit) & (gap < band)).reshape(h, sub, w, sub).all(axis=(1, 3))


def assert_corners_match_mitsuba(eng: Engine, img: np.ndarray) -> None:
    """A 96x96 cornell-box image's pixels within 10 and within 30 (of 555) of a concave
    corner, per channel, within 3% of Mitsuba 3's path tracer (CORNELL_CORNERS)."""
    ref = read_image(CORNELL_CORNERS)[..., :3]
    for band in (10.0, 30.0):
        corners = concave_corner_pixels(eng, band)
        assert corners.sum() > 150
        ratio = img[corners].mean(axis=0) / ref[corners].mean(axis=0)
        np.testing.assert_array_less(np.abs(ratio - 1.0), 0.03, err_msg=f"band {band}: {ratio}")


# The sharded setup: the main Redis and SHARDS state nodes; the W x H frame in tiles of
# TILE pixels has 6 tiles, two on each node; BATCHES deltas of 2 passes each.
SHARDS = 3
TILE = 512
W, H = 64, 48
BATCHES = 12


def running_job(store: Jobs, w: int, h: int, r0: np.ndarray | float = 0.05, settings: Settings | None = None,
                scene: dict | None = None, scene_name: str | None = None, started: float = 1.0) -> str:
    """A job of w x h pixels (default settings: 1000 passes), its setup written with radius
    `r0` (an array, or one radius for every pixel) and its record running since `started`:
    what batches merge into. Returns its id."""
    settings = settings or Settings(max_passes=1000)
    job_id = store.create(scene or {}, settings, w, h, scene_name)
    store.init_setup(store.get(job_id), {"R0": np.broadcast_to(np.asarray(r0, np.float64), w * h).copy()})
    store.r.hset(keys.job(job_id), mapping={"status": "running", "started": started})
    return job_id


def sharded_store(urls: list[str]) -> Jobs:
    """The store over the main Redis (urls[0]) and the state nodes (the rest), in TILE-pixel tiles."""
    return Jobs(redis.Redis.from_url(urls[0]), [redis.Redis.from_url(u) for u in urls[1:]], tile_pixels=TILE)


def caustics_job(store: Jobs, scene: dict, settings: Settings, r0: np.ndarray, max_passes: int = 1000) -> str:
    """A running W x H cornell-caustics job (the `deltas` fixture's scene) of `max_passes`, no time limit."""
    return running_job(store, W, H, r0, settings.model_copy(update={"max_passes": max_passes, "max_seconds": None}),
                       scene, "cornell-caustics")


def merge_new(store: Jobs, job_id: str, d: Delta) -> None:
    """Merge a delta the job has not seen: the store must accept it."""
    assert store.merge(Batch(job_id, d.first_pass, d.n_passes), d, 0.1) == "merged"


def assert_folded_once(store: Jobs, job_id: str, made: list[Delta]) -> None:
    """After a final fold the record counts each delta of `made` once; every tile of the
    sharded job folded each of their batches once, holds nothing pending, lies on its own
    node only, stores exactly the arrays the deltas carried there (with R0 and N), and its
    state is the sum of the deltas as sent."""
    store.fold(job_id, wait=True, checkpoint=True)
    record = store.get(job_id)
    state = store.state(record)
    record = store.get(job_id)
    assert record.folded_passes == record.passes == sum(d.n_passes for d in made)
    assert record.folded_emitted == record.emitted == sum(d.emitted for d in made)
    assert not store.r.exists(keys.tofold(job_id))
    ids = {Batch(job_id, d.first_pass, d.n_passes).id.encode() for d in made}
    tiling = store.tiling(record)
    assert tiling.count == 6
    for k in range(tiling.count):
        node = store.tiles.nodes[tiling.node(k)]
        assert node.smembers(keys.tile(job_id, k, "folded")) == ids
        assert not node.exists(keys.tile(job_id, k, "pending"))
        for other in store.tiles.nodes:  # each tile on its own node only
            assert bool(other.exists(keys.tile(job_id, k, "state"))) == (other is node)
        # A tile stores the arrays its deltas carried (and N, derived from them, and R0): an
        # array no delta carried there (e.g. directly seen emission away from the light) is absent.
        span = tiling.span(k)
        carried = {name for d in made for name, a in d.sums.items() if a[span].any() and name in state.sums}
        stored = {f.decode() for f in node.hkeys(keys.tile(job_id, k, "state"))}
        assert stored == {"R0", "N"} | carried, (k, stored, carried)
    assert any("Ld" not in {n for d in made for n, a in d.sums.items() if a[tiling.span(k)].any()}
               for k in range(tiling.count))  # the check above sees a missing array somewhere
    sent = [as_sent(d.sums, tiling, record.integrator.sums.half) for d in made]
    for name in state.sums:
        expected = sum(d[name] for d in sent)
        np.testing.assert_allclose(getattr(state, name), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


# A Mitsuba 3 scene document around `body`, and a small perspective sensor for one.
def xml(body: str, version: str = "3.0.0") -> str:
    return f'<?xml version="1.0"?>\n<scene version="{version}">\n{body}\n</scene>\n'


SENSOR = """<sensor type="perspective"><float name="fov" value="40"/>
<transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
<film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film></sensor>"""


# Mitsuba 3's bsdf classes (as a loaded bsdf describes itself) and the material each becomes.
MITSUBA_BSDF_CLASSES = {"SmoothDiffuse": "diffuse", "SmoothConductor": "conductor", "RoughConductor": "rough_conductor",
                        "SmoothDielectric": "glass", "ThinDielectric": "thin_glass", "SmoothPlastic": "plastic",
                        "RoughPlastic": "rough_plastic", "RoughDielectric": "rough_glass"}


def mitsuba_material(mi, bsdf) -> dict:
    """A loaded Mitsuba bsdf (a `twosided` one's front) in our material's fields: the values of
    `mi.traverse`, Mitsuba's defaults where it lists none (1 for an unset reflectance or
    transmittance), and what it keeps out of traverse (distribution, nonlinear) from its description.
    A conductor of eta 0 reflects everything whatever k: a `mirror`, or a rough conductor without eta."""
    text = str(bsdf)
    kind = next(MITSUBA_BSDF_CLASSES[c] for c in re.findall(r"(\w+)\[", text) if c in MITSUBA_BSDF_CLASSES)
    params = {key.removeprefix("brdf_0."): value for key, value in mi.traverse(bsdf).items()}

    def rgb(name: str, default: float = 1.0) -> list[float]:
        return np.broadcast_to(np.asarray(params.get(f"{name}.value", default), np.float64), (3,)).tolist()

    def described(name: str) -> str:
        found = re.search(rf"\b{name} = (\w+)", text)
        assert found, (name, text)
        return found.group(1)

    if kind == "diffuse":
        return {"type": kind, "albedo": rgb("reflectance")}
    if kind in ("glass", "thin_glass", "rough_glass"):
        out = {"type": kind, "ior": float(params["eta"]), "albedo": rgb("specular_reflectance"),
               "transmittance": rgb("specular_transmittance")}
        if kind == "rough_glass":
            out.update(alpha=float(params["alpha.value"]), distribution=described("distribution"))
        return out
    if kind in ("plastic", "rough_plastic"):
        out = {"type": kind, "albedo": rgb("diffuse_reflectance"), "specular": rgb("specular_reflectance"),
               "ior": float(params["eta"]), "nonlinear": described("nonlinear") == "1"}
        if kind == "rough_plastic":
            out.update(alpha=float(params["alpha"]), distribution=described("distribution"))
        return out
    out = {"type": kind, "specular": rgb("specular_reflectance")}
    if any(rgb("eta", 0.0)):
        out.update(eta=rgb("eta", 0.0), k=rgb("k", 1.0))
    elif kind == "conductor":
        return {"type": "mirror", "albedo": out["specular"]}
    if kind == "rough_conductor":
        out.update(alpha=float(params.get("alpha.value", params.get("alpha_u.value", math.nan))),
                   distribution=described("distribution"))
    return out


def our_material(material: BaseModel) -> dict:
    """One of our materials (validated, so with its defaults) as `mitsuba_material` states
    Mitsuba's: a glass's transmittance is its albedo unless given; an unset eta and k left out,
    and an opacity of 1 (Mitsuba's bsdf without a mask)."""
    out = material.model_dump(exclude_none=True)
    if out.get("opacity") == 1.0:
        del out["opacity"]
    if out["type"] in ("glass", "rough_glass"):
        out.setdefault("transmittance", out["albedo"])
    return out


def assert_same_material(ours: dict, theirs: dict, rtol: float = 0.01) -> None:
    """The same fields; numbers within `rtol` (and 1e-3 absolute), the rest equal."""
    assert ours.keys() == theirs.keys(), (ours, theirs)
    for name, value in ours.items():
        if isinstance(value, (str, bool)):
            assert value == theirs[name], (name, ours, theirs)
        else:
            np.testing.assert_allclose(value, theirs[name], rtol=rtol, atol=1e-3, err_msg=f"{name}: {ours} {theirs}")


def block_luminance(img: np.ndarray) -> np.ndarray:
    """Per 8 x 8 block of an (h, w, 3) image: the mean luminance."""
    h, w, _ = img.shape
    return img.reshape(h // 8, 8, w // 8, 8, 3).mean(axis=(1, 3)) @ LUMINANCE


def mean_variance(runs: np.ndarray) -> np.ndarray:
    """Per block, the variance of the mean of independent runs (axis 0): the runs' spread,
    floored at the median block's relative spread (a spread from a few samples is small by
    chance in some block of many)."""
    mean, var = runs.mean(axis=0), runs.var(axis=0, ddof=1)
    return np.maximum(var, np.median(var / mean ** 2) * mean ** 2) / len(runs)


# Bias allowed a block against a peer, a fraction of its luminance: 2% for bpt, which is
# unbiased; 3% for sppm and 6% for vcm, whose radius after 32 passes still carries light
# into contact shadows and blurs caustics.
PEER_BIAS = {"sppm": 0.03, "vcm": 0.06, "bpt": 0.02}


def room_shell(floor: str) -> str:
    """Mitsuba XML of a closed 2 x 2 x 2 room about the origin: its floor of bsdf `floor`, the
    other walls of bsdf `white`, and a small square area light under the ceiling."""
    walls = [("floor", '<rotate x="1" angle="-90"/><translate y="-1"/>'),
             ("white", '<rotate x="1" angle="90"/><translate y="1"/>'), ("white", '<translate z="-1"/>'),
             ("white", '<rotate y="1" angle="90"/><translate x="-1"/>'),
             ("white", '<rotate y="1" angle="-90"/><translate x="1"/>'),
             ("white", '<rotate y="1" angle="180"/><translate z="1"/>')]
    shapes = [f'<shape type="rectangle"><transform name="to_world">{ops}</transform>'
              f'<ref id="{floor if kind == "floor" else kind}"/></shape>' for kind, ops in walls]
    light = ('<shape type="rectangle"><transform name="to_world"><scale x="0.25" y="0.25"/><rotate x="1" angle="90"/>'
             '<translate y="0.99"/></transform><bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>'
             '<emitter type="area"><rgb name="radiance" value="12"/></emitter></shape>')
    return "\n".join(shapes + [light])


def mitsuba_renders(path: Path, runs: int, **params: str) -> np.ndarray:
    """`runs` independent renders of a Mitsuba XML file by Mitsuba 3 itself (its own
    integrator, 1024 spp, seeds 0, 1, ...), rgb float64: the peer side of a block comparison."""
    import mitsuba

    mitsuba.set_variant("scalar_rgb")
    return np.array([np.array(mitsuba.render(mitsuba.load_file(str(path), **params), spp=1024, seed=s),
                              np.float64)[..., :3] for s in range(runs)])


def assert_matches_block_by_block(mine: np.ndarray, theirs: np.ndarray, mean_rtol: float, bias: float) -> None:
    """Independent renders of one scene by us and by a peer, (runs, h, w, 3) a side: image
    means per channel within `mean_rtol`, and every 8 x 8 block's luminance within 5 combined
    standard errors of the two means plus `bias` of the block."""
    np.testing.assert_allclose(mine.mean(axis=(0, 1, 2)), theirs.mean(axis=(0, 1, 2)), rtol=mean_rtol)
    a = np.array([block_luminance(x) for x in mine])
    b = np.array([block_luminance(x) for x in theirs])
    bound = 5.0 * np.sqrt(mean_variance(a) + mean_variance(b)) + bias * b.mean(axis=0)
    excess = np.abs(a.mean(axis=0) - b.mean(axis=0)) / bound
    assert excess.max() <= 1.0, (excess.max(), np.unravel_index(np.argmax(excess), excess.shape))
