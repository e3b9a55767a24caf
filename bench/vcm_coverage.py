"""Coverage of the hybrid methods' error bounds at smooth and at edge pixels (issue 49).

    python -m bench.vcm_coverage [--seeds N] [--size PIXELS]

On the analytic scenes of tests/analytic.py (a spot light's cone edge, a hard shadow, a
checkerboard's texture edges, and point-plane, which has no edge), `vcm` and `bpt` at their
default settings (light subpaths per pass = the pixel count): the share of pixels whose 50%
and 90% bounds hold the actual error, at 16, 64 and 256 passes, over pixels that had a
non-zero sample (`known`), split into edge pixels (within a pixel of a jump in the
analytic image, tests/analytic.edge_pixels) and the rest, pooled over seeds.
Writes bench/out/vcm_coverage.json.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from bench.common import write_json
from tests.analytic import EDGE_CASES, edge_pixels
from worker.engine import Engine
from worker.integrators.connect_merge import hybrid_estimate
from worker.render_loop import render
from worker.scene import bundled_scene_path, load_any_scene
from worker.settings import Settings

PASSES = (16, 64, 256)
CONFIDENCES = (0.5, 0.9)


def engine(case: str, size: int, directory: Path, **settings: object) -> Engine:
    """An engine for `case` at size x size pixels (point-plane: the bundled scene)."""
    scene = EDGE_CASES[case][0]
    path = bundled_scene_path("point-plane")
    if scene is not None:
        path = directory / "scene.json"
        path.write_text(json.dumps(scene((size, size))))
    parsed, base = load_any_scene(path)
    return Engine(parsed, base, Settings(resolution=(size, size), **settings))


def covered_counts(case: str, method: str, size: int, seed: int, directory: Path) -> dict:
    """Per pass count and confidence: [covered, of] for edge and for smooth known pixels."""
    eng = engine(case, size, directory, method=method, seed=seed)
    truth = EDGE_CASES[case][1](eng)
    edge = edge_pixels(truth.reshape(size, size)).ravel()
    counts: dict = {}

    def observe(st: object, _: float) -> None:
        if st.passes in PASSES:
            for confidence in CONFIDENCES:
                est = hybrid_estimate(st, confidence, size)
                held = est.bound >= np.abs(est.luminance - truth)
                for name, pixels in (("edge", est.known & edge), ("smooth", est.known & ~edge)):
                    counts[(st.passes, confidence, name)] = [int(held[pixels].sum()), int(pixels.sum())]

    render(eng, passes=max(PASSES), progress=observe)
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--methods", default="vcm,bpt")
    parser.add_argument("--name", default="vcm_coverage")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in EDGE_CASES:
            for method in args.methods.split(","):
                total: dict = {}
                for seed in range(1, args.seeds + 1):
                    for key, (held, of) in covered_counts(case, method, args.size, seed, Path(tmp)).items():
                        acc = total.setdefault(key, [0, 0])
                        acc[0] += held
                        acc[1] += of
                for (passes, confidence, name), (held, of) in sorted(total.items()):
                    rows.append({"case": case, "method": method, "passes": passes, "confidence": confidence,
                                 "pixels": name, "coverage": held / of if of else None, "count": of})
                    print(rows[-1], flush=True)
    write_json(args.name, {"size": args.size, "seeds": args.seeds, "rows": rows})
    print(table(rows))


def table(rows: list[dict]) -> str:
    """Markdown: a row per case, method and pixel group; the 50% and 90% coverage at each pass count."""
    lines = ["| case | method | pixels | " + " | ".join(f"{c:.0%} at {p}" for c in CONFIDENCES for p in PASSES) + " |",
             "|---" * (3 + len(CONFIDENCES) * len(PASSES)) + "|"]
    groups: dict[tuple[str, str, str], dict] = {}
    for row in rows:
        groups.setdefault((row["case"], row["method"], row["pixels"]), {})[(row["confidence"], row["passes"])] = row
    for (case, method, pixels), cells in groups.items():
        values = [cells[(c, p)]["coverage"] for c in CONFIDENCES for p in PASSES]
        if all(v is None for v in values):
            continue
        lines.append(f"| {case} | {method} | {pixels} | "
                     + " | ".join("-" if v is None else f"{v:.2f}" for v in values) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
