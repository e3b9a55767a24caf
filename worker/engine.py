"""The engine: one scene on this process's OpenCL device, rendering batches of passes of
one integrator (worker/integrators/).

The device state (context, compiled program, scene buffers) lives as long as the Engine,
so consecutive batches pay no set-up. A batch sums its passes on the device in float64,
in the integrator's SumLayout (kernels/contract.py), and hands them over without a copy
(Device.read_sums).
"""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyopencl as cl

from kernels.contract import SumLayout
from kernels.program import Program, create_context, f32, i32, program_for
from worker.integrators import integrator_for
from worker.integrators.base import Delta, KeepGoing, Passes, State
from worker.scene import Scene
from worker.scene_arrays import SceneArrays, compile_scene
from worker.settings import Settings


@dataclass
class StageTimes:
    """Seconds spent per stage: device time from OpenCL profiling events, read once the
    events have completed (`settle`, after the pass's own waits), so timing adds no
    synchronisation to a pass."""

    seconds: dict[str, float] = field(default_factory=dict)
    pending: list[tuple[str, cl.Event]] = field(default_factory=list)

    def add(self, stage: str, events: list[cl.Event]) -> None:
        self.pending.extend((stage, e) for e in events)

    def add_seconds(self, stage: str, seconds: float) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds

    def settle(self) -> None:
        for stage, e in self.pending:
            e.wait()  # (done already but for a batch stopped mid-pass: vcm's camera pass may still run)
            self.add_seconds(stage, (e.profile.end - e.profile.start) * 1e-9)
        self.pending.clear()


class Device:
    """The OpenCL side of one scene: context, queue, program, scene buffers, batch sums."""

    def __init__(self, arrays: SceneArrays, layout: SumLayout, ctx: cl.Context | None = None,
                 program: str = "photon_mapping") -> None:
        self.arrays = arrays
        self.layout = layout
        self.ctx = ctx or create_context()
        self.queue = cl.CommandQueue(self.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
        self.program: Program = program_for(self.ctx, layout, program)
        self.times = StageTimes()
        a = arrays
        self.geometry = [self.const(a.tri_v0), self.const(a.tri_e1), self.const(a.tri_e2), self.const(a.tri_nrm),
                         self.const(a.tri_adj), self.const(a.node_lo), self.const(a.node_hi), i32(len(a.node_lo)),
                         self.const(a.spheres), self.const(a.sphere_surf), i32(len(a.spheres)), f32(a.eps_floor),
                         self.const(a.surfaces), self.const(a.tex_info), self.const(a.tex_texels),
                         self.const(a.tex_uv)]
        self.n_emitters = len(a.emitter_cdf) if a.emitters.any() else 0
        self.emitter_args = [self.const(a.emitters), self.const(a.emitter_cdf), i32(self.n_emitters)]
        self.camera = self.const(a.camera)
        self._sums = self.buffer(self._sums_bytes)
        # The mappings of _sums whose arrays were handed out (read_sums): each array's weak
        # reference and its map, which unmaps the buffer when released.
        self._lent: list[tuple[weakref.ref, cl.MemoryMap]] = []

    @property
    def _sums_bytes(self) -> int:
        return 8 * self.layout.stride * self.arrays.n_pixels

    @property
    def batch_sums(self) -> cl.Buffer:
        """The buffer a batch sums into, for the kernels to write: never one that sums handed
        out by read_sums still view. While any of them is referenced (a Delta kept), the
        next batch gets a new buffer and the old one is freed with the last view (its map's
        destructor unmaps it); otherwise the buffer is unmapped and summed into again."""
        if self._lent:
            if any(ref() is not None for ref, _ in self._lent):
                self._sums = self.buffer(self._sums_bytes)
            else:
                for _, mapping in self._lent:
                    mapping.release(self.queue)
            self._lent.clear()
        return self._sums

    def const(self, arr: np.ndarray) -> cl.Buffer:
        arr = np.ascontiguousarray(arr)
        if arr.nbytes == 0:  # OpenCL has no empty buffers
            arr = np.zeros(4, arr.dtype)
        return cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=arr)

    def buffer(self, nbytes: int) -> cl.Buffer:
        return cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, max(nbytes, 4))

    def fill(self, buf: cl.Buffer, value: np.generic, count: int) -> cl.Event:
        return cl.enqueue_fill_buffer(self.queue, buf, np.asarray(value), 0, value.nbytes * count)

    def zero_sums(self) -> None:
        """Start a batch: every per-pixel sum back to zero."""
        self.fill(self.batch_sums, np.float64(0.0), self.layout.stride * self.arrays.n_pixels)

    def read_sums(self) -> dict[str, np.ndarray]:
        """The batch's per-pixel sums split by name: views of the sums buffer mapped into
        host memory, which on PoCL's CPU device is no copy at all (a fresh copy would fault
        in every page, then copy). They stay valid for as
        long as they are referenced, whatever runs next (batch_sums). The readback's time
        starts once the kernels that write the sums have run: an integrator need not wait
        for its last kernel (the hybrid's camera pass), whose time is its own stage's."""
        self.queue.finish()
        t0 = time.perf_counter()
        # The stub types map_flags as an enum; OpenCL's flags are bits, and their union an int.
        read_write: cl.map_flags = cl.map_flags.READ | cl.map_flags.WRITE  # type: ignore[assignment]
        flat, _ = cl.enqueue_map_buffer(self.queue, self._sums, read_write, 0,
                                        (self.arrays.n_pixels * self.layout.stride,), np.dtype(np.float64),
                                        is_blocking=True)
        self._lent.append((weakref.ref(flat), flat.base))  # views of flat keep flat (and its map) alive
        self.times.add_seconds("readback", time.perf_counter() - t0)
        self.times.settle()
        return self.layout.split(flat, self.arrays.n_pixels)


class Engine:
    """Renders batches of passes of one scene with the integrator its settings name."""

    def __init__(self, scene: Scene, base_dir: Path, settings: Settings, ctx: cl.Context | None = None) -> None:
        from worker.integrators.device import passes_for  # the device halves need OpenCL

        settings = settings.for_frame(*(settings.resolution or scene.camera.resolution))
        self.settings = settings
        self.integrator = integrator_for(settings)
        self.arrays: SceneArrays = compile_scene(scene, base_dir, settings.resolution)
        self.device = Device(self.arrays, self.integrator.sums, ctx, self.integrator.program)
        self.passes: Passes = passes_for(self.integrator, self.device)

    @property
    def times(self) -> StageTimes:
        return self.device.times

    def start(self) -> State:
        """An empty job state, its setup arrays (e.g. R0) computed from pass 0."""
        return self.integrator.start(self.passes.setup())

    def run_batch(self, inputs: Any, first_pass: int, n_passes: int, keep_going: KeepGoing | None = None) -> Delta:
        return self.passes.run_batch(inputs, first_pass, n_passes, keep_going)

    def render_batch(self, state: State, first_pass: int, n_passes: int) -> Delta:
        """A batch at the inputs the current state gives (what the progressive loop runs)."""
        return self.run_batch(self.integrator.batch_inputs(state), first_pass, n_passes)
