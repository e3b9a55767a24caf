"""The pass loop: scene -> kernels -> per-batch delta.

A pass is: eye pass (one measurement point per pixel), photon pass, lookup-structure
build (stochastic hash or exact grid), gather. A batch runs several passes at the radii
it was given and sums their contributions on the device in float64; the host merges the
resulting `Delta` (worker/stats.py). The OpenCL context, compiled program, scene buffers
and work buffers live as long as the Engine, so consecutive batches pay no set-up.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import pyopencl as cl

from kernels.program import create_context, f32, i32, program_for, u32, u64
from worker.scene import Scene
from worker.scene_arrays import SceneArrays, compile_scene
from worker.stats import ADDITIVE, Delta

MAX_PHOTONS_PER_PASS = 1 << 24
# Photon paths end by Russian roulette and eye paths at their first diffuse hit; this cap
# on bounces per photon path and specular bounces per eye path is only a safety net.
# Russian roulette keeps the expected throughput, so the energy the cap cuts is the true
# throughput still carried after MAX_BOUNCES bounces: at most a^MAX_BOUNCES of the emitted
# (or seen) energy where every surface reflects at most a. For a = 0.99 that is
# 0.99^4096 = 1.3e-18, for a = 0.999 1.7e-2; the 16 bounces of old lost 0.99^16 = 15%.
# Lossless surfaces (albedo 1: ideal mirrors and glass) absorb nothing, so there the cut is
# the share of paths still trapped among them after 4096 bounces: zero in any scene where
# such a chain ends at a diffuse surface or escapes (glass: each internal hit stays inside
# only with the Fresnel reflectance), and the radiance of a closed lossless cavity with no
# diffuse surface is not defined at all. 4096 = 2^12 is what the photon key holds
# (kernels/photon_pass.cl).
MAX_BOUNCES = 4096
R0_PHOTONS = 16.0  # default initial radius: holds this many photons per pass at the median lit pixel ...
R0_FOOTPRINTS = 2.0  # ... but spans at least this many pixel footprints
PROBE_FOOTPRINTS = 8.0  # the first pass measures photon density within this many pixel footprints


@dataclass(frozen=True)
class RenderSettings:
    method: Literal["sppm", "ppm"] = "sppm"
    gather: Literal["stochastic", "exact"] = "exact"
    photons_per_pass: int = 1 << 18
    seed: int = 0
    initial_radius: float | None = None  # world units; default: see Engine.initial_radius
    hash_entries_per_photon: float = 1.0  # stochastic hash table size / photons stored per pass
    error_estimation: bool = True  # accumulate the error estimator's sums (G, Gr, X1, X2, L2)
    max_bounces: int = MAX_BOUNCES  # safety cap on path length (lower only to study what it cuts)

    def __post_init__(self) -> None:
        if not 1 <= self.photons_per_pass <= MAX_PHOTONS_PER_PASS:
            raise ValueError(f"photons_per_pass must lie in [1, {MAX_PHOTONS_PER_PASS}]")
        if not 0 <= self.seed < 2 ** 63:
            raise ValueError("seed must lie in [0, 2^63)")
        if self.initial_radius is not None and not (0.0 < self.initial_radius < math.inf):
            raise ValueError("initial_radius must be positive and finite")
        if not 0.0 < self.hash_entries_per_photon <= 64.0:
            raise ValueError("hash_entries_per_photon must lie in (0, 64]")
        if not 1 <= self.max_bounces <= MAX_BOUNCES:
            raise ValueError(f"max_bounces must lie in [1, {MAX_BOUNCES}]")


STAGES = ("eye", "trace", "build", "gather", "readback")


class BatchAborted(Exception):
    """A batch stopped between passes because its job no longer wants it."""


@dataclass
class StageTimes:
    """Seconds spent per stage: device time from OpenCL profiling events, read once the
    events have completed (`settle`), so timing adds no synchronisation to a pass."""

    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    pending: list[tuple[str, cl.Event]] = field(default_factory=list)

    def add(self, stage: str, events: list[cl.Event]) -> None:
        self.pending.extend((stage, e) for e in events)

    def settle(self) -> None:
        for stage, e in self.pending:
            self.seconds[stage] += (e.profile.end - e.profile.start) * 1e-9
        self.pending.clear()


def _pack_dir(d: np.ndarray) -> int:
    """Octahedral 2 x 16-bit direction, as pack_dir in kernels/materials.cl."""
    v = np.asarray(d, np.float64) / np.abs(d).sum()
    p = v[:2] if v[2] >= 0 else (1.0 - np.abs(v[[1, 0]])) * np.where(v[:2] >= 0, 1.0, -1.0)
    q = np.clip(np.round((p * 0.5 + 0.5) * 65535.0), 0, 65535).astype(np.uint32)
    return int(q[0] | (q[1] << 16))


def _next_pow2(n: int) -> int:
    return 1 << max(10, math.ceil(math.log2(max(n, 1))))


class Engine:
    """Renders passes of one scene on the OpenCL CPU device of this process."""

    def __init__(self, scene: Scene, base_dir: Path, settings: RenderSettings,
                 resolution: tuple[int, int] | None = None, ctx: cl.Context | None = None) -> None:
        self.settings = settings
        self.arrays: SceneArrays = compile_scene(scene, base_dir, resolution)
        self.ctx = ctx or create_context()
        self.queue = cl.CommandQueue(self.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
        self.program = program_for(self.ctx, settings.error_estimation)
        self.times = StageTimes()
        a = self.arrays
        mf = cl.mem_flags

        def const(arr: np.ndarray) -> cl.Buffer:
            arr = np.ascontiguousarray(arr)
            if arr.nbytes == 0:  # OpenCL has no empty buffers
                arr = np.zeros(4, arr.dtype)
            return cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=arr)

        self.geometry = [const(a.tri_v0), const(a.tri_e1), const(a.tri_e2), const(a.node_lo), const(a.node_hi),
                         i32(len(a.node_lo)), const(a.spheres), const(a.sphere_surf), i32(len(a.spheres)),
                         const(a.surf_a), const(a.surf_b)]
        self.n_emitters = len(a.emitters) // 4 if a.emitters.any() else 0
        self.emitter_args = [const(a.emitters), const(a.emitter_cdf), i32(self.n_emitters)]
        self.camera = const(a.camera)

        n = a.n_pixels
        self.mp_pos = cl.Buffer(self.ctx, mf.READ_WRITE, 16 * n)
        self.mp_nrm = cl.Buffer(self.ctx, mf.READ_WRITE, 16 * n)
        self.mp_wgt = cl.Buffer(self.ctx, mf.READ_WRITE, 16 * n)
        self.mp_dist = cl.Buffer(self.ctx, mf.READ_WRITE, 4 * n)
        self.radius = cl.Buffer(self.ctx, mf.READ_ONLY, 4 * n)
        self.bias = cl.Buffer(self.ctx, mf.READ_ONLY, 4 * n)
        # Batch sums on the device, float64; rgb and vectors as double4.
        self.acc = {name: cl.Buffer(self.ctx, mf.READ_WRITE, (32 if width == 3 else 8) * n)
                    for name, width in ADDITIVE.items()}
        self.ph_count = cl.Buffer(self.ctx, mf.READ_WRITE, 4)
        self.capacity = 0
        self.entries = 0
        self._reserve_photons(3 * settings.photons_per_pass)
        self.photons_stored = 0  # of the last pass

    # ------------------------------------------------------------------ buffers
    def _reserve_photons(self, capacity: int) -> None:
        mf = cl.mem_flags
        self.capacity = capacity
        self.ph_pos = cl.Buffer(self.ctx, mf.READ_WRITE, 16 * capacity)
        self.ph_flux = cl.Buffer(self.ctx, mf.READ_WRITE, 16 * capacity)
        self.ph_key = cl.Buffer(self.ctx, mf.READ_WRITE, 8 * capacity)
        self.sorted = cl.Buffer(self.ctx, mf.READ_WRITE, 4 * capacity)

    def _reserve_table(self, entries: int) -> None:
        if entries <= self.entries:
            return
        mf = cl.mem_flags
        self.entries = entries
        self.tab_key = cl.Buffer(self.ctx, mf.READ_WRITE, 8 * entries)
        self.tab_count = cl.Buffer(self.ctx, mf.READ_WRITE, 4 * entries)
        self.tab_pos = cl.Buffer(self.ctx, mf.READ_WRITE, 16 * entries)
        self.tab_flux = cl.Buffer(self.ctx, mf.READ_WRITE, 16 * entries)
        self.cell_start = cl.Buffer(self.ctx, mf.READ_WRITE, 4 * entries)
        self.cell_fill = cl.Buffer(self.ctx, mf.READ_WRITE, 4 * entries)

    def _fill(self, buf: cl.Buffer, value: np.generic, count: int) -> cl.Event:
        return cl.enqueue_fill_buffer(self.queue, buf, value, 0, value.nbytes * count)

    def _zero_sums(self) -> None:
        """Start a batch: every device sum back to zero (rgb and vectors are double4)."""
        for name, width in ADDITIVE.items():
            self._fill(self.acc[name], np.float64(0.0), (4 if width == 3 else 1) * self.arrays.n_pixels)

    # ------------------------------------------------------------------- passes
    def _eye_pass(self, pass_index: int) -> None:
        a = self.arrays
        eye_index = 0 if self.settings.method == "ppm" else pass_index  # PPM: one fixed set of points
        ev = self.program.launch(self.queue, "eye_pass", a.n_pixels, *self.geometry, self.camera,
                                 i32(a.width), i32(a.height), u64(self.settings.seed), u32(eye_index),
                                 i32(self.settings.max_bounces), self.radius, self.mp_pos, self.mp_nrm, self.mp_wgt, self.mp_dist, self.acc["Ld"])
        self.times.add("eye", [ev])

    def _photon_pass(self, pass_index: int) -> int:
        """Trace the pass's photons; returns how many were stored."""
        while True:
            events = [self._fill(self.ph_count, np.uint32(0), 1)]
            events.append(self.program.launch(
                self.queue, "photon_pass", self.settings.photons_per_pass, *self.geometry, *self.emitter_args,
                u64(self.settings.seed), u32(pass_index), i32(self.settings.max_bounces), u32(self.capacity),
                self.ph_pos, self.ph_flux, self.ph_key, self.ph_count))
            stored = np.zeros(1, np.uint32)
            cl.enqueue_copy(self.queue, stored, self.ph_count)
            self.times.add("trace", events)
            if stored[0] <= self.capacity:
                return int(stored[0])
            self._reserve_photons(int(stored[0] * 1.25))  # same seed: the re-run is identical

    def _gather_sums(self) -> list[cl.Buffer]:
        return [self.acc[name] for name in ("S", "D", "G", "Gr", "X1", "X2", "L2", "H")]

    def _build_and_gather(self, n_stored: int, max_radius: float, gather: str | None = None) -> None:
        a, p = self.arrays, self.program
        photons = f32(self.settings.photons_per_pass)
        inv_cell = f32(1.0 / (2.0 * max_radius))  # cell = 2 * largest radius (dissertation 10.2.2)
        if (gather or self.settings.gather) == "stochastic":
            entries = _next_pow2(int(math.ceil(n_stored * self.settings.hash_entries_per_photon)))
            self._reserve_table(entries)
            mask = u32(entries - 1)
            build = [self._fill(self.tab_key, np.uint64(2 ** 64 - 1), entries),
                     self._fill(self.tab_count, np.uint32(0), entries),
                     p.launch(self.queue, "hash_select", n_stored, u32(n_stored), self.ph_pos, self.ph_key,
                              inv_cell, mask, self.tab_key, self.tab_count),
                     p.launch(self.queue, "hash_store", n_stored, u32(n_stored), self.ph_pos, self.ph_flux,
                              self.ph_key, inv_cell, mask, self.tab_key, self.tab_pos, self.tab_flux)]
            gather = p.launch(self.queue, "gather_stochastic", a.n_pixels, i32(a.n_pixels), self.mp_pos,
                              self.mp_nrm, self.mp_wgt, self.radius, self.bias, photons, inv_cell, mask,
                              self.tab_count, self.tab_pos, self.tab_flux, *self._gather_sums())
        else:
            entries = _next_pow2(n_stored)
            self._reserve_table(entries)
            mask = u32(entries - 1)
            build = [self._fill(self.tab_count, np.uint32(0), entries),
                     p.launch(self.queue, "grid_count", n_stored, u32(n_stored), self.ph_pos, inv_cell, mask,
                              self.tab_count),
                     p.launch(self.queue, "grid_scan", 1, u32(entries), self.tab_count, self.cell_start,
                              self.cell_fill),
                     p.launch(self.queue, "grid_scatter", n_stored, u32(n_stored), self.ph_pos, inv_cell, mask,
                              self.cell_fill, self.sorted),
                     p.launch(self.queue, "grid_sort", entries, u32(entries), self.cell_start, self.tab_count,
                              self.sorted, self.ph_key)]
            gather = p.launch(self.queue, "gather_exact", a.n_pixels, i32(a.n_pixels), self.mp_pos, self.mp_nrm,
                              self.mp_wgt, self.radius, self.bias, photons, inv_cell, mask, self.cell_start,
                              self.tab_count, self.sorted, self.ph_pos, self.ph_flux, *self._gather_sums())
        gather.wait()
        self.times.add("build", build)
        self.times.add("gather", [gather])

    def gather_photons(self, points: np.ndarray, normals: np.ndarray, radius: np.ndarray, photon_pos: np.ndarray,
                       photon_flux: np.ndarray, photon_dir: np.ndarray,
                       photon_normal: np.ndarray | None = None) -> Delta:
        """Gather given photons at given points with the real kernels, no eye or photon pass:
        a probe of the density and derivative estimates (e.g. noise-free on a photon grid).
        Needs an Engine whose resolution has exactly len(points) pixels; unit weights.
        `photon_normal` is each photon's surface normal facing it (default: photon_dir,
        photons that arrived along their surface's normal)."""
        n, m = self.arrays.n_pixels, len(photon_pos)
        if len(points) != n:
            raise ValueError(f"this engine gathers at exactly {n} points")
        if m > self.capacity:
            self._reserve_photons(m)

        def f4(a: np.ndarray, w: float | np.ndarray = 0.0) -> np.ndarray:
            out = np.zeros((len(a), 4), np.float32)
            out[:, :3] = a
            out[:, 3] = w
            return out

        def packed(dirs: np.ndarray) -> np.ndarray:
            return np.array([_pack_dir(d) for d in dirs], np.uint32).view(np.float32)

        nrm = packed(photon_dir if photon_normal is None else photon_normal)
        for buf, host in ((self.mp_pos, f4(points, 1.0)), (self.mp_nrm, f4(normals)),
                          (self.mp_wgt, f4(np.ones((n, 3)), 1.0)),  # the whole disc on the plane
                          (self.ph_pos, f4(photon_pos, nrm)), (self.ph_flux, f4(photon_flux, packed(photon_dir))),
                          (self.radius, np.ascontiguousarray(radius, np.float32)), (self.bias, np.zeros(n, np.float32))):
            cl.enqueue_copy(self.queue, buf, host)
        cl.enqueue_copy(self.queue, self.ph_key, np.arange(m, dtype=np.uint64))
        self._zero_sums()
        self._build_and_gather(m, float(np.max(radius)))
        return self._read_sums(0, 1)

    def initial_radius(self) -> np.ndarray:
        """R0 for every pixel: the override, or the larger of R0_FOOTPRINTS pixel footprints
        and the radius that holds R0_PHOTONS photons per pass at the median lit pixel.

        Both are the dissertation's (5.3.1): "the footprint of the pixel", or after the first
        photon pass a k-nearest-photon radius, here made one value for the whole image as in
        its GPU SPPM, since the stochastic hash sizes its cells by the largest radius. The
        footprint alone ignores how many photons a pass brings: on smallppm at 1024x768 it
        gave R0 = 0.10 and 4.7x the image error of R0 = 0.5 at smallppm's 4M photons. The
        photon count alone shrinks R0 below a pixel where photons are dense, which buys no
        resolution, only noise.

        The density comes from pass 0 itself: its eye pass, its photons, and an exact gather
        at PROBE_FOOTPRINTS pixel footprints; nothing of it is kept."""
        n = self.arrays.n_pixels
        if self.settings.initial_radius is not None:
            return np.full(n, self.settings.initial_radius)
        cl.enqueue_copy(self.queue, self.radius, np.zeros(n, np.float32))  # no disc coverage: the probe is rough
        self._eye_pass(0)
        dist = np.empty(n, np.float32)
        cl.enqueue_copy(self.queue, dist, self.mp_dist)
        hit = dist > 0.0
        footprint = float(np.median(dist[hit])) * self.arrays.pixel_angle if hit.any() \
            else self.arrays.scene_diagonal / max(self.arrays.width, self.arrays.height)
        probe = PROBE_FOOTPRINTS * footprint
        self._zero_sums()
        cl.enqueue_copy(self.queue, self.radius, np.full(n, probe, np.float32))
        cl.enqueue_copy(self.queue, self.bias, np.zeros(n, np.float32))
        self._build_and_gather(self._photon_pass(0), probe, gather="exact")  # every photon counted
        density = np.empty(n, np.float64)  # D = M / (pi probe^2): photons per unit area per pass
        cl.enqueue_copy(self.queue, density, self.acc["D"])
        self.times.pending.clear()  # set-up, not rendering
        lit = density > 0.0
        r0 = R0_FOOTPRINTS * footprint
        if lit.any():  # else no photon reached anything the camera sees
            r0 = max(r0, math.sqrt(R0_PHOTONS / (math.pi * float(np.median(density[lit])))))
        return np.full(n, r0)

    def run_batch(self, radius: np.ndarray, first_pass: int, n_passes: int, bias: np.ndarray | None = None,
                  keep_going: Callable[[int], bool] | None = None) -> Delta:
        """Run passes first_pass .. first_pass+n_passes-1, all gathering at `radius`.

        `bias` is the per-pixel bias estimate subtracted from each pass's sample for the
        variance estimate (eq. 6.22); zero if not given. `keep_going(pass_index)` is asked
        after every pass; False raises BatchAborted."""
        n = self.arrays.n_pixels
        r32 = np.ascontiguousarray(radius, np.float32)
        if r32.shape != (n,) or not np.all(r32 > 0.0) or not np.all(np.isfinite(r32)):
            raise ValueError("radius must hold one positive finite value per pixel")
        b32 = np.zeros(n, np.float32) if bias is None else np.ascontiguousarray(bias, np.float32)
        cl.enqueue_copy(self.queue, self.radius, r32)
        cl.enqueue_copy(self.queue, self.bias, b32)
        self._zero_sums()
        for k in range(first_pass, first_pass + n_passes):
            self._eye_pass(k)
            self.photons_stored = self._photon_pass(k)
            self._build_and_gather(self.photons_stored, float(r32.max()))
            if keep_going is not None and not keep_going(k):
                self.times.settle()
                raise BatchAborted(f"stopped after pass {k}")
        return self._read_sums(first_pass, n_passes)

    def _read_sums(self, first_pass: int, n_passes: int) -> Delta:
        n = self.arrays.n_pixels
        t0 = time.perf_counter()
        sums = {}
        for name, width in ADDITIVE.items():
            host = np.empty((n, 4) if width == 3 else n, np.float64)
            cl.enqueue_copy(self.queue, host, self.acc[name])
            sums[name] = host[:, :3].copy() if width == 3 else host
        self.times.seconds["readback"] += time.perf_counter() - t0
        self.times.settle()
        return Delta(first_pass=first_pass, n_passes=n_passes, emitted=n_passes * self.settings.photons_per_pass,
                     sums=sums)
