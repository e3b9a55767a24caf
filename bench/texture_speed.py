"""Texture speed: what a textured scene's pass costs against the same scene in constant colours
(issue 48: at most 1.2x).

    python -m bench.texture_speed [--passes N] [--rounds R] [--resolution W] [--side S]
                                  [--pattern P] [--methods M ...]

cornell-box (its camera at W x W, default 128) in two forms, rendered in the same process:
`constant`, as bundled, and `textured`, every material's albedo (four materials, six walls) an
S x S sRGB bitmap (default 1024, bilinear, repeated 4 times over each wall: every eye, photon
and light-path hit on a wall looks up four texels, at random places in the texels). The
texels (--pattern): `brightness` (default), the constant colour times a random factor
uniform in [0.5, 1.5] a texel (clipped to 1), so that each channel's mean and the mean of the
largest channel, which Russian roulette keeps a path by, stay near the constant's and paths
are as long; `colour`, a factor a channel, whose largest channel is brighter than the
constant's (longer paths: more work that is not the lookups'); `flat`, the constant colour
in every texel, the same paths, so that only the lookups differ. For each method (sppm,
vcm, bpt) both engines render one warm-up pass (excluded), then R rounds, each N passes of
one form and N of the other back to back, the order alternating (so load drifts on the
shared machine fall on both alike), each with the progressive loop (worker/render_loop.py).
Reported per method: the median over rounds of the wall ms per pass of each form and of
their ratio, and of the ratio of the process's CPU time a pass (ms_per_pass). Writes
bench/out/texture_speed.json (texture_speed_S_P.json for another side or pattern).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import write_json
from kernels.program import create_context
from worker.engine import Engine
from worker.images import Pixels
from worker.render_loop import render
from worker.scene import bundled_scene_path, parse_scene
from worker.settings import Settings

METHODS = ("sppm", "vcm", "bpt")
TEXTURE_SIDE = 1024
PATTERNS = ("brightness", "colour", "flat")
REPEATS = 4.0  # the texture's repeats over a wall


def textured(scene: dict, rng: np.random.Generator, side: int = TEXTURE_SIDE, pattern: str = "brightness") -> dict:
    """`scene` with every material's albedo a side x side sRGB bitmap of `pattern` around it
    (the module's docstring)."""
    out = json.loads(json.dumps(scene))
    out["textures"] = {}
    for name, material in out["materials"].items():
        linear = np.clip(np.asarray(material["albedo"]) * texel_factors(pattern, rng, side), 0.0, 1.0)
        srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
        pixels = Pixels.of((srgb * 255.0).round().astype(np.uint8))
        out["textures"][name] = {"type": "bitmap", "pixels": pixels.model_dump(),
                                 "to_uv": [[REPEATS, 0.0, 0.0], [0.0, REPEATS, 0.0]]}
        material["albedo"] = {"texture": name}
    return out


def texel_factors(pattern: str, rng: np.random.Generator, side: int) -> np.ndarray:
    """The factors of a `pattern` texture's texels on the constant colour, (side, side, 1 or 3)."""
    if pattern == "colour":
        return rng.uniform(0.5, 1.5, (side, side, 3))
    if pattern == "brightness":
        return rng.uniform(0.5, 1.5, (side, side, 1))
    return np.ones((side, side, 1))


def ms_per_pass(engine: Engine, passes: int) -> tuple[float, float]:
    """Wall and CPU ms a pass (the CPU time of the whole process, the device's threads
    included: what other work on the machine delays the passes by drops out of it)."""
    wall, cpu = time.perf_counter(), time.process_time()
    render(engine, passes=passes)
    return 1e3 * (time.perf_counter() - wall) / passes, 1e3 * (time.process_time() - cpu) / passes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--passes", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--side", type=int, default=TEXTURE_SIDE, help="the textures' width and height")
    parser.add_argument("--pattern", default=PATTERNS[0], choices=PATTERNS, help="the textures' texels")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    args = parser.parse_args()
    scene = json.loads(bundled_scene_path("cornell-box").read_text())
    forms = {"constant": scene, "textured": textured(scene, np.random.default_rng(1), args.side, args.pattern)}
    ctx = create_context()
    base = Path(tempfile.gettempdir())
    results = []
    for method in args.methods:
        settings = Settings(method=method, seed=3, resolution=(args.resolution, args.resolution))
        engines = {form: Engine(parse_scene(data), base, settings, ctx=ctx) for form, data in forms.items()}
        for engine in engines.values():
            render(engine, passes=1)  # warm-up: first launches, allocations
        times: dict[str, list[float]] = {form: [] for form in forms}
        cpu: dict[str, list[float]] = {form: [] for form in forms}
        for round_ in range(args.rounds):
            for form in sorted(engines, reverse=round_ % 2 == 1):
                wall_ms, cpu_ms = ms_per_pass(engines[form], args.passes)
                times[form].append(wall_ms)
                cpu[form].append(cpu_ms)
        ratios = [t / c for t, c in zip(times["textured"], times["constant"], strict=True)]
        cpu_ratios = [t / c for t, c in zip(cpu["textured"], cpu["constant"], strict=True)]
        row = {"method": method, "constant_ms": statistics.median(times["constant"]),
               "textured_ms": statistics.median(times["textured"]), "ratio": statistics.median(ratios),
               "cpu_ratio": statistics.median(cpu_ratios), "ratios": ratios, "cpu_ratios": cpu_ratios,
               "times": times, "cpu_times": cpu}
        results.append(row)
        print(f"{method}: constant {row['constant_ms']:.1f} ms, textured {row['textured_ms']:.1f} ms a pass, "
              f"ratio {row['ratio']:.3f} (rounds: {', '.join(f'{r:.3f}' for r in ratios)}); "
              f"CPU time ratio {row['cpu_ratio']:.3f}", flush=True)
    default = (args.side, args.pattern) == (TEXTURE_SIDE, PATTERNS[0])
    name = "texture_speed" if default else f"texture_speed_{args.side}_{args.pattern}"
    write_json(name, {"passes": args.passes, "rounds": args.rounds, "resolution": args.resolution,
                      "texture_side": args.side, "pattern": args.pattern, "load": os.getloadavg(),
                      "results": results})


if __name__ == "__main__":
    main()
