"""Engine speed: photon paths per second and where a pass spends its time.

For each scene (smallppm at its 1024x768, cornell-caustics at 256x256, or 512x512 with
--full) and each gather mode (stochastic hash, exact grid), one Engine renders one
warm-up pass (excluded), then `passes` passes of `photons_per_pass` photon paths with the
progressive loop (worker/render_loop.py: each pass its own batch at the current radii,
then the merge). Measured over that loop:

- paths_per_second: passes * photons_per_pass / wall-clock seconds of the loop;
- ms_per_pass by stage: eye, trace, build (hash or grid build), gather are device
  seconds from OpenCL profiling events (Engine.times, differenced around the loop);
  readback is the host time of handing the batch sums to the host (Device.read_sums:
  a map of the device buffer, no copy on PoCL's CPU device) and merge the host time of
  the integrator's merge, which reads them (Engine.times); other is the rest of the wall
  time (radius computation, uploads, buffer fills, queue synchronisation, Python);
- wall_ms_per_pass.

The hybrid methods (vcm, bpt) on cornell-box, gap and cornell-caustics at the size of
bench/error_vs_time.py (64 px, or 128 with --full; one light subpath per pixel per pass),
split by stage, ms per pass:

- light trace, splats (the light vertices' connections to the camera), camera trace, NEE,
  connections (to the light subpath's vertices), grid build and merge gather, finish: device
  time. The light and camera kernels do several techniques in one launch, so each pass is
  rendered again with techniques left out (the kernels' `skip` bits, kernels/contract.py
  HYBRID_SKIP: the MIS weights stay the method's) and a technique's time is the difference
  it makes; the variants of a pass run back to back, so load drifts cancel;
- host: the wall time of the progressive loop less its device time (the launches, the
  light-vertex count read back each pass, the batch read back and merged, Python).

Results go to bench/out/engine_speed.json and stacked-bar charts engine_speed.png and
engine_speed_hybrid.png.

    python -m bench.engine_speed [--full] [--passes N] [--only photon|hybrid]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import asdict, dataclass

from bench.common import bench_engine, save_figure, write_json
from bench.error_vs_time import resolution as bench_resolution
from kernels.contract import HYBRID_SKIP
from worker.render_loop import render
from worker.settings import DEFAULTS

GATHERS = ("stochastic", "exact")
TIMED_STAGES = ("eye", "trace", "build", "gather", "readback", "merge")
CHART_STAGES = TIMED_STAGES + ("other",)
PHOTONS_PER_PASS = 1 << 18  # a fixed load, so that per-path costs compare across scenes and frames
HYBRID_METHODS = ("vcm", "bpt")
HYBRID_SCENES = ("cornell-box", "gap", "cornell-caustics")
HYBRID_STAGES = ("light trace", "splats", "camera trace", "nee", "connections", "build", "merge gather", "finish",
                 "host")
# skip masks -> the kernel a variant is timed for: every variant's light and camera time
SKIP_VARIANTS = {
    "none": 0,
    "merge": HYBRID_SKIP["merge"],
    "connect+merge": HYBRID_SKIP["connect"] | HYBRID_SKIP["merge"],
    "all": HYBRID_SKIP["nee"] | HYBRID_SKIP["connect"] | HYBRID_SKIP["merge"] | HYBRID_SKIP["splat"],
}


@dataclass
class Result:
    scene: str
    resolution: tuple[int, int]
    gather: str
    photons_per_pass: int
    passes: int
    wall_seconds: float
    paths_per_second: float
    wall_ms_per_pass: float
    ms_per_pass: dict[str, float]
    photons_stored_per_pass: int  # photon-surface hits stored in the last pass


def measure(scene_name: str, resolution: tuple[int, int] | None, gather: str, passes: int,
            photons_per_pass: int = PHOTONS_PER_PASS) -> Result:
    """Time `passes` passes (after one warm-up pass) of one scene and gather mode."""
    eng = bench_engine(scene_name, resolution, gather=gather, photons_per_pass=photons_per_pass)
    state = render(eng, passes=1)  # warm-up: first launches, buffer growth
    before = dict(eng.times.seconds)
    start = time.perf_counter()
    render(eng, passes=passes + 1, state=state)
    wall = time.perf_counter() - start
    ms = {s: 1e3 * (eng.times.seconds.get(s, 0.0) - before.get(s, 0.0)) / passes for s in TIMED_STAGES}
    ms["other"] = max(0.0, 1e3 * wall / passes - sum(ms.values()))
    return Result(scene=scene_name, resolution=(eng.arrays.width, eng.arrays.height), gather=gather,
                  photons_per_pass=photons_per_pass, passes=passes, wall_seconds=wall,
                  paths_per_second=passes * photons_per_pass / wall, wall_ms_per_pass=1e3 * wall / passes,
                  ms_per_pass=ms, photons_stored_per_pass=eng.passes.photons_stored)


@dataclass
class HybridResult:
    scene: str
    resolution: tuple[int, int]
    method: str
    light_paths_per_pass: int
    passes: int
    wall_ms_per_pass: float
    ms_per_pass: dict[str, float]  # HYBRID_STAGES
    light_vertices_per_pass: int  # stored in the last pass


def measure_hybrid(scene_name: str, res: tuple[int, int], method: str, passes: int) -> HybridResult:
    """Time `passes` passes of the progressive loop (after one warm-up pass), then split the
    device time by technique from the same passes rendered with techniques skipped."""
    n_light = res[0] * res[1]
    eng = bench_engine(scene_name, res, method=method, photons_per_pass=n_light)
    times, cmp = eng.times.seconds, eng.passes
    state = render(eng, passes=1)
    device = ("light", "build", "camera", "finish")
    before = {s: times.get(s, 0.0) for s in device}
    start = time.perf_counter()
    render(eng, passes=passes + 1, state=state)
    wall = time.perf_counter() - start
    device_ms = sum(1e3 * (times.get(s, 0.0) - before[s]) for s in device) / passes
    # The split: each pass once per skip variant, back to back.
    r0 = eng.integrator.batch_inputs(state)
    split = {name: {"light": 0.0, "camera": 0.0, "build": 0.0, "finish": 0.0} for name in SKIP_VARIANTS}
    for k in range(1, passes + 1):
        for name, mask in SKIP_VARIANTS.items():
            cmp.skip = mask
            t0 = {s: times.get(s, 0.0) for s in split[name]}
            eng.run_batch(r0, k, 1)
            for s in split[name]:
                split[name][s] += 1e3 * (times.get(s, 0.0) - t0[s]) / passes
    cmp.skip = 0
    full, no_merge, no_connect, bare = (split[v] for v in SKIP_VARIANTS)
    ms = {"light trace": bare["light"], "splats": full["light"] - bare["light"],
          "camera trace": bare["camera"], "nee": no_connect["camera"] - bare["camera"],
          "connections": no_merge["camera"] - no_connect["camera"], "build": full["build"],
          "merge gather": full["camera"] - no_merge["camera"], "finish": full["finish"],
          "host": 1e3 * wall / passes - device_ms}
    return HybridResult(scene=scene_name, resolution=res, method=method, light_paths_per_pass=n_light, passes=passes,
                        wall_ms_per_pass=1e3 * wall / passes, ms_per_pass=ms,
                        light_vertices_per_pass=cmp.vertices_stored)


def chart_hybrid(results: list[HybridResult]) -> None:
    """Stacked bars of ms per pass by stage, one bar per scene x method (negative
    differences, noise, drawn as zero)."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5))
    labels = [f"{r.scene}\n{r.resolution[0]}x{r.resolution[1]}\n{r.method}" for r in results]
    bottoms = [0.0] * len(results)
    for stage in HYBRID_STAGES:
        heights = [max(0.0, r.ms_per_pass[stage]) for r in results]
        ax.bar(labels, heights, bottom=bottoms, label=stage)
        bottoms = [b + h for b, h in zip(bottoms, heights, strict=True)]
    ax.set_ylabel("ms per pass (one light subpath per pixel)")
    ax.set_title("photonfarm hybrid methods: time per pass by stage")
    ax.set_ylim(0, 1.15 * max(bottoms))
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    save_figure(fig, "engine_speed_hybrid")


