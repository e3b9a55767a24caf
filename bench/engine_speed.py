"""Engine speed: photon paths per second and where a pass spends its time.

For each scene (smallppm at its 1024x768, cornell-caustics at 256x256, or 512x512 with
--full) and each gather mode (stochastic hash, exact grid), one Engine renders one
warm-up pass (excluded), then `passes` passes of `photons_per_pass` photon paths with the
progressive loop (worker/render_loop.py: each pass its own batch at the current radii,
then the merge). Measured over that loop:

- paths_per_second: passes * photons_per_pass / wall-clock seconds of the loop;
- ms_per_pass by stage: eye, trace, build (hash or grid build), gather are device
  seconds from OpenCL profiling events (Engine.times, differenced around the loop);
  readback is the host time of copying the batch sums back and merge the host time of
  the integrator's merge (Engine.times); other is the rest of the wall time (radius
  computation, buffer fills, queue synchronisation, Python);
- wall_ms_per_pass.

Results go to bench/out/engine_speed.json and a stacked-bar chart engine_speed.png.

    python -m bench.engine_speed [--full] [--passes N]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import asdict, dataclass

from bench.common import bench_engine, save_figure, write_json
from worker.render_loop import render
from worker.settings import DEFAULTS

GATHERS = ("stochastic", "exact")
TIMED_STAGES = ("eye", "trace", "build", "gather", "readback", "merge")
CHART_STAGES = TIMED_STAGES + ("other",)
PHOTONS_PER_PASS = DEFAULTS.photons_per_pass  # the engine default, 2^18


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


def chart(results: list[Result]) -> None:
    """Stacked bars of ms per pass by stage, one bar per scene x gather, paths/s on top."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    labels = [f"{r.scene}\n{r.resolution[0]}x{r.resolution[1]}\n{r.gather}" for r in results]
    bottoms = [0.0] * len(results)
    for stage in CHART_STAGES:
        heights = [r.ms_per_pass[stage] for r in results]
        ax.bar(labels, heights, bottom=bottoms, label=stage)
        bottoms = [b + h for b, h in zip(bottoms, heights)]
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
    args = parser.parse_args()
    passes = args.passes or (100 if args.full else 20)
    scenes: dict[str, tuple[int, int] | None] = {
        "smallppm": None,  # its own 1024x768
        "cornell-caustics": (512, 512) if args.full else (256, 256),
    }
    results = []
    for name, resolution in scenes.items():
        for gather in GATHERS:
            r = measure(name, resolution, gather, passes)
            print(f"{name:17s} {gather:10s} {r.paths_per_second / 1e3:7.0f}k paths/s  {r.wall_ms_per_pass:6.0f} ms/pass  "
                  + " ".join(f"{s} {v:.0f}" for s, v in r.ms_per_pass.items()), flush=True)
            results.append(r)
    report = {
        "measured": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine()},
        "full": args.full,
        "alpha": DEFAULTS.alpha,
        "notes": "eye/trace/build/gather: OpenCL device time; readback, merge, other: host time; "
                 "one warm-up pass excluded",
        "results": [asdict(r) for r in results],
    }
    path = write_json("engine_speed", report)
    chart(results)
    print(f"wrote {path} and engine_speed.png")


if __name__ == "__main__":
    main()
