"""Engine speed: photon paths per second and where a pass spends its time.

For each scene (smallppm at its 1024x768, cornell-caustics at 256x256, or 512x512 with
--full) and each gather mode (stochastic hash, exact grid), one Engine renders one
warm-up pass (excluded), then `passes` passes of `photons_per_pass` photon paths, each
pass its own run_batch at the current radii followed by Accumulators.merge, as a
render job does. Measured over that loop:

- paths_per_second: passes * photons_per_pass / wall-clock seconds of the loop;
- ms_per_pass by stage: eye, trace, build (hash or grid build), gather are device
  seconds from OpenCL profiling events (Engine.times, differenced around the loop);
  readback is the host time of copying the batch sums back (Engine.times); merge is
  the host time of Accumulators.merge (perf_counter); other is the rest of the wall
  time (radius computation, buffer fills, queue synchronisation, Python);
- wall_ms_per_pass.

Results go to bench/out/engine_speed.json and a stacked-bar chart engine_speed.png.

    python -m bench.engine_speed [--full] [--passes N]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import asdict, dataclass

from bench.common import OUT_DIR
from worker.engine import Engine, RenderSettings
from worker.scene import bundled_scene_path, load_scene_file
from worker.stats import Accumulators

GATHERS = ("stochastic", "exact")
DEVICE_STAGES = ("eye", "trace", "build", "gather", "readback")
CHART_STAGES = DEVICE_STAGES + ("merge", "other")
PHOTONS_PER_PASS = RenderSettings.photons_per_pass  # the engine default, 2^18
ALPHA = 0.7


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
    scene, base = load_scene_file(bundled_scene_path(scene_name))
    eng = Engine(scene, base, RenderSettings(gather=gather, photons_per_pass=photons_per_pass), resolution)
    acc = Accumulators.start(ALPHA, eng.initial_radius())
    acc.merge(eng.run_batch(acc.radius(), 0, 1))  # warm-up: first launches, buffer growth
    before = dict(eng.times.seconds)
    merge = 0.0
    start = time.perf_counter()
    for k in range(1, passes + 1):
        delta = eng.run_batch(acc.radius(), k, 1)
        t = time.perf_counter()
        acc.merge(delta)
        merge += time.perf_counter() - t
    wall = time.perf_counter() - start
    ms = {s: 1e3 * (eng.times.seconds[s] - before[s]) / passes for s in DEVICE_STAGES}
    ms["merge"] = 1e3 * merge / passes
    ms["other"] = max(0.0, 1e3 * wall / passes - sum(ms.values()))
    return Result(scene=scene_name, resolution=(eng.arrays.width, eng.arrays.height), gather=gather,
                  photons_per_pass=photons_per_pass, passes=passes, wall_seconds=wall,
                  paths_per_second=passes * photons_per_pass / wall, wall_ms_per_pass=1e3 * wall / passes,
                  ms_per_pass=ms, photons_stored_per_pass=eng.photons_stored)


def chart(results: list[Result], path: str) -> None:
    """Stacked bars of ms per pass by stage, one bar per scene x gather, paths/s on top."""
    import matplotlib
    matplotlib.use("Agg")
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
    fig.savefig(path, dpi=120)
    plt.close(fig)


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
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    report = {
        "measured": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine()},
        "full": args.full,
        "alpha": ALPHA,
        "notes": "eye/trace/build/gather: OpenCL device time; readback, merge, other: host time; "
                 "one warm-up pass excluded",
        "results": [asdict(r) for r in results],
    }
    (OUT_DIR / "engine_speed.json").write_text(json.dumps(report, indent=1) + "\n")
    chart(results, str(OUT_DIR / "engine_speed.png"))
    print(f"wrote {OUT_DIR / 'engine_speed.json'} and engine_speed.png")


if __name__ == "__main__":
    main()
