"""The kernel-host contract: every constant the kernels and Python share, defined once here
and handed to the OpenCL build as `-D` options (no `.cl` file repeats a value).

Importable without OpenCL (the API process uses the constants and layouts too).

Per-pixel sums. A batch's sums live on the device in one float64 buffer of `stride`
doubles per pixel, one block per sum (name-major: the host reads every sum back as a
contiguous array, with no copy to split them). A `SumLayout` names each sum with its width
(1 = scalar, 3 = rgb); SUM_<NAME> is its offset in doubles per pixel, the kernels address
it as `sum_at(sums, n_pixels, gid, SUM_<NAME>, width)` (kernels/sums.cl) and test
`#ifdef SUM_<NAME>` for optional ones, so adding a sum is one entry in a layout here plus
the kernel code that writes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Materials (surface record type), their flags and the record's size: kernels/materials.cl.
# `mirror` is a conductor without a Fresnel term (MF_NO_FRESNEL); MF_TEXTURED: the record's
# textures row names a texture (kernels/textures.cl); MF_MASKED: an opacity below 1 (the
# record's opacity row); TABLE_SIZE: the cosines a rough
# plastic's coat transmittance is tabulated at, evenly over [0, 1] (as Mitsuba 3's).
MATERIALS = {"diffuse": 0, "glossy": 1, "conductor": 2, "rough_conductor": 3, "glass": 4, "thin_glass": 5,
             "plastic": 6, "rough_plastic": 7, "rough_glass": 8}
MATERIAL_FLAGS = {"beckmann": 1, "nonlinear": 2, "no_fresnel": 4, "textured": 8, "masked": 16}
SURF_ROWS = 6
TABLE_SIZE = 64
# Textures (kernels/textures.cl): a record of TEX_ROWS rows per texture; its flags: the kind,
# the wrap mode shifted by 2, and the TEXTURE_FLAGS bits.
TEXTURE_KINDS = {"bitmap": 0, "checkerboard": 1}
WRAP_MODES = {"repeat": 0, "mirror": 1, "clamp": 2}
TEXTURE_FLAGS = {"nearest": 16, "grey": 32, "bytes": 64}
TEX_ROWS = 3
TEX_ALIGN = 16  # bytes: each texture's data starts at a multiple (its table's floats, its texels' aligned loads)
# Emitter kinds: kernels/lights.cl (the environment: kernels/environment.cl).
EMITTERS = {"triangle": 0, "sphere": 1, "point": 2, "spot": 3, "directional": 4, "environment": 5}
# Random-number domains: independent streams for eye paths, photon paths and the light
# samples at the measurement points (kernels/rng.cl).
RNG_DOMAINS = {"eye": 1, "photon": 2, "nee": 3, "light_path": 4, "camera_path": 5, "chain": 6}

# Adaptive photon tracing (kernels/photon_chains.cl): the dimensions of the primary sample
# space (a path's first PSS_DIM random numbers in the order it asks for them: emitter 1,
# emission 4, then per bounce 0-3 for the part, the direction or the glass branch and 1 for Russian
# roulette, so 32 cover about 9 bounces; the rest come from a stream seeded by a hash of the
# vector, kernels/rng.cl), and how many photons of a chain state are kept to be re-counted
# without tracing it again (a state with more is traced again at every splat).
PSS_DIM = 32
DEPOSIT_CACHE = 16

# The smooth kernel K(t) = 1 - 6t^5 + 15t^4 - 10t^3 (dissertation eq. 6.34) and its moments.
K1 = 2.0 * math.pi / 7.0  # integral of K over the unit disc: the flux normalisation k1 r^2
K2 = 10.0 * math.pi / 168.0  # integral of |u|^2 K over the unit disc
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 weights: what "error" measures

# Photon paths end by Russian roulette and eye paths at their first diffuse hit; this cap
# on bounces per photon path and specular bounces per eye path is only a safety net.
# Russian roulette keeps the expected throughput, so the energy the cap cuts is the true
# throughput still carried after MAX_BOUNCES bounces: at most a^MAX_BOUNCES of the emitted
# (or seen) energy where every surface reflects at most a. For a = 0.99 that is
# 0.99^4096 = 1.3e-18, for a = 0.999 1.7e-2.
# Lossless surfaces (albedo 1: ideal mirrors and glass) absorb nothing, so there the cut is
# the share of paths still trapped among them after 4096 bounces: zero in any scene where
# such a chain ends at a diffuse surface or escapes (glass: each internal hit stays inside
# only with the Fresnel reflectance), and the radiance of a closed lossless cavity with no
# diffuse surface is not defined at all. 4096 = 2^12 is what the photon key's bounce field
# holds (kernels/photon_pass.cl).
MAX_BOUNCES = 4096

# The hybrid integrator (kernels/vcm_*.cl): light-tracing splats land on any pixel, so
# they are summed with 64-bit integer atomics in fixed point (no float atomics on PoCL;
# integer addition is associative, so the sum is the same bit for bit whatever the order).
# One unit is 2^-SPLAT_FRACTION_BITS of the scene's radiance scale (SceneArrays.radiance_scale:
# its brightest light's radiance, or what a delta light gives a white surface): 3.7e-9 of it per
# splat, far below any noise, and a pixel holds up to 2^(63 - SPLAT_FRACTION_BITS) = 3.4e10 of
# it per pass (more saturates). Scaled to the scene so that both bounds hold in any radiance
# unit: a fixed unit would round a dim scene's splats away (tests/test_connect_merge.py).
SPLAT_FRACTION_BITS = 28
# Stage timing of the hybrid passes (bench/engine_speed.py): bits of the kernels' `skip`
# argument that leave a technique's evaluation out while every MIS weight stays the
# method's, so the device time of a pass with and without it is that technique's cost.
# Rendering passes 0; an image rendered with any bit set is wrong by design.
HYBRID_SKIP = {"nee": 1, "connect": 2, "merge": 4, "splat": 8}
# The hybrid program builds on the photon-mapping sources (for spatial_hash.cl's grid build),
# whose eye-pass and gather kernels address these sums unconditionally; a layout without
# them gets them defined as offset 0 so the source compiles (those kernels never run).
PHOTON_RECORD_NAMES = ("S", "D", "M", "H", "LD")
# The eye pass casts its disc-coverage rays only where a conservative test finds a shape
# that could cut the disc (kernels/eye_pass.cl, disc_may_be_cut); 0 casts them at every
# point, which must give the same coverage bit for bit (tests/test_disc_coverage.py).
COVERAGE_PRETEST = 1
# Surfaces match when their normals lie within 45 degrees: the gather counts only photons on
# a surface matching the measurement point's (kernels/spatial_hash.cl), and the gather disc
# is only as large as that surface, which continues across a triangle edge only to a
# neighbour whose normal matches (worker/adjacency.py). The eye pass walks at most
# EXTENT_STEPS triangles from the point's own to find where its surface ends (a convex
# edge; kernels/eye_pass.cl, surface_extent); a surface that runs on past them is taken to
# run on.
NORMAL_MATCH_COS = 0.7071
EXTENT_STEPS = 64
# The exact gather's grid (kernels/spatial_hash.cl, ball_rows): cells of 2 largest radii split this
# many ways along x, the axis of its rows (at most 31: a row's cells are bits of a uint). A query
# reads 4 runs of photons whatever the split; a finer split visits fewer photons but spreads the
# cells over more of the table (the trade-off: docs/results.md).
GRID_ROW_SPLIT = 2


@dataclass(frozen=True)
class SumLayout:
    """Named per-pixel float64 sums, `stride` doubles a pixel, one block per sum (sums.cl).
    `half`: the sums a batch's delta may send in half precision (worker/store/tiles.py):
    non-negative ones only ever added into the image or the radius rule, never subtracted
    one from another by the error estimator (a variance's moments, and the mean it
    subtracts)."""

    widths: tuple[tuple[str, int], ...]
    half: tuple[str, ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.widths)

    @property
    def offsets(self) -> dict[str, int]:
        out, at = {}, 0
        for name, width in self.widths:
            out[name] = at
            at += width
        return out

    @property
    def stride(self) -> int:
        return sum(width for _, width in self.widths)

    def width(self, name: str) -> int:
        return dict(self.widths)[name]

    def zeros(self, n_pixels: int, name: str) -> np.ndarray:
        width = self.width(name)
        return np.zeros((n_pixels, width) if width > 1 else n_pixels)

    def split(self, flat: np.ndarray, n_pixels: int) -> dict[str, np.ndarray]:
        """The device buffer's (n_pixels * stride,) doubles -> one array per sum, (pixels,) or
        (pixels, 3): contiguous views into `flat`, no copies."""
        out = {}
        for name, at in self.offsets.items():
            width = self.width(name)
            block = flat[at * n_pixels:(at + width) * n_pixels]
            out[name] = block.reshape(n_pixels, width) if width > 1 else block
        return out

    def defines(self) -> dict[str, int]:
        return {f"SUM_{name.upper()}": at for name, at in self.offsets.items()}


def build_options(layout: SumLayout) -> list[str]:
    """The `-D` options that hand this contract to the kernels."""
    borrowed = {f"SUM_{name}": 0 for name in PHOTON_RECORD_NAMES if name.upper() not in map(str.upper, layout.names)}
    defines: dict[str, object] = {
        **{f"MAT_{name.upper()}": code for name, code in MATERIALS.items()},
        **{f"MF_{name.upper()}": f"{bit}u" for name, bit in MATERIAL_FLAGS.items()},
        "SURF_ROWS": SURF_ROWS,
        "TABLE_SIZE": TABLE_SIZE,
        **{f"TEX_{name.upper()}": code for name, code in TEXTURE_KINDS.items()},
        **{f"WRAP_{name.upper()}": code for name, code in WRAP_MODES.items()},
        **{f"TEX_{name.upper()}": bit for name, bit in TEXTURE_FLAGS.items()},
        "TEX_ROWS": TEX_ROWS,
        **{f"EMIT_{name.upper()}": code for name, code in EMITTERS.items()},
        **{f"DOMAIN_{name.upper()}": f"{code}UL" for name, code in RNG_DOMAINS.items()},
        "K1": repr(K1),
        "PSS_DIM": PSS_DIM,
        "DEPOSIT_CACHE": DEPOSIT_CACHE,
        "COVERAGE_PRETEST": COVERAGE_PRETEST,
        "NORMAL_MATCH_COS": f"{NORMAL_MATCH_COS!r}f",
        "EXTENT_STEPS": EXTENT_STEPS,
        "GRID_ROW_SPLIT": GRID_ROW_SPLIT,
        **{f"LUM_{c}": repr(float(w)) for c, w in zip("RGB", LUMINANCE, strict=True)},
        **{f"SKIP_{name.upper()}": bit for name, bit in HYBRID_SKIP.items()},
        **borrowed,
        **layout.defines(),
    }
    return [f"-D{name}={value}" for name, value in defines.items()]
