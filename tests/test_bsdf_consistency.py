"""Every material's sampling, value and pdfs agree (kernels/bsdf.cl), as vertex connection
and merging needs: a path's weight f cos / pdf is only right if its directions were drawn
with the density pdf_fwd states, and VCM's weights need pdf_rev to be the density of
sampling the reverse direction.

For each material and incoming direction, a probe kernel draws SAMPLES bounces and, on a
grid over the whole sphere of directions, evaluates f |cos| and both pdfs:
- the mean of the sampled non-delta weights equals the quadrature of f |cos| (within 1%,
  the samples' noise well below it): sampling draws from pdf_fwd;
- the pdf of the samples integrates to the share of the non-delta parts they took;
- pdf_rev(wo, wi) equals pdf_fwd(wi, wo) at every grid direction;
- a masked material's null part passes 1 - opacity of what arrives.
Both transport modes (radiance for camera paths, importance for light paths) and both sides
of a dielectric.
"""

from __future__ import annotations

import math

import numpy as np
import pyopencl as cl
import pytest

from kernels.contract import build_options
from kernels.program import KERNEL_DIR, PREAMBLE, SOURCES
from worker.integrators.photon_mapping import sum_layout
from worker.scene import parse_scene
from worker.surfaces import surface_records

SAMPLES = 1 << 20
GRID = (1024, 512)  # cos(theta) over [-1, 1], phi over [0, 2 pi): midpoints
PROBE = """
__kernel void probe_sample(__global const float4* surfaces, float4 wo4, int radiance, __global float4* out) {
    int i = get_global_id(0);
    Rng rng = rng_make(7UL, 0u, (uint)i, 9UL);
    Material m = load_material(surfaces, 0);
    float3 n = (float3)(0.0f, 0.0f, 1.0f);
    BsdfSample s;
    bool ok = bsdf_sample(&m, n, n, -wo4.xyz, PART_ALL, radiance != 0, &rng, &s);
    float lum = LUM_R * s.weight.x + LUM_G * s.weight.y + LUM_B * s.weight.z;
    out[i] = (float4)(ok ? lum : 0.0f, ok && !s.delta ? 1.0f : 0.0f, ok && s.delta ? 1.0f : 0.0f, 0.0f);
}

__kernel void probe_eval(__global const float4* surfaces, float4 wo4, int radiance, __global const float4* dirs,
                         __global float4* out) {
    int i = get_global_id(0);
    Material m = load_material(surfaces, 0);
    float3 n = (float3)(0.0f, 0.0f, 1.0f), wi = dirs[i].xyz, wo = wo4.xyz;
    BsdfEval e = bsdf_eval(&m, n, n, wo, wi, PART_ALL, radiance != 0);
    BsdfEval back = bsdf_eval(&m, n, n, wi, wo, PART_ALL, radiance != 0);
    float lum = LUM_R * e.f.x + LUM_G * e.f.y + LUM_B * e.f.z;
    out[i] = (float4)(lum * fabs(wi.z), e.pdf_fwd, e.pdf_rev, back.pdf_fwd);
}
"""

MATERIALS = {
    "diffuse": {"type": "diffuse", "albedo": [0.7, 0.5, 0.3]},
    "glossy": {"type": "glossy", "albedo": [0.8, 0.8, 0.8], "exponent": 20.0},
    "rough_conductor": {"type": "rough_conductor", "alpha": 0.3, "distribution": "ggx",
                        "eta": [0.2, 0.4, 1.4], "k": [3.4, 2.4, 1.8]},
    "rough_conductor_beckmann": {"type": "rough_conductor", "alpha": 0.15},
    "plastic": {"type": "plastic", "albedo": [0.6, 0.4, 0.2]},
    "rough_plastic": {"type": "rough_plastic", "albedo": [0.6, 0.4, 0.2], "alpha": 0.2},
    "rough_glass": {"type": "rough_glass", "ior": 1.5, "alpha": 0.3, "distribution": "ggx"},
    "rough_glass_beckmann": {"type": "rough_glass", "ior": 1.33, "alpha": 0.15},
    # Masked (Mitsuba's mask): the lobes scaled by the opacity, the rest a delta (null) part.
    "masked_diffuse": {"type": "diffuse", "albedo": [0.7, 0.5, 0.3], "opacity": 0.4},
    "masked_rough_plastic": {"type": "rough_plastic", "albedo": [0.6, 0.4, 0.2], "alpha": 0.2, "opacity": 0.7},
    "masked_rough_glass": {"type": "rough_glass", "ior": 1.5, "alpha": 0.3, "opacity": 0.25},
}
CASES = [(name, cos_o, side, radiance) for name in MATERIALS for cos_o in (0.9, 0.4) for side in (1, -1)
         for radiance in (True, False) if side == 1 or "rough_glass" in name]


