"""Error against time on seven scenes, every method measured in one run on this machine:
SPPM with the exact grid, SPPM with stochastic hashing, PPM (exact grid), SPPM with NEE,
the hybrid integrator's bpt and vcm (all at their default, one path per pixel per pass), and the peer,
Mitsuba 3 (`scalar_rgb`) path tracer and particle tracer, on the same scene converted
automatically (bench/mitsuba_peer.py).

    python -m bench.error_vs_time [--full] [--make-references] [--seconds S] [--scenes A,B] [--methods M,N]

Error: relative RMS per pixel, sqrt(mean(((image - reference) / max(reference, floor))^2))
over all pixels and channels, floor = 5% of the reference's mean (as the error estimator's
policy): every pixel counts by its relative error, so a few bright pixels (a visible lamp)
cannot decide the comparison, and dark ones cannot dominate it. Time: wall clock from the
start, set-up included, for our engine (every pass is a point; one untimed warm-up pass
first, so PoCL compiling the kernels is not counted); each Mitsuba point is a whole render
at 1, 2, 4, ... samples per pixel (its scene loading not counted). References
(bench/reference/<scene>-<W>x<H>.exr, with a JSON sidecar saying how):
a long Mitsuba path-tracing run where path tracing converges (an area light reaches every
path), otherwise a long SPPM run with the exact grid, marked `sppm` (point, spot and
directional lights through glass: paths no unbiased tracer from the camera can sample).
Writes bench/out/error_vs_time.json and one PNG per scene (error_vs_time_full* with --full,
*_methods for a subset of the methods).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bench.common import BENCH_DIR, bench_engine, save_figure, write_json
from bench.make_reference import render as sppm_reference
from bench.mitsuba_peer import render as mitsuba_render
from worker.error_estimate import FLOOR_FRACTION
from worker.image_io import read_image, write_image
from worker.render_loop import render
from worker.scene import bundled_scene_path, load_scene_file

REFERENCES = BENCH_DIR / "reference"
# scene -> how its reference is made: "path" (Mitsuba path tracing converges) or "sppm"
SCENES = {"cornell-box": "path", "cornell-caustics": "path", "gap": "path",
          "directional-caustic": "sppm", "smallppm": "sppm", "glossy": "sppm", "window-sky": "path"}
OURS = {"sppm exact": ("sppm", "exact"), "sppm stochastic": ("sppm", "stochastic"), "ppm exact": ("ppm", "exact"),
        "sppm nee": ("sppm", "exact", "nee"), "bpt": ("bpt", "exact"), "vcm": ("vcm", "exact")}
# (method, gather[, direct]); every method traces its default paths per pass, one per pixel
PEERS = ("mitsuba path", "mitsuba ptracer")
TARGETS = (0.10, 0.05)


def resolution(scene: str, side: int) -> tuple[int, int]:
    w, h = load_scene_file(bundled_scene_path(scene))[0].camera.resolution
    return (side, max(1, round(side * h / w))) if w >= h else (max(1, round(side * w / h)), side)


def reference_path(scene: str, res: tuple[int, int]) -> Path:
    return REFERENCES / f"{scene}-{res[0]}x{res[1]}.exr"


def make_reference(scene: str, res: tuple[int, int], seconds: float) -> None:
    parsed, base = load_scene_file(bundled_scene_path(scene))
    if SCENES[scene] == "path":
        halves = []
        for half in (1, 2):  # two independent halves: half their difference estimates the error
            total, renders, used = np.zeros((res[1], res[0], 3)), 0, 0.0
            while used < seconds / 2:
                img, t = mitsuba_render(parsed, base, res, 256, "path", seed=100_000 * half + renders)
                total, renders, used = total + img, renders + 1, used + t
            halves.append(total / renders)
        a, b = halves
        how = {"method": "mitsuba path tracer (scalar_rgb), independent of photonfarm"}
    else:
        (a, pa), (b, pb) = (sppm_reference(scene, res, 1 << 18, seed, seconds / 2, photon_only=False)
                            for seed in (101, 102))
        how = {"method": "sppm (photonfarm, exact grid): no unbiased method converges here", "passes": [pa, pb]}
    ref = 0.5 * (a + b)
    path = reference_path(scene, res)
    write_image(path, ref)
    own = rel_rms(a, b) / 2  # half the difference of two independent halves
    path.with_suffix(".json").write_text(json.dumps({"scene": scene, "resolution": list(res), **how,
                                                     "seconds": seconds, "own_relative_rms_error": own}, indent=1))
    print(f"reference {path.name}: {how['method']}, own relative RMS error {own:.4f}", flush=True)


def rel_rms(img: np.ndarray, ref: np.ndarray) -> float:
    floor = FLOOR_FRACTION * float(ref.mean())
    return float(np.sqrt(np.mean(((img - ref) / np.maximum(ref, floor)) ** 2)))


def run_ours(scene: str, res: tuple[int, int], ref: np.ndarray, budget: float, method: str, gather: str,
             direct: str = "photons") -> list:
    settings = dict(method=method, gather=gather, direct=direct)  # paths per pass: the default, one per pixel
    # Warm-up, not timed: one pass of the same configuration first, so the clock does not
    # count PoCL compiling the kernels (once per machine and kernel source, then loaded from
    # its cache; a worker pays it once, not per job), and each method's build options differ.
    render(bench_engine(scene, res, seed=6, **settings), passes=1)
    t0 = time.perf_counter()
    eng = bench_engine(scene, res, seed=7, **settings)
    state = eng.start()
    setup = time.perf_counter() - t0
    curve = []

    def observe(st: object, seconds: float) -> None:  # the clock: set-up and rendering, not this
        curve.append((setup + seconds, rel_rms(eng.integrator.image(st).reshape(res[1], res[0], 3), ref)))

    render(eng, seconds=budget - setup, progress=observe, state=state)
    return curve


def run_peer(scene: str, res: tuple[int, int], ref: np.ndarray, integrator: str, budget: float) -> list:
    parsed, base = load_scene_file(bundled_scene_path(scene))
    curve, spp = [], 1
    while True:
        img, seconds = mitsuba_render(parsed, base, res, spp, integrator, seed=7)
        curve.append((seconds, rel_rms(img, ref)))
        if seconds * 2 > budget:  # the next doubling would overrun the budget
            return curve
        spp *= 2


def time_to(curve: list, target: float) -> float | None:
    return next((t for t, e in curve if e <= target), None)


def chart(scene: str, curves: dict[str, list], ref_method: str, ref_error: float, report_name: str) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for name, curve in curves.items():
        if curve:
            ax.loglog(*zip(*curve, strict=True), "-" if name in OURS else "--o", ms=3, label=name)
    for target in TARGETS:
        ax.axhline(target, color="grey", lw=0.6, ls=":")
    # No curve can be measured below the reference's own error (they add in quadrature).
    ax.axhline(ref_error, color="black", lw=0.8, ls="--", label="reference's own error")
    ax.set_xlabel("wall time, s")
    ax.set_ylabel("relative RMS error")
    ax.set_title(f"{scene} (reference: {ref_method})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, f"{report_name}_{scene}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="128-pixel images and 60 s per method")
    parser.add_argument("--make-references", action="store_true")
    parser.add_argument("--reference-seconds", type=float, default=120.0)
    parser.add_argument("--seconds", type=float, help="budget per method (a smoke run; default 12, --full 60)")
    parser.add_argument("--scenes", help="comma-separated subset of the scenes")
    parser.add_argument("--methods", help=f"comma-separated subset of the methods: {', '.join((*OURS, *PEERS))}")
    args = parser.parse_args()
    side, budget = (128, 60.0) if args.full else (64, 12.0)
    budget = args.seconds or budget
    scenes = {name: SCENES[name] for name in args.scenes.split(",")} if args.scenes else SCENES
    methods = args.methods.split(",") if args.methods else [*OURS, *PEERS]
    unknown = sorted(set(methods) - {*OURS, *PEERS})
    if unknown:
        parser.error(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join((*OURS, *PEERS))}")
    # --full and the reduced size keep their own files, and a subset of methods does not
    # overwrite the run of all of them
    report_name = "error_vs_time" + ("_full" if args.full else "") + ("_methods" if args.methods else "")
    report = {"measured": time.strftime("%Y-%m-%d %H:%M:%S"), "budget_seconds": budget,
              "scenes": {}}
    for scene, ref_method in scenes.items():
        res = resolution(scene, side)
        if args.make_references or not reference_path(scene, res).exists():
            make_reference(scene, res, args.reference_seconds)
        ref = read_image(reference_path(scene, res))[..., :3].astype(np.float64)
        curves = {name: run_ours(scene, res, ref, budget, *how) for name, how in OURS.items() if name in methods}
        curves.update({name: run_peer(scene, res, ref, name.split()[1], budget) for name in PEERS if name in methods})
        times = {name: {f"{t:.2f}": time_to(c, t) for t in TARGETS} for name, c in curves.items()}
        peers = [p for p in PEERS if p in curves]
        best_peer = {f"{t:.2f}": min((times[p][f"{t:.2f}"] for p in peers if times[p][f"{t:.2f}"] is not None),
                                     default=None) for t in TARGETS}
        ref_info = json.loads(reference_path(scene, res).with_suffix(".json").read_text())
        report["scenes"][scene] = {"resolution": list(res), "reference": ref_info, "time_to_error": times,
                                   "best_peer": best_peer, "final_error": {n: c[-1][1] for n, c in curves.items() if c},
                                   "curves": curves}
        chart(scene, curves, ref_method, ref_info["own_relative_rms_error"], report_name)
        print(scene, {n: (v["0.10"], v["0.05"]) for n, v in times.items()}, flush=True)
    write_json(report_name, report)


if __name__ == "__main__":
    main()
