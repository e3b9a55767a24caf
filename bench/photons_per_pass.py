"""SPPM's photons per pass against its error at equal wall time: the default (one photon per
pixel, worker/settings.py) among fixed counts, every count in one run, repetitions
interleaved.

    python -m bench.photons_per_pass [--seconds S] [--reps N] [--cases cornell-box:64,cornell-box:128,...]

Error: bench/error_vs_time.py's relative RMS against its reference (bench/reference). Each
run renders for S seconds of wall clock after an untimed warm-up pass (the kernels' build).
Writes bench/out/photons_per_pass.json and prints a Markdown table of the median errors.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench.common import bench_engine, write_json
from bench.error_vs_time import reference_path, rel_rms
from worker.image_io import read_image
from worker.render_loop import render

COUNTS = (None, 1 << 14, 1 << 16, 1 << 18)  # None: the default for the frame
CASES = ("cornell-box:64", "cornell-box:128", "cornell-caustics:64")


def run(scene: str, side: int, photons: int | None, seconds: float, seed: int) -> dict:
    """Error after `seconds` of rendering, and the passes that took."""
    ref = read_image(reference_path(scene, (side, side))).reshape(side, side, 3)
    render(bench_engine(scene, (side, side), seed=seed + 1000, photons_per_pass=photons), passes=1)  # warm-up
    eng = bench_engine(scene, (side, side), seed=seed, photons_per_pass=photons)
    state = render(eng, seconds=seconds)
    image = eng.integrator.image(state).reshape(side, side, 3)
    return {"error": rel_rms(image, ref), "passes": state.passes, "photons_per_pass": eng.settings.paths_per_pass}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--reps", type=int, default=2)
    parser.add_argument("--cases", default=",".join(CASES))
    args = parser.parse_args()
    rows = []
    for case in args.cases.split(","):
        scene, side = case.split(":")
        results: dict[str, list[dict]] = {}
        for rep in range(args.reps):
            for photons in COUNTS:
                label = "default" if photons is None else f"2^{photons.bit_length() - 1}"
                results.setdefault(label, []).append(run(scene, int(side), photons, args.seconds, 7 + rep))
        rows.append({"scene": scene, "side": int(side), "results": results})
    load = os.getloadavg()[0]
    write_json("photons_per_pass", {"seconds": args.seconds, "load": load, "time": time.time(), "rows": rows})
    labels = ["default"] + [f"2^{p.bit_length() - 1}" for p in COUNTS if p is not None]
    print(f"| scene | px | {' | '.join(labels)} |\n|---|---|" + "---|" * len(labels))
    for row in rows:
        cells = []
        for label in labels:
            runs = row["results"][label]
            cells.append(f"{np.median([r['error'] for r in runs]):.3f} ({int(np.median([r['passes'] for r in runs]))})")
        print(f"| {row['scene']} | {row['side']} | {' | '.join(cells)} |")
    print(f"load average at the end: {load:.1f}")


if __name__ == "__main__":
    main()