@pytest.fixture(scope="module")
def program(ctx: cl.Context) -> cl.Program:
    source = PREAMBLE + "\n".join((KERNEL_DIR / name).read_text() for name in SOURCES) + PROBE
    return cl.Program(ctx, source).build(options=["-cl-mad-enable", *build_options(sum_layout(False))])


def grid_directions() -> tuple[np.ndarray, float]:
    """Midpoints of GRID cells over the sphere (equal solid angle each) and that solid angle."""
    nz, nphi = GRID
    z = -1.0 + (np.arange(nz) + 0.5) * 2.0 / nz
    phi = (np.arange(nphi) + 0.5) * 2.0 * math.pi / nphi
    r = np.sqrt(1.0 - z ** 2)
    dirs = np.zeros((nz, nphi, 4), np.float32)
    dirs[..., 0], dirs[..., 1], dirs[..., 2] = r[:, None] * np.cos(phi), r[:, None] * np.sin(phi), z[:, None]
    return dirs.reshape(-1, 4), 4.0 * math.pi / (nz * nphi)


@pytest.mark.parametrize("name, cos_o, side, radiance", CASES,
                         ids=[f"{n}-{c}-{'out' if s > 0 else 'in'}-{'rad' if r else 'imp'}" for n, c, s, r in CASES])
def test_sampling_matches_value_and_pdfs(ctx, program, name: str, cos_o: float, side: int, radiance: bool) -> None:
    scene = parse_scene({"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0]}, "materials": {"m": MATERIALS[name]},
                         "shapes": [{"type": "sphere", "center": [0, 0, 0], "radius": 1, "material": "m"}]})
    queue = cl.CommandQueue(ctx)
    mf = cl.mem_flags
    surfaces = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(surface_records(scene)))
    wo = np.array([math.sqrt(1.0 - cos_o ** 2), 0.0, side * cos_o, 0.0], np.float32)
    flag = np.int32(radiance)

    samples = np.empty((SAMPLES, 4), np.float32)
    out = cl.Buffer(ctx, mf.WRITE_ONLY, samples.nbytes)
    cl.Kernel(program, "probe_sample")(queue, (SAMPLES,), None, surfaces, wo, flag, out)
    cl.enqueue_copy(queue, samples, out)

    dirs, cell = grid_directions()
    values = np.empty_like(dirs)
    dbuf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=dirs)
    vbuf = cl.Buffer(ctx, mf.WRITE_ONLY, values.nbytes)
    cl.Kernel(program, "probe_eval")(queue, (len(dirs),), None, surfaces, wo, flag, dbuf, vbuf)
    cl.enqueue_copy(queue, values, vbuf)
    queue.finish()

    nondelta = samples[:, 1] > 0.0
    weights = np.where(nondelta, samples[:, 0], 0.0).astype(np.float64)
    sampled = weights.mean()
    noise = weights.std() / math.sqrt(SAMPLES)
    quadrature = float(np.sum(values[:, 0], dtype=np.float64) * cell)
    assert noise < 0.003 * max(quadrature, 1e-3)
    assert sampled == pytest.approx(quadrature, rel=0.01, abs=1e-4), (sampled, quadrature)
    share = float(np.sum(values[:, 1], dtype=np.float64) * cell)
    assert share == pytest.approx(nondelta.mean(), rel=0.01, abs=2e-3), (share, nondelta.mean())
    # (atol: refraction that grazes a microfacet is ill-conditioned, cos_t = sqrt(1 - sin^2) near 0,
    # and both pdfs are near 0 there)
    np.testing.assert_allclose(values[:, 2], values[:, 3], rtol=2e-3, atol=1e-3 * values[:, 1].max())
    opacity = MATERIALS[name].get("opacity", 1.0)
    if opacity < 1.0:  # every delta sample is the null part (these lobes have none): it passes 1 - opacity
        null = np.where(samples[:, 2] > 0.0, samples[:, 0], 0.0).astype(np.float64).mean()
        assert null == pytest.approx(1.0 - opacity, rel=0.01), null