def chart(results: list[Result]) -> None:
    """Stacked bars of ms per pass by stage, one bar per scene x gather, paths/s on top."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    labels = [f"{r.scene}\n{r.resolution[0]}x{r.resolution[1]}\n{r.gather}" for r in results]
    bottoms = [0.0] * len(results)
    for stage in CHART_STAGES:
        heights = [r.ms_per_pass[stage] for r in results]
        ax.bar(labels, heights, bottom=bottoms, label=stage)
        bottoms = [b + h for b, h in zip(bottoms, heights, strict=True)]
    for i, r in enumerate(results):
        ax.annotate(f"{r.paths_per_second / 1e3:.0f}k paths/s", (i, r.wall_ms_per_pass), ha="center",
                    va="bottom", xytext=(0, 3), textcoords="offset points")
    ax.set_ylabel(f"ms per pass ({results[0].photons_per_pass} photon paths)")
    ax.set_title("photonfarm engine: time per pass by stage")
    ax.set_ylim(0, 1.15 * max(bottoms))
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    save_figure(fig, "engine_speed")


def main() -> None:
    parser = argparse.ArgumentParser(description="Engine speed: paths/s and per-stage time per pass.")
    parser.add_argument("--full", action="store_true", help="more passes, cornell-caustics at 512x512")
    parser.add_argument("--passes", type=int, help="measured passes per configuration (default 20, --full 100)")
    parser.add_argument("--only", choices=("photon", "hybrid"), help="only the photon-mapping or the hybrid runs")
    args = parser.parse_args()
    passes = args.passes or (100 if args.full else 20)
    scenes: dict[str, tuple[int, int] | None] = {
        "smallppm": None,  # its own 1024x768
        "cornell-caustics": (512, 512) if args.full else (256, 256),
    }
    results = []
    for name, resolution in scenes.items() if args.only != "hybrid" else ():
        for gather in GATHERS:
            r = measure(name, resolution, gather, passes)
            print(f"{name:17s} {gather:10s} {r.paths_per_second / 1e3:7.0f}k paths/s  "
                  f"{r.wall_ms_per_pass:6.0f} ms/pass  "
                  + " ".join(f"{s} {v:.0f}" for s, v in r.ms_per_pass.items()), flush=True)
            results.append(r)
    hybrid = []
    for name in HYBRID_SCENES if args.only != "photon" else ():
        for method in HYBRID_METHODS:
            h = measure_hybrid(name, bench_resolution(name, 128 if args.full else 64), method, passes)
            print(f"{name:17s} {method:4s} {h.wall_ms_per_pass:6.1f} ms/pass  "
                  + " ".join(f"{s} {v:.1f}" for s, v in h.ms_per_pass.items()), flush=True)
            hybrid.append(h)
    report = {
        "measured": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine()},
        "full": args.full,
        "alpha": DEFAULTS.alpha,
        "notes": "eye/trace/build/gather: OpenCL device time; readback, merge, other: host time; "
                 "one warm-up pass excluded; hybrid: device time by technique from passes re-rendered with "
                 "techniques skipped, host = wall less device time",
        "results": [asdict(r) for r in results],
        "hybrid": [asdict(h) for h in hybrid],
    }
    path = write_json("engine_speed", report)
    if results:
        chart(results)
    if hybrid:
        chart_hybrid(hybrid)
    print(f"wrote {path} and engine_speed.png")


if __name__ == "__main__":
    main()
