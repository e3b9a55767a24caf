"""Vertex connection and merging, the device half: the kernels of one pass and of a batch.

A pass is: light subpaths (kernels/vcm_light_pass.cl: vertices stored, light-tracing
splats), for merging the grid over the stored vertices (spatial_hash.cl's counting sort,
cells sorted by vertex key), camera subpaths (vcm_camera_pass.cl), and the pass's sums
(vcm_finish.cl). A batch sums its passes on the device and reads them back once.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pyopencl as cl

from kernels.contract import SPLAT_FRACTION_BITS
from kernels.program import f32, i32, u32, u64
from worker.integrators.base import BatchAborted, Delta, KeepGoing
from worker.integrators.connect_merge import ConnectMerge, HybridInputs, pass_radius
from worker.integrators.photon_mapping import PhotonMapping
from worker.integrators.photon_mapping_passes import R0_FOOTPRINTS, PhotonMappingPasses, _next_pow2

if TYPE_CHECKING:
    from worker.engine import Device

VERTICES_PER_PATH = 4  # initial room for stored light vertices per light path (grown on overflow)


class ConnectMergePasses:
    """Light pass, vertex grid, camera pass and pass sums for vcm, bpt and lt."""

    def __init__(self, integrator: ConnectMerge, device: Device) -> None:
        self.integrator = integrator
        self.settings = integrator.settings
        self.dev = device
        self.n_light = self.settings.paths_per_pass
        n = device.arrays.n_pixels
        self.cam_out = device.buffer(16 * n)
        self.cam_hit = device.buffer(4 * n)
        self.splats = device.buffer(24 * n)
        device.fill(self.splats, np.int64(0), 3 * n)
        self.splat_scale = f32(2.0 ** SPLAT_FRACTION_BITS / device.arrays.radiance_scale)  # fixed point per radiance
        self.path_last = device.buffer(4 * self.n_light)
        self.lv_count = device.buffer(4)
        self.capacity = 0
        self.entries = 0
        self._reserve_vertices(VERTICES_PER_PATH * self.n_light if self.stores else 1)
        self._reserve_grid(1)
        self.vertices_stored = 0  # of the last pass
        self.skip = 0  # stage timing only (kernels/contract.py HYBRID_SKIP); 0 renders

    @property
    def stores(self) -> bool:
        return self.integrator.connects or self.integrator.merges

    # ------------------------------------------------------------------ buffers
    def _reserve_vertices(self, capacity: int) -> None:
        self.capacity = capacity
        b = self.dev.buffer
        self.lv_pos, self.lv_thr, self.lv_wo, self.lv_ng, self.lv_ns = (b(16 * capacity) for _ in range(5))
        self.lv_key = b(8 * capacity)
        self.lv_prev = b(4 * capacity)
        # A textured material's values at each vertex (kernels/textures.cl, store_textured).
        self.lv_tex = b(32 * capacity if len(self.dev.arrays.tex_info) else 4)
        self.sorted = b(4 * capacity)
        self.grid_pos = b(16 * capacity)

    def _reserve_grid(self, entries: int) -> None:
        if entries <= self.entries:
            return
        self.entries = entries
        self.cell_start, self.cell_count, self.cell_fill = (self.dev.buffer(4 * entries) for _ in range(3))

    # ------------------------------------------------------------------- passes
    def _light_pass(self, pass_index: int, eta_vcm: float) -> int:
        """Trace the pass's light subpaths (splats included); returns the vertices stored."""
        dev, a, it = self.dev, self.dev.arrays, self.integrator
        while True:
            events = [dev.fill(self.lv_count, np.uint32(0), 1)]
            events.append(dev.program.launch(
                dev.queue, "vcm_light_pass", self.n_light, *dev.geometry, *dev.emitter_args, dev.camera,
                i32(a.width), i32(a.height), u64(self.settings.seed), u32(pass_index), i32(self.settings.max_bounces),
                u32(self.n_light), u32(self.capacity), i32(it.connects), i32(it.merges), f32(eta_vcm),
                i32(self.stores), u32(self.skip), self.lv_pos, self.lv_thr, self.lv_wo, self.lv_ng, self.lv_ns,
                self.lv_key, self.lv_prev, self.path_last, self.lv_tex, self.lv_count, self.splats,
                self.splat_scale))
            stored = np.zeros(1, np.uint32)
            cl.enqueue_copy(dev.queue, stored, self.lv_count)
            dev.times.add("light", events)
            if stored[0] <= self.capacity:
                return int(stored[0])
            # Same seed: the re-run is identical; its splats start again from zero.
            self._reserve_vertices(int(stored[0] * 1.25))
            dev.fill(self.splats, np.int64(0), 3 * a.n_pixels)

    def _build_grid(self, n_stored: int, radius: float) -> tuple[float, int]:
        """The grid over the stored vertices, cell 2r; returns (1 / cell, hash mask)."""
        dev, p = self.dev, self.dev.program
        entries = _next_pow2(n_stored)
        self._reserve_grid(entries)
        inv_cell, mask = f32(1.0 / (2.0 * radius)), u32(entries - 1)
        # Launched over `entries` work items (the kernels bound-check n_stored), not n_stored:
        # PoCL builds a kernel anew for every work-group size it picks, and it picks one that
        # divides the launch size, so a launch size that changed every pass would cost a kernel
        # build (or a cache load) every pass.
        events = [dev.fill(self.cell_count, np.uint32(0), entries),
                  p.launch(dev.queue, "grid_count", entries, u32(n_stored), self.lv_pos, inv_cell, u32(1), mask,
                           self.cell_count),
                  p.launch(dev.queue, "grid_scan", 1, u32(entries), self.cell_count, self.cell_start, self.cell_fill),
                  p.launch(dev.queue, "grid_scatter", entries, u32(n_stored), self.lv_pos, inv_cell, u32(1), mask,
                           self.cell_fill, self.sorted),
                  p.launch(dev.queue, "grid_sort", entries, u32(entries), self.cell_start, self.cell_count,
                           self.sorted, self.lv_key),
                  p.launch(dev.queue, "vcm_grid_positions", entries, u32(n_stored), self.sorted, self.lv_pos,
                           self.grid_pos)]
        dev.times.add("build", events)
        return float(inv_cell), int(mask)

    def _pass(self, k: int, r0: float) -> None:
        dev, a, it = self.dev, self.dev.arrays, self.integrator
        radius = pass_radius(r0, self.integrator.alpha, k)
        eta_vcm = math.pi * radius * radius * self.n_light
        self.vertices_stored = self._light_pass(k, eta_vcm)
        inv_cell, mask = self._build_grid(self.vertices_stored, radius) if it.merges else (1.0, 0)
        cam = dev.program.launch(
            dev.queue, "vcm_camera_pass", a.n_pixels, *dev.geometry, *dev.emitter_args, dev.camera,
            i32(a.width), i32(a.height), u64(self.settings.seed), u32(k), i32(self.settings.max_bounces),
            u32(self.n_light), i32(it.connects), i32(it.merges), f32(eta_vcm), f32(radius), u32(self.skip),
            self.lv_pos, self.lv_thr, self.lv_wo, self.lv_ng, self.lv_ns, self.lv_prev, self.path_last, self.lv_tex,
            f32(inv_cell), u32(mask), self.cell_start, self.cell_count, self.grid_pos, self.cam_out,
            self.cam_hit)
        finish = dev.program.launch(dev.queue, "vcm_finish", a.n_pixels, i32(a.n_pixels), self.cam_out,
                                    self.cam_hit, self.splats, self.splat_scale, dev.batch_sums)
        dev.times.add("camera", [cam])
        dev.times.add("finish", [finish])

    # -------------------------------------------------------------------- setup
    def setup(self) -> dict[str, np.ndarray]:
        """R0: the override, or R0_FOOTPRINTS pixel footprints (SPPM's footprint rule, from
        a photon-mapping eye pass on the same context). Not SPPM's photon-count rule: with
        few light paths per pass it grows R0 until merging reaches across walls (light leaks
        through them), and connections already carry the light that merging would smooth;
        merging is there for the specular paths, where a small radius is what they need."""
        dev = self.dev
        if self.settings.initial_radius is not None:
            return {"R0": np.full(dev.arrays.n_pixels, self.settings.initial_radius)}
        from worker.engine import Device  # (a cycle at import time otherwise)

        photon_mapping = PhotonMapping(self.settings.model_copy(update={"method": "sppm"}))
        probe = Device(dev.arrays, photon_mapping.sums, dev.ctx)
        footprint, _ = PhotonMappingPasses(photon_mapping, probe).pixel_footprint()
        return {"R0": np.full(dev.arrays.n_pixels, R0_FOOTPRINTS * footprint)}

    # -------------------------------------------------------------------- batch
    def run_batch(self, inputs: HybridInputs, first_pass: int, n_passes: int,
                  keep_going: KeepGoing | None = None) -> Delta:
        """Passes first_pass .. first_pass + n_passes - 1 at the job's R0."""
        r0 = inputs.r0
        if not (r0 > 0.0 and math.isfinite(r0)):
            raise ValueError("R0 must be positive and finite")
        dev = self.dev
        dev.zero_sums()
        for k in range(first_pass, first_pass + n_passes):
            self._pass(k, r0)
            if keep_going is not None and not keep_going(k):
                dev.times.settle()
                raise BatchAborted(f"stopped after pass {k}")
        return Delta(first_pass=first_pass, n_passes=n_passes, emitted=n_passes * self.n_light,
                     sums=dev.read_sums())
