"""The eye pass's shortcut for disc coverage (kernels/eye_pass.cl, disc_may_be_cut): rays
are cast only where a conservative test finds a shape that could cut the gather disc.
Wherever it skips them, every ray would have found coverage 1, so a pass must come out
the same bit for bit as one that casts the rays at every point (COVERAGE_PRETEST = 0).
The scenes cover the test's cases: triangles of flat walls meeting in corners
(cornell-box, gap), convex sphere walls and balls on the floor (smallppm,
cornell-caustics), a concave sphere the points lie on (furnace), a smooth-shaded mesh
(ply-mesh). Radii of 3 R0 make many discs reach a wall."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

import kernels.contract
from kernels.contract import build_options
from kernels.program import KERNEL_DIR, PREAMBLE, SOURCES, create_context
from worker.engine import Engine
from worker.integrators.photon_mapping import GatherInputs
from worker.scene import bundled_scene_path, load_any_scene
from worker.settings import Settings

SCENES = {
    "cornell-box": bundled_scene_path("cornell-box"),
    "gap": bundled_scene_path("gap"),
    "smallppm": bundled_scene_path("smallppm"),
    "cornell-caustics": bundled_scene_path("cornell-caustics"),
    "furnace": bundled_scene_path("furnace"),
    "ply-mesh": Path(__file__).resolve().parents[1] / "scenes" / "mitsuba" / "ply-mesh.xml",
}


@pytest.fixture(scope="module")
def exhaustive_ctx():
    """A context of its own, so its program is built with the coverage rays cast everywhere."""
    return create_context()


@pytest.mark.parametrize("scene", SCENES)
def test_skipping_coverage_rays_changes_no_pass(make_engine, exhaustive_ctx, monkeypatch, scene) -> None:
    settings = dict(resolution=(48, 36), photons_per_pass=1 << 13, seed=11)
    fast = make_engine(SCENES[scene], **settings)
    monkeypatch.setattr(kernels.contract, "COVERAGE_PRETEST", 0)
    parsed, base = load_any_scene(SCENES[scene])
    exhaustive = Engine(parsed, base, Settings(**settings), ctx=exhaustive_ctx)
    inputs = GatherInputs(3.0 * fast.start().R0)
    a, b = fast.run_batch(inputs, 1, 2), exhaustive.run_batch(inputs, 1, 2)
    for name in a.sums:
        assert np.array_equal(a.sums[name], b.sums[name]), name
    # Not vacuous: the last pass's coverage is below 1 where a wall cuts the disc (a concave
    # sphere's own points excepted), and the pixels saw photons.
    point, weight = (np.empty((fast.arrays.n_pixels, 4), np.float32) for _ in range(2))
    cl.enqueue_copy(fast.device.queue, point, fast.passes.mp_pos)
    cl.enqueue_copy(fast.device.queue, weight, fast.passes.mp_wgt)
    coverage = weight[point[:, 3] > 0.0, 3]
    assert (a.D > 0).any() and len(coverage) > 0
    assert (coverage < 1.0).any() == (scene != "furnace"), np.unique(coverage)[:5]


@pytest.mark.parametrize("scene", ["cornell-box", "cornell-caustics"])
def test_skipping_coverage_rays_changes_no_vcm_pass(make_engine, exhaustive_ctx, monkeypatch, scene) -> None:
    """The same for vcm's merging, which tests the disc at every camera vertex that merged
    something (kernels/vcm_camera_pass.cl), about the side the path arrived from."""
    settings = dict(resolution=(32, 32), photons_per_pass=1 << 10, seed=11, method="vcm", initial_radius=40.0)
    fast = make_engine(SCENES[scene], **settings)
    monkeypatch.setattr(kernels.contract, "COVERAGE_PRETEST", 0)
    parsed, base = load_any_scene(SCENES[scene])
    exhaustive = Engine(parsed, base, Settings(**settings), ctx=exhaustive_ctx)
    inputs = fast.integrator.batch_inputs(fast.start())
    a, b = fast.run_batch(inputs, 0, 2), exhaustive.run_batch(inputs, 0, 2)
    assert (a.sums["C"] > 0).any()
    for name in a.sums:
        assert np.array_equal(a.sums[name], b.sums[name]), name


PROBE = """
__kernel void probe_may_be_cut(SCENE_PARAMS, __global const float4* points, __global const float4* normals,
                               __global int* out) {
    int i = get_global_id(0);
    SceneGeom g = SCENE_GEOM;
    out[i] = disc_may_be_cut(&g, points[i].xyz, normals[i].xyz, points[i].w);
}
"""


def test_pretest_skips_discs_no_wall_reaches(make_engine) -> None:
    """The shortcut must also prune, or every disc pays the rays (as it did on cornell-box,
    whose BVH leaves hold triangles of several walls: the leaf's box reached every point,
    and the side walls' triangles in it were taken as cutting discs far from them).
    Cornell-box's walls span 0..555; discs of radius 26 (vcm's R0 at 64 px)."""
    eng = make_engine("cornell-box", resolution=(16, 16), photons_per_pass=1 << 10)
    dev = eng.device
    r = 26.0
    cases = [  # (point, normal toward the eye, may a wall cut its disc)
        ((278.0, 0.0, 278.0), (0, 1, 0), False),     # the floor's centre
        ((508.0, 555.0, 4.0), (0, -1, 0), False),    # the ceiling, 47 from the red wall
        ((278.0, 273.0, 555.0), (0, 0, -1), False),  # the back wall's centre
        ((540.0, 0.0, 278.0), (0, 1, 0), True),      # the floor, 15 from the red wall
        ((278.0, 540.0, 555.0), (0, 0, -1), True),   # the back wall, 15 below the ceiling
    ]
    points = np.array([(*p, r) for p, _, _ in cases], np.float32)
    normals = np.array([(*n, 0.0) for _, n, _ in cases], np.float32)
    source = PREAMBLE + "\n".join((KERNEL_DIR / name).read_text() for name in SOURCES) + PROBE
    program = cl.Program(dev.ctx, source).build(options=["-cl-mad-enable", *build_options(eng.integrator.sums)])
    out = np.zeros(len(cases), np.int32)
    out_buf = dev.buffer(out.nbytes)
    program.probe_may_be_cut(dev.queue, (len(cases),), None, *dev.geometry, *dev.emitter_args,
                             dev.const(points), dev.const(normals), out_buf)
    cl.enqueue_copy(dev.queue, out, out_buf)
    assert out.astype(bool).tolist() == [cut for _, _, cut in cases]
