"""Engine speed of two work trees side by side: per-stage ms per pass, interleaved runs.

On a shared machine absolute timings drift with the other processes' load; running the
two trees alternately, several times, on the same configuration and comparing them run by
run gives ratios that drift much less. Each run is a subprocess with the tree first on
PYTHONPATH, calling that tree's own `bench.engine_speed.measure` (one warm-up pass, then
`passes` passes of the progressive loop, stages from OpenCL profiling events and host
timers) and also recording the process's CPU seconds. Results go to
bench/out/compare_trees_SCENE_WxH_GATHER.json.

    python -m bench.compare_trees BASE_TREE NEW_TREE [--scene smallppm] [--resolution 1920x1080]
        [--gather exact] [--passes 5] [--repeats 3]

Set POCL_MAX_PTHREAD_COUNT (e.g. 1) to give both trees the same device threads.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import write_json

STAGES = ("eye", "trace", "build", "gather", "readback", "merge", "other")
PER_PIXEL = ("eye", "gather", "readback", "other")  # the stages whose work grows with the pixels

RUN = """
import json, sys, time
from bench.engine_speed import measure
scene, w, h, gather, passes = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], int(sys.argv[5])
cpu0 = time.process_time()
r = measure(scene, (w, h), gather, passes)
print(json.dumps({"wall_ms_per_pass": r.wall_ms_per_pass, "ms_per_pass": r.ms_per_pass,
                  "process_cpu_seconds": time.process_time() - cpu0}))
"""


def run_once(tree: Path, scene: str, resolution: tuple[int, int], gather: str, passes: int) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", RUN, scene, *map(str, resolution), gather, str(passes)],
                         env=env, cwd=tree, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def summary(runs: list[dict], megapixels: float) -> dict:
    """Median per stage over the runs, and the per-pixel stages per megapixel."""
    stages = {s: float(np.median([r["ms_per_pass"][s] for r in runs])) for s in STAGES}
    per_pixel = sum(stages[s] for s in PER_PIXEL)
    return {"ms_per_pass": stages, "wall_ms_per_pass": float(np.median([r["wall_ms_per_pass"] for r in runs])),
            "per_pixel_ms_per_pass": per_pixel, "per_pixel_ms_per_megapixel": per_pixel / megapixels}


def main() -> None:
    parser = argparse.ArgumentParser(description="Engine speed of two work trees, interleaved.")
    parser.add_argument("base", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--scene", default="smallppm")
    parser.add_argument("--resolution", default="1920x1080")
    parser.add_argument("--gather", default="exact")
    parser.add_argument("--passes", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    resolution = tuple(int(v) for v in args.resolution.lower().split("x"))
    megapixels = resolution[0] * resolution[1] / 1e6
    runs: dict[str, list[dict]] = {"base": [], "new": []}
    for k in range(args.repeats):
        for name, tree in (("base", args.base), ("new", args.new)):
            r = run_once(tree.resolve(), args.scene, resolution, args.gather, args.passes)
            runs[name].append(r)
            print(f"run {k} {name}: wall {r['wall_ms_per_pass']:.0f} ms/pass  "
                  + " ".join(f"{s} {r['ms_per_pass'][s]:.0f}" for s in STAGES), flush=True)
    result = {name: summary(rs, megapixels) for name, rs in runs.items()}
    ratios = {s: result["new"]["ms_per_pass"][s] / result["base"]["ms_per_pass"][s]
              for s in STAGES if result["base"]["ms_per_pass"][s] > 0}
    ratios["per_pixel"] = result["new"]["per_pixel_ms_per_pass"] / result["base"]["per_pixel_ms_per_pass"]
    ratios["wall"] = result["new"]["wall_ms_per_pass"] / result["base"]["wall_ms_per_pass"]
    # Run by run (each new run against the base run just before it): the spread of the ratio.
    paired = [n["wall_ms_per_pass"] / b["wall_ms_per_pass"] for b, n in zip(runs["base"], runs["new"], strict=True)]
    report = {"measured": time.strftime("%Y-%m-%d %H:%M:%S"), "trees": {"base": str(args.base), "new": str(args.new)},
              "scene": args.scene, "resolution": resolution, "gather": args.gather, "passes": args.passes,
              "repeats": args.repeats, "pocl_threads": os.environ.get("POCL_MAX_PTHREAD_COUNT"),
              "load_average_at_end": os.getloadavg(), "summary": result, "ratios_new_over_base": ratios,
              "paired_wall_ratios": paired, "runs": runs}
    name = f"compare_trees_{args.scene}_{resolution[0]}x{resolution[1]}_{args.gather}"
    path = write_json(name, report)
    print(json.dumps({"summary": result, "ratios": ratios, "paired_wall_ratios": paired}, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
