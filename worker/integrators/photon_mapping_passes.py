"""Photon mapping, the device half: the kernels of one pass and of a batch of passes.

A pass is: eye pass (one measurement point per pixel), photon pass, lookup-structure
build (exact grid or stochastic hash), gather. A batch runs several passes at the radii
it was given and sums their contributions on the device (worker/engine.py, Device).
With chains (`sampler: adaptive`, or `auto` where it chose them or measures them) the
photon pass is the chains' (kernels/photon_chains.cl), after a grid over the pass's
measurement points that tells them which paths are visible.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pyopencl as cl

from kernels.contract import GRID_ROW_SPLIT
from kernels.program import f32, i32, u32, u64
from worker import adaptive, stats
from worker.integrators.base import BatchAborted, Delta, KeepGoing
from worker.integrators.photon_mapping import ChainInputs, GatherInputs, PhotonMapping

if TYPE_CHECKING:
    from worker.engine import Device

R0_PHOTONS = 16.0  # default initial radius: holds this many photons per pass at the median lit pixel ...
R0_FOOTPRINTS = 2.0  # ... but spans at least this many pixel footprints
PROBE_FOOTPRINTS = 8.0  # the first pass measures photon density within this many pixel footprints, ...
# ... a radius grown by PROBE_GROWTH until the median lit probe point holds PROBE_MIN_PHOTONS
# (or it would pass PROBE_MAX_SHARE of the scene): where photons lie sparser than the probe (a
# close-up, a big frame), a point that caught one photon overstates the density by the photons
# it missed, and points that caught none leave R0 at the footprints', which no photon may reach.
PROBE_GROWTH = 4.0
PROBE_MIN_PHOTONS = 4.0
# The probe grows to at most this share of the scene's diagonal: a disc that spans the scene
# gathers photons of surfaces the points do not see (the outer side of a closed room's wall,
# which would make its unlit interior look lit).
PROBE_MAX_SHARE = 1.0 / 16.0
# ... at most at this many pixels, a regular subset of the frame (R0's medians): a median needs
# no more, and the probe's gather is most of the set-up (the accuracy of R0 against the subset's
# size: docs/results.md).
PROBE_POINTS = 1 << 14


def _next_pow2(n: int) -> int:
    return 1 << max(10, math.ceil(math.log2(max(n, 1))))


class PhotonMappingPasses:
    """Eye pass, photon pass, lookup structure and gather for SPPM and PPM."""

    def __init__(self, integrator: PhotonMapping, device: Device) -> None:
        self.integrator = integrator
        self.settings = integrator.settings
        self.dev = device
        self.nee = self.settings.direct == "nee"  # direct light by next-event estimation (kernels/lights.cl)
        n = device.arrays.n_pixels
        self.mp_pos = device.buffer(16 * n)  # measurement points: position (w: 1 if present)
        self.mp_nrm = device.buffer(16 * n)  # normal facing the eye path
        self.mp_wgt = device.buffer(16 * n)  # path throughput * albedo / pi (w: disc coverage)
        self.mp_dist = device.buffer(4 * n)  # eye path length to the point
        self.mp_cut = device.buffer(16 * n)  # where the coverage rays cut the gather disc
        # Per pixel within a batch: the radius and the radius rule's count N, moving on pass by
        # pass (shrink_radius, spatial_hash.cl), and the bias.
        self.radius = device.buffer(4 * n)
        self.radius_count = device.buffer(4 * n)
        self.bias = device.buffer(4 * n)
        self.steps = 1  # how many passes of the job the pass being gathered stands for (shrink_radius)
        self.own = 0  # which of those steps is the pass itself (after the passes its batch's inputs lack)
        self.ph_count = device.buffer(4)
        self.counters = device.buffer(4 * len(adaptive.COUNTERS))  # the chains' per-pass counters
        self.capacity = 0
        self.mp_entries = _next_pow2(n)  # the grid over measurement points (adaptive sampler)
        self.mp_count = device.buffer(4 * self.mp_entries)
        self.mp_start = device.buffer(4 * self.mp_entries)
        self.mp_fill = device.buffer(4 * self.mp_entries)
        self.mp_sorted = device.buffer(4 * n)
        self.entries = 0
        self._reserve_photons(3 * self.settings.paths_per_pass)
        self.photons_stored = 0  # of the last pass
        self.replica_exchange = True  # False: the adaptive sampler's chains mutate only (an ablation, for tests)

    # ------------------------------------------------------------------ buffers
    def _reserve_photons(self, capacity: int) -> None:
        self.capacity = capacity
        self.ph_pos = self.dev.buffer(16 * capacity)
        self.ph_flux = self.dev.buffer(16 * capacity)
        self.ph_dirs = self.dev.buffer(8 * capacity)  # packed incoming direction and surface normal
        self.ph_key = self.dev.buffer(8 * capacity)
        # The photons' records in the exact grid's slots, one 64-byte line each (PhotonSlot,
        # grid_scatter_photons), sorted within each entry (grid_sort_slots), then split into
        # the gather's arrays with directions unpacked to unit vectors (grid_permute).
        self.slots = self.dev.buffer(64 * capacity)
        self.grid_pos = self.dev.buffer(16 * capacity)
        self.grid_flux = self.dev.buffer(16 * capacity)
        self.grid_in = self.dev.buffer(16 * capacity)  # incoming direction
        self.grid_nrm = self.dev.buffer(16 * capacity)  # surface normal facing the photon

    def _reserve_table(self, entries: int) -> None:
        if entries <= self.entries:
            return
        self.entries = entries
        self.tab_key = self.dev.buffer(8 * entries)
        self.tab_count = self.dev.buffer(4 * entries)
        self.tab_pos = self.dev.buffer(16 * entries)
        self.tab_flux = self.dev.buffer(16 * entries)
        self.tab_dirs = self.dev.buffer(8 * entries)
        self.cell_start = self.dev.buffer(4 * entries)
        self.cell_fill = self.dev.buffer(4 * entries)

    # ------------------------------------------------------------------- passes
    def _eye_pass(self, pass_index: int, stride: int = 1) -> int:
        """Trace every `stride`-th pixel's eye path (all of them by default) to its
        measurement point, stored at the front of the point buffers; returns their number."""
        dev, a = self.dev, self.dev.arrays
        eye_index = 0 if self.integrator.fixed_points else pass_index
        points = -(-a.n_pixels // stride)
        ev = dev.program.launch(dev.queue, "eye_pass", points, *dev.geometry, *dev.emitter_args, dev.camera,
                                i32(a.width), i32(a.height), i32(stride), u64(self.settings.seed), u32(eye_index),
                                i32(self.settings.max_bounces), i32(self.nee), u32(pass_index), self.radius,
                                self.mp_pos, self.mp_nrm, self.mp_wgt, self.mp_dist, self.mp_cut,
                                dev.batch_sums)
        dev.times.add("eye", [ev])
        return points

    def _photon_pass(self, pass_index: int, first_hits: bool = False) -> int:
        """Trace the pass's photons; returns how many were stored. With nee, photons store
        nothing at their first hit unless `first_hits`."""
        skip_first = i32(self.nee and not first_hits)
        dev = self.dev
        while True:
            events = [dev.fill(self.ph_count, np.uint32(0), 1)]
            events.append(dev.program.launch(
                dev.queue, "photon_pass", self.settings.paths_per_pass, *dev.geometry, *dev.emitter_args,
                u64(self.settings.seed), u32(pass_index), u32(self.settings.paths_per_pass),
                i32(self.settings.max_bounces), u32(self.capacity), skip_first, self.ph_pos, self.ph_flux,
                self.ph_dirs, self.ph_key, self.ph_count))
            stored = np.zeros(1, np.uint32)
            cl.enqueue_copy(dev.queue, stored, self.ph_count)
            dev.times.add("trace", events)
            if stored[0] <= self.capacity:
                return int(stored[0])
            self._reserve_photons(int(stored[0] * 1.25))  # same seed: the re-run is identical

    def _point_grid(self, inv_cell: np.float32) -> None:
        """The grid over this pass's measurement points that V(u) queries (visibility.cl):
        the photon grid's kernels, run over the points (no sort: V only asks whether any)."""
        dev, p, n = self.dev, self.dev.program, self.dev.arrays.n_pixels
        mask = u32(self.mp_entries - 1)
        events = [dev.fill(self.mp_count, np.uint32(0), self.mp_entries),
                  p.launch(dev.queue, "grid_count", n, u32(n), self.mp_pos, inv_cell, u32(1), mask, self.mp_count),
                  p.launch(dev.queue, "grid_scan", 1, u32(self.mp_entries), self.mp_count, self.mp_start,
                           self.mp_fill),
                  p.launch(dev.queue, "grid_scatter", n, u32(n), self.mp_pos, inv_cell, u32(1), mask, self.mp_fill,
                           self.mp_sorted)]
        dev.times.add("build", events)

    def _chain_pass(self, pass_index: int, chains: ChainInputs, max_radius: float) -> tuple[int, dict[str, int]]:
        """The adaptive sampler's photons (kernels/photon_chains.cl); returns how many were
        stored and the pass's counters."""
        dev, settings = self.dev, self.settings
        inv_cell = f32(1.0 / (2.0 * max_radius))
        self._point_grid(inv_cell)
        photons = settings.paths_per_pass
        iterations = photons if chains.iterations is None else chains.iterations
        while True:
            events = [dev.fill(self.ph_count, np.uint32(0), 1),
                      dev.fill(self.counters, np.uint32(0), len(adaptive.COUNTERS))]
            events.append(dev.program.launch(
                dev.queue, "photon_chains", chains.chains, *dev.geometry, *dev.emitter_args,
                u64(settings.seed), u32(pass_index), i32(settings.max_bounces), u32(self.capacity), i32(self.nee),
                u32(chains.chains), u32(iterations), f32(chains.theta),
                u32(adaptive.boot_draws(chains.chains, photons)),
                i32(self.replica_exchange), i32(1), i32(settings.gather == "exact"),  # 1: the chains mutate
                self.mp_pos, self.mp_nrm, self.mp_cut, self.radius, inv_cell, u32(self.mp_entries - 1), self.mp_start,
                self.mp_count, self.mp_sorted, self.ph_pos, self.ph_flux, self.ph_dirs, self.ph_key, self.ph_count,
                self.counters, one_per_group=True))
            stored = np.zeros(1, np.uint32)
            counts = np.zeros(len(adaptive.COUNTERS), np.uint32)
            cl.enqueue_copy(dev.queue, stored, self.ph_count)
            cl.enqueue_copy(dev.queue, counts, self.counters)
            dev.times.add("trace", events)
            if stored[0] <= self.capacity:
                return int(stored[0]), dict(zip(adaptive.COUNTERS, (int(c) for c in counts), strict=True))
            self._reserve_photons(int(stored[0] * 1.25))  # same seeds: the re-run is identical

    def _device_seconds(self) -> float:
        """Device seconds of every stage so far, the pending events waited for (a measuring
        pass's time is the difference across it: adaptive.measured)."""
        self.dev.times.settle()
        return sum(self.dev.times.seconds.values())

    def _scale_pass(self, n_stored: int, scale: float) -> None:
        """A chain pass's photons in uniform photons: their counts times adaptive.pass_scale."""
        if scale == 1.0 or n_stored == 0:
            return
        dev = self.dev
        ev = dev.program.launch(dev.queue, "scale_pass", n_stored, u32(n_stored), f32(scale), self.ph_pos)
        dev.times.add("trace", [ev])

    def _radii(self) -> tuple:
        """The gathers' radius arguments (spatial_hash.cl: radius, radius_count, bias, alpha,
        steps, own)."""
        return (self.radius, self.radius_count, self.bias, f32(self.integrator.alpha), u32(self.steps), u32(self.own))

    def _set_radii(self, radius: np.ndarray, count: np.ndarray, bias: np.ndarray) -> None:
        """A batch's (or a probe's) starting radius, count N and bias per pixel, float32 (each
        pass counting once until run_batch says otherwise)."""
        r32 = np.ascontiguousarray(radius, np.float32)
        for buf, host in ((self.radius, r32), (self.radius_count, count), (self.bias, bias)):
            cl.enqueue_copy(self.dev.queue, buf, np.ascontiguousarray(host, np.float32))
        self.steps, self.own = 1, 0

    def _build_and_gather(self, n_stored: int, max_radius: float, gather: str | None = None,
                          points: int | None = None) -> None:
        """Build the photon lookup and gather at the first `points` measurement points (all
        pixels by default); a pass's own estimates (the error estimator's per-pass samples)
        divide the flux by the photons per pass (a chain pass's counts are already in uniform
        photons, _scale_pass)."""
        dev, a, p = self.dev, self.dev.arrays, self.dev.program
        n = a.n_pixels if points is None else points
        photons = f32(self.settings.paths_per_pass)
        inv_cell = f32(1.0 / (2.0 * max_radius))  # cell = 2 * largest radius (dissertation 10.2.2)
        if (gather or self.settings.gather) == "stochastic":
            entries = _next_pow2(int(math.ceil(n_stored * self.settings.hash_entries_per_photon)))
            self._reserve_table(entries)
            mask = u32(entries - 1)
            build = [dev.fill(self.tab_key, np.uint64(2 ** 64 - 1), entries),
                     dev.fill(self.tab_count, np.uint32(0), entries),
                     p.launch(dev.queue, "hash_select", n_stored, u32(n_stored), self.ph_pos, self.ph_key,
                              inv_cell, mask, self.tab_key, self.tab_count),
                     p.launch(dev.queue, "hash_store", n_stored, u32(n_stored), self.ph_pos, self.ph_flux,
                              self.ph_dirs, self.ph_key, inv_cell, mask, self.tab_key, self.tab_pos, self.tab_flux,
                              self.tab_dirs)]
            gather_ev = p.launch(dev.queue, "gather_stochastic", n, i32(a.n_pixels), self.mp_pos,
                                 self.mp_nrm, self.mp_wgt, self.mp_cut, *self._radii(), photons, inv_cell, mask,
                                 self.tab_count, self.tab_pos, self.tab_flux, self.tab_dirs, dev.batch_sums)
        else:
            entries = _next_pow2(n_stored)  # cells split GRID_ROW_SPLIT ways along x (spatial_hash.cl, ball_rows)
            self._reserve_table(entries)
            mask = u32(entries - 1)
            build = [dev.fill(self.tab_count, np.uint32(0), entries),
                     p.launch(dev.queue, "grid_count", n_stored, u32(n_stored), self.ph_pos, inv_cell,
                              u32(GRID_ROW_SPLIT), mask, self.tab_count),
                     p.launch(dev.queue, "grid_scan", 1, u32(entries), self.tab_count, self.cell_start,
                              self.cell_fill),
                     p.launch(dev.queue, "grid_scatter_photons", n_stored, u32(n_stored), self.ph_pos, self.ph_flux,
                              self.ph_dirs, self.ph_key, inv_cell, u32(GRID_ROW_SPLIT), mask, self.cell_fill,
                              self.slots),
                     p.launch(dev.queue, "grid_sort_slots", entries, u32(entries), self.cell_start, self.tab_count,
                              self.slots),
                     p.launch(dev.queue, "grid_permute", n_stored, u32(n_stored), self.slots, self.grid_pos,
                              self.grid_flux, self.grid_in, self.grid_nrm)]
            gather_ev = p.launch(dev.queue, "gather_exact", n, i32(a.n_pixels), self.mp_pos, self.mp_nrm,
                                 self.mp_wgt, self.mp_cut, *self._radii(), photons, inv_cell, mask, self.cell_start,
                                 self.tab_count, self.grid_pos, self.grid_flux, self.grid_in, self.grid_nrm,
                                 dev.batch_sums)
        gather_ev.wait()
        dev.times.add("build", build)
        dev.times.add("gather", [gather_ev])

    # -------------------------------------------------------------------- setup
    def pixel_footprint(self) -> tuple[float, int]:
        """The median eye-path length to the first diffuse hit times the pixel's angle, over
        a regular subset of at most PROBE_POINTS pixels (a median needs no more); their
        measurement points stay at the front of the point buffers, and the second value is
        their number."""
        dev, a = self.dev, self.dev.arrays
        n = a.n_pixels
        cl.enqueue_copy(dev.queue, self.radius, np.zeros(n, np.float32))  # radius 0: no disc coverage rays
        points = self._eye_pass(0, stride=-(-n // PROBE_POINTS))
        dist = np.empty(points, np.float32)
        cl.enqueue_copy(dev.queue, dist, self.mp_dist)
        hit = dist > 0.0
        if not hit.any():  # any positive radius serves a camera that sees nothing: one of the scene's size
            # (a scene of no shapes and no lights is the camera's point alone: no size, a unit taken instead)
            return (a.scene_diagonal or 1.0) / max(a.width, a.height), points
        return float(np.median(dist[hit])) * a.pixel_angle, points

    def setup(self) -> dict[str, np.ndarray]:
        """R0 for every pixel: the override, or the larger of R0_FOOTPRINTS pixel footprints
        and the radius that holds R0_PHOTONS photons per pass at the median lit pixel.

        Both are the dissertation's (5.3.1): "the footprint of the pixel", or after the first
        photon pass a k-nearest-photon radius, here made one value for the whole image as in
        its GPU SPPM, since the stochastic hash sizes its cells by the largest radius. The
        footprint alone ignores how many photons a pass brings, and where they are sparse it
        leaves too few in a disc: noise that takes many passes to average. The photon count
        alone shrinks R0 below a pixel where photons are dense, which buys no resolution,
        only noise.

        The density comes from pass 0 itself: its eye pass, its photons, and an exact gather
        at PROBE_FOOTPRINTS pixel footprints (grown until the median lit point holds
        PROBE_MIN_PHOTONS, within PROBE_MAX_SHARE of the scene), both at a regular subset of
        the pixels (pixel_footprint); nothing of it is kept."""
        dev, a = self.dev, self.dev.arrays
        n = a.n_pixels
        if self.settings.initial_radius is not None:
            return {"R0": np.full(n, self.settings.initial_radius)}
        footprint, points = self.pixel_footprint()
        # Every photon counted, first hits too: with nee the radius is the one photons alone
        # would get (sized by the density of the photons that are stored, mostly bounced
        # light, it would be larger and blur the caustics that only photons carry).
        stored = self._photon_pass(0, first_hits=True)
        probe = PROBE_FOOTPRINTS * footprint
        while True:
            # Density: an exact gather of pass 0's photons at the probe radius, at the
            # footprint's pixels only (a median needs no more).
            dev.zero_sums()
            self._set_radii(np.full(points, probe), np.zeros(points), np.zeros(points))  # what the gather reads
            self._build_and_gather(stored, probe, gather="exact", points=points)
            # M / (pi probe^2): photons per unit area per pass (a copy: a view kept would make the
            # next gather sum into a new buffer, Device.batch_sums, and touch fresh memory),
            # at the median lit point
            density = dev.read_sums()["D"][:points].copy()
            lit = density[density > 0.0]
            median = float(np.median(lit)) if len(lit) else 0.0
            if median * math.pi * probe ** 2 >= PROBE_MIN_PHOTONS \
                    or probe * PROBE_GROWTH > PROBE_MAX_SHARE * a.scene_diagonal:
                break
            probe *= PROBE_GROWTH
        dev.times.seconds.clear()  # set-up, not rendering
        r0 = R0_FOOTPRINTS * footprint
        if median > 0.0:  # else no photon reached anything the camera sees
            r0 = max(r0, math.sqrt(R0_PHOTONS / (math.pi * median)))
        return {"R0": np.full(n, r0)}

    # -------------------------------------------------------------------- batch
    def run_batch(self, inputs: GatherInputs, first_pass: int, n_passes: int,
                  keep_going: KeepGoing | None = None) -> Delta:
        """Run passes first_pass .. first_pass+n_passes-1, the first gathering at `inputs.radius`
        (taken back along the radius schedule if the inputs hold later passes, stats.rewind)
        and each next one at the radius the pass before left (shrink_radius, spatial_hash.cl)."""
        dev = self.dev
        n = dev.arrays.n_pixels
        r32 = np.ascontiguousarray(inputs.radius, np.float32)
        if r32.shape != (n,) or not np.all(r32 > 0.0) or not np.all(np.isfinite(r32)):
            raise ValueError("radius must hold one positive finite value per pixel")
        count = np.zeros(n) if inputs.count is None else inputs.count
        bias = np.zeros(n) if inputs.bias is None else inputs.bias
        if inputs.passes is not None and first_pass < inputs.passes:
            # The inputs hold passes after this batch's first: back to where the job's first
            # `first_pass` passes leave the radius (stats.rewind).
            n_factor, r2_factor = stats.rewind(self.integrator.alpha, inputs.passes, first_pass)
            r32 = r32 * np.float32(math.sqrt(r2_factor))
            count, bias = count * n_factor, bias * r2_factor
        self._set_radii(r32, count, bias)
        dev.zero_sums()
        totals = {stats.SCHEDULE: stats.schedule_count(self.integrator.alpha, first_pass, n_passes)}
        for k in range(first_pass, first_pass + n_passes):
            # The job's passes before this one that the inputs lack: the first pass takes the
            # radius rule for them too, any number (shrink_radius's closed form; GatherInputs).
            catch_up = max(0, first_pass - inputs.passes) if k == first_pass and inputs.passes is not None else 0
            self.steps, self.own = 1 + catch_up, catch_up
            chains = inputs.chains
            measuring = chains is not None and chains.measuring and adaptive.measures(k)
            started = self._device_seconds() if measuring else 0.0
            self._eye_pass(k)
            counts = None
            if chains is None or not adaptive.runs_chains(k, chains.measuring):
                self.photons_stored = self._photon_pass(k)
            else:
                self.photons_stored, counts = self._chain_pass(k, chains, float(r32.max()))
                self._scale_pass(self.photons_stored, adaptive.pass_scale(counts, self.settings.paths_per_pass))
            self._build_and_gather(self.photons_stored, float(r32.max()))
            if counts is not None and chains is not None:
                counts.update(adaptive.binned(chains.theta, counts["mutations"], counts["accepted"]))
            if measuring:
                counts = {**(counts or {}), **adaptive.measured(self._device_seconds() - started, counts)}
            for name, value in (counts or {}).items():
                totals[name] = totals.get(name, 0) + value
            if keep_going is not None and not keep_going(k):
                dev.times.settle()
                raise BatchAborted(f"stopped after pass {k}")
        return Delta(first_pass=first_pass, n_passes=n_passes,
                     emitted=n_passes * self.settings.paths_per_pass, sums=dev.read_sums(), counters=totals)

    # -------------------------------------------------------------------- probe
    def gather_photons(self, points: np.ndarray, normals: np.ndarray, radius: np.ndarray, photon_pos: np.ndarray,
                       photon_flux: np.ndarray, photon_dir: np.ndarray,
                       photon_normal: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Gather given photons at given points with the real kernels, no eye or photon pass:
        a probe of the density and Laplacian estimates (e.g. noise-free on a photon grid).
        Needs an engine whose resolution has exactly len(points) pixels; unit weights, the
        whole disc on the point's surface. `photon_normal` is each photon's surface normal
        facing it (default: photon_dir, photons that arrived along their surface's normal)."""
        dev = self.dev
        n, m = dev.arrays.n_pixels, len(photon_pos)
        if len(points) != n:
            raise ValueError(f"this engine gathers at exactly {n} points")
        if m > self.capacity:
            self._reserve_photons(m)

        def f4(a: np.ndarray, w: float = 0.0) -> np.ndarray:
            out = np.zeros((len(a), 4), np.float32)
            out[:, :3] = a
            out[:, 3] = w
            return out

        def packed(dirs: np.ndarray) -> np.ndarray:
            return np.array([_pack_dir(d) for d in dirs], np.uint32)

        dirs = np.stack([packed(photon_dir), packed(photon_dir if photon_normal is None else photon_normal)], axis=1)
        for buf, host in ((self.mp_pos, f4(points, 1.0)), (self.mp_nrm, f4(normals, 1.0)),
                          (self.mp_wgt, f4(np.ones((n, 3)), 1.0)), (self.ph_pos, f4(photon_pos, 1.0)),
                          (self.ph_flux, f4(photon_flux)), (self.ph_dirs, np.ascontiguousarray(dirs)),
                          (self.mp_cut, np.tile(np.array([0xFFFFFFFF, 0xFFFFFFFF, 0, 0], np.uint32), (n, 1)))):
            cl.enqueue_copy(dev.queue, buf, host)
        cl.enqueue_copy(dev.queue, self.ph_key, np.arange(m, dtype=np.uint64))
        self._set_radii(radius, np.zeros(n), np.zeros(n))
        dev.zero_sums()
        self._build_and_gather(m, float(np.max(radius)))
        return dev.read_sums()


def _pack_dir(d: np.ndarray) -> int:
    """Octahedral 2 x 16-bit direction, as pack_dir in kernels/materials.cl (for the probe)."""
    v = np.asarray(d, np.float64) / np.abs(d).sum()
    p = v[:2] if v[2] >= 0 else (1.0 - np.abs(v[[1, 0]])) * np.where(v[:2] >= 0, 1.0, -1.0)
    q = np.clip(np.round((p * 0.5 + 0.5) * 65535.0), 0, 65535).astype(np.uint32)
    return int(q[0] | (q[1] << 16))
