"""The one host wrapper of kernels/*.cl: pick the CPU device, build once, launch.

The program is compiled once per process and context (PoCL caches the binary on disk
as well) and the kernel objects are kept, so launching a pass costs no compilation.
OpenCL state must never cross a fork: create it inside the process that uses it.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("PYOPENCL_NO_CACHE", "1")  # PoCL caches itself; pyopencl's cache double-compiles

import numpy as np
import pyopencl as cl

from kernels.contract import SumLayout, build_options

KERNEL_DIR = Path(__file__).resolve().parent
WORK_GROUP = 64  # work items a work group (Program.launch)
# Order matters: later files use what earlier ones define.
SOURCES = ("rng.cl", "sums.cl", "geometry.cl", "materials.cl", "textures.cl", "bsdf.cl", "environment.cl", "lights.cl",
           "eye_pass.cl", "spatial_hash.cl", "visibility.cl", "photon_pass.cl", "photon_chains.cl")
PREAMBLE = ("#pragma OPENCL EXTENSION cl_khr_fp64 : enable\n"
            "#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable\n")
KERNEL_NAMES = ("eye_pass", "photon_pass", "hash_select", "hash_store", "grid_count", "grid_scan",
                "grid_scatter", "grid_scatter_photons", "grid_sort_slots", "grid_permute", "gather_stochastic",
                "gather_exact", "photon_chains", "scale_pass")
# The programs an integrator names (Integrator.program): its sources and kernels. The
# hybrid integrator (vertex connection and merging) builds on the photon-mapping sources
# (materials, lights, spatial_hash.cl's grid build for its light vertices) with its own.
PROGRAMS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "photon_mapping": (SOURCES, KERNEL_NAMES),
    "hybrid": (SOURCES + ("vcm_lights.cl", "vcm_camera.cl", "vcm_subpath.cl", "vcm_light_pass.cl",
                          "vcm_grid.cl", "vcm_camera_pass.cl", "vcm_finish.cl"),
               ("vcm_light_pass", "vcm_camera_pass", "vcm_finish", "grid_count", "grid_scan", "grid_scatter",
                "grid_sort", "vcm_grid_positions")),
}


PROBE_KERNEL = "kernel void probe(global float* a) { a[get_global_id(0)] = sqrt((float)get_global_id(0)); }"


def create_context() -> cl.Context:
    """A context on the first CPU device that compiles a kernel.

    A PoCL whose LLVM does not know the host CPU lists its device and then fails every
    build ("unknown target CPU 'generic'"); a later platform (Debian's pocl-opencl-icd
    beside the wheel's) may know it, so each CPU device is tried with a one-line kernel.
    """
    failures = []
    for platform in cl.get_platforms():
        for device in platform.get_devices(device_type=cl.device_type.CPU)[:1]:
            ctx = cl.Context([device])
            try:
                cl.Program(ctx, PROBE_KERNEL).build()
            except cl.Error as error:
                lines = [line.strip() for line in str(error).splitlines() if "error:" in line]
                failures.append(f"{platform.name} {device.version}: {lines[0] if lines else 'build failed'}")
                continue
            return ctx
    if failures:
        raise RuntimeError("no OpenCL CPU device compiles kernels here (" + "; ".join(failures)
                           + "); install Debian's pocl-opencl-icd (`make deps`)")
    raise RuntimeError("no OpenCL CPU device found: install pocl-binary-distribution")


class Program:
    """Compiled kernels for one context and one layout of per-pixel sums (the contract of
    kernels/contract.py, handed over as build options), with a launcher."""

    def __init__(self, ctx: cl.Context, layout: SumLayout, sources: tuple[str, ...] = SOURCES,
                 kernel_names: tuple[str, ...] = KERNEL_NAMES) -> None:
        source = PREAMBLE + "\n".join((KERNEL_DIR / name).read_text() for name in sources)
        program = cl.Program(ctx, source).build(options=["-cl-mad-enable", *build_options(layout)])
        self.kernels = {name: getattr(program, name) for name in kernel_names}

    def launch(self, queue: cl.CommandQueue, name: str, n: int, *args: object, one_per_group: bool = False) -> cl.Event:
        """Run kernel `name` over n work items in work groups of WORK_GROUP items, the last
        one padded (kernels bound-check their id); with `one_per_group`, each its own work
        group (few long work items, e.g. Markov chains, then spread over every core).

        The work-group size is fixed because PoCL compiles a kernel anew for every local size
        it is launched with, and left to choose it picks one that divides the global size:
        counts that change from pass to pass (stored photons, hash entries) would then
        compile kernels during rendering, on every worker."""
        local = 1 if one_per_group else WORK_GROUP
        return self.kernels[name](queue, (-(-max(int(n), 1) // local) * local,), (local,), *args)


_programs: dict[tuple[int, SumLayout, str], Program] = {}


def program_for(ctx: cl.Context, layout: SumLayout, name: str = "photon_mapping") -> Program:
    """The process-wide compiled program `name` (PROGRAMS) for `ctx` and `layout`."""
    key = (ctx.int_ptr, layout, name)
    if key not in _programs:
        _programs[key] = Program(ctx, layout, *PROGRAMS[name])
    return _programs[key]


def i32(x: int) -> np.int32:
    return np.int32(x)


def u32(x: int) -> np.uint32:
    return np.uint32(x)


def u64(x: int) -> np.uint64:
    return np.uint64(x)


def f32(x: float) -> np.float32:
    return np.float32(x)
