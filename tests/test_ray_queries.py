"""The ray queries' shortcuts (kernels/geometry.cl) answer bit for bit as what they replace:
the spelled-out dot, cross, fmin and fmax of the triangle and box tests give the builtins'
bits (PoCL calls its builtins out of line, so the hot loops avoid them), and the any-hit
visibility query `occluded` gives intersect_within(...).surf != SURF_NONE. Both keep every
image the same; these tests catch a change that would make them differ (an fma contraction,
a NaN rule, a traversal that prunes by a different bound)."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

from kernels.contract import build_options
from kernels.program import KERNEL_DIR, PREAMBLE, SOURCES

PROBE = """
__kernel void probe_builtins(__global const float4* a, __global const float4* b, __global float4* spelled,
                             __global float4* builtin) {
    int i = get_global_id(0);
    float3 x = a[i].xyz, y = b[i].xyz;
    float3 c = cross3(x, y), d = cross(x, y);
    spelled[2 * i] = (float4)(c, dot3(x, y));
    builtin[2 * i] = (float4)(d, dot(x, y));
    spelled[2 * i + 1] = (float4)(min1(a[i].w, b[i].w), max1(a[i].w, b[i].w), min1(a[i].x, b[i].w),
                                  max1(a[i].x, b[i].w));
    builtin[2 * i + 1] = (float4)(fmin(a[i].w, b[i].w), fmax(a[i].w, b[i].w), fmin(a[i].x, b[i].w),
                                  fmax(a[i].x, b[i].w));
}

__kernel void probe_occluded(SCENE_PARAMS, __global const float4* origins, __global const float4* dirs,
                             __global int* any_hit, __global int* closest_hit) {
    int i = get_global_id(0);
    SceneGeom g = SCENE_GEOM;
    float3 o = origins[i].xyz, d = dirs[i].xyz;
    float tmax = origins[i].w;
    any_hit[i] = occluded(&g, o, d, tmax);
    closest_hit[i] = intersect_within(&g, o, d, tmax).surf != SURF_NONE;
}
"""


def _program(eng) -> cl.Program:
    source = PREAMBLE + "\n".join((KERNEL_DIR / name).read_text() for name in SOURCES) + PROBE
    return cl.Program(eng.device.ctx, source).build(options=["-cl-mad-enable", *build_options(eng.integrator.sums)])


def test_spelled_out_builtins_give_the_builtins_bits(make_engine) -> None:
    eng = make_engine("cornell-box", resolution=(8, 8), photons_per_pass=1 << 10)
    dev = eng.device
    rng = np.random.default_rng(5)
    n = 1 << 14
    a = (rng.standard_normal((n, 4)) * 10.0 ** rng.integers(-6, 7, (n, 4))).astype(np.float32)
    b = (rng.standard_normal((n, 4)) * 10.0 ** rng.integers(-6, 7, (n, 4))).astype(np.float32)
    special = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e-45, -1e-45, 3.4e38], np.float32)
    a[: n // 4, 3] = rng.choice(special, n // 4)  # the min/max lanes meet NaN, infinities, signed zeros
    b[n // 8: n // 2, 3] = rng.choice(special, 3 * n // 8)
    a[n // 2: n // 2 + 64, 0] = special[np.arange(64) % len(special)]
    spelled, builtin = (np.empty((2 * n, 4), np.float32) for _ in range(2))
    bufs = dev.buffer(spelled.nbytes), dev.buffer(builtin.nbytes)
    _program(eng).probe_builtins(dev.queue, (n,), None, dev.const(a), dev.const(b), *bufs)
    cl.enqueue_copy(dev.queue, spelled, bufs[0])
    cl.enqueue_copy(dev.queue, builtin, bufs[1])
    assert np.array_equal(spelled.view(np.uint32), builtin.view(np.uint32))
    assert np.isnan(builtin[1::2, :2]).sum() > 0  # not vacuous: both NaN operands were met


@pytest.mark.parametrize("scene", ["cornell-box", "gap", "smallppm", "cornell-caustics"])
def test_occluded_answers_as_the_closest_hit_query(make_engine, scene) -> None:
    """Random rays from inside the scene's bounds (triangles and spheres), with bounds from
    0 to beyond the scene, infinity included."""
    eng = make_engine(scene, resolution=(8, 8), photons_per_pass=1 << 10)
    dev, arr = eng.device, eng.arrays
    corners = np.concatenate([arr.node_lo[:, :3], arr.node_hi[:, :3]]) if len(arr.node_lo) else None
    if corners is None or len(arr.spheres):  # smallppm's walls are spheres: its scene lies within 0..100
        lo, hi = np.zeros(3), np.full(3, 100.0)
    else:
        lo, hi = corners.min(axis=0), corners.max(axis=0)
    rng = np.random.default_rng(7)
    n = 1 << 14
    size = float(np.linalg.norm(hi - lo))
    tmax = rng.uniform(0.0, 1.2 * size, n)
    tmax[::16] = np.inf
    origins = np.column_stack([rng.uniform(lo, hi, (n, 3)), tmax]).astype(np.float32)
    dirs = rng.standard_normal((n, 4))
    dirs[:, :3] /= np.linalg.norm(dirs[:, :3], axis=1, keepdims=True)
    dirs[:256, :3] = np.eye(3)[np.arange(256) % 3]  # axis-aligned: 1 / d is infinite in the box test
    any_hit, closest_hit = np.empty(n, np.int32), np.empty(n, np.int32)
    bufs = dev.buffer(any_hit.nbytes), dev.buffer(closest_hit.nbytes)
    _program(eng).probe_occluded(dev.queue, (n,), None, *dev.geometry, *dev.emitter_args, dev.const(origins),
                                 dev.const(dirs.astype(np.float32)), *bufs)
    cl.enqueue_copy(dev.queue, any_hit, bufs[0])
    cl.enqueue_copy(dev.queue, closest_hit, bufs[1])
    assert np.array_equal(any_hit, closest_hit)
    assert 0.05 < closest_hit.mean() < 0.95, closest_hit.mean()  # both answers are tested
